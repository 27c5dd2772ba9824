"""Two copies of a phase pattern in one pixel, taken apart: the direct light's code where a mirror adds a second.

Where a mirror-like face reflects the projector onto another surface, that surface's pixels see the pattern
twice: directly (code ``u1``) and through the mirror, from a virtual projector (code ``u2``). The decoder's
blend check finds such pixels (several fine Gray bits with the contrast of a difference of two lights) and
drops them (reason ``INTERREFLECTION``). With two or more phase sets per axis whose periods divide the
coarsest (the default sequence's [16, 8]), the two copies can be told apart:

1. per pixel (of a :data:`LATTICE_PX` lattice), a grid search over (u1, u2) fits the sums of every phase set and
   white - black to two copies (amplitudes by least squares; the direct copy the stronger):
   ``W_s = k_s A e^(i 2 pi u1 / P_s) + c_s e^(i 2 pi u2 / P_s)``, ``r = A + B``, with ``k_s`` the clean pixels'
   modulation share of set ``s``. Alone this is too imprecise: where the two codes coincide modulo a period
   nothing tells them apart (on issue 25's mirror groove 8.7 % of the pixels > 0.5 px off, with the Gray
   contrasts in the fit too).
2. A planar mirror makes the second copy's code a smooth function of the pixel, like the first: a robust plane
   through the per-pixel ``u2`` (modulo the coarsest period) over a window of :data:`RADIUS` pixels replaces it.
3. The second copy's complex modulation per set (its share of the light, and any phase its light carries beyond
   its code: the mirror's blur) is the window's median of what the fit leaves.
4. Taken off each set's sums, what is left is the direct copy alone: its code in closed form, unwrapped from the
   decoder's code of the blend through the sets, coarse to fine.

Which copy is direct: light straight from the projector keeps the scene's orientation of the code (the sign of
du/dx with one coded axis, of the Jacobian d(u, v)/d(x, y) with both), one mirror reverses it. A pixel is taken
apart only where the stronger copy keeps it and the other reverses it: where the camera sees a lit surface in
the mirror the stronger copy is that reflection, and nothing is taken apart.

A pixel gets its code back only where the window's plane holds (at least :data:`MIN_INLIERS` of its pixels
within 2.5 robust scales, the scale at most :data:`MAX_SCALE_PX`), the finest set agrees with the one before
within a quarter of its period, and the code stays within :data:`SPAN_PX` of the blend's. Decoded pixels amid
such a region (:data:`AMID_SHARE`; the copies' fine bits agreed by chance, the phase is pulled) go with it; a
second pass takes the decoded pixels within :data:`NEAR_PX` of the separated ones (the band along a mirror's
corner line, where the copies nearly coincide) from the separated pixels' planes, where the light is more
consistent as two copies (:data:`EVIDENCE`, :data:`MIN_SPREAD`) or the direct code continues the separated
ones' (:data:`ON_PLANE_PX`). The sigma gains the variance :data:`SEPARATED_VAR_PX2` per unit of the second
copy's relative strength (``DecodedMaps.separated``); the reconstruction counts the separated pixels as
reflection evidence (the visibility and walled-region checks).

Measured on the mirror groove (480 x 384, the matte face lit directly and through a mirror of reflectance 0.6,
the copies 1.7-2.1 : 1): 26.3 k of the face's 27.8 k lit pixels separated, median error 0.058 px, p99 0.26 px,
max 0.45 px; none on the mirror; the scene 69.8 -> 84.8 % complete (85.8 % since the image's border keeps its
points), 0.012 % of the points > 1 mm. Cost there:
decode 5 -> 265 ms (the per-pixel fit 110 ms, planes and terms 105 ms); a scene without such a region pays
nothing (fewer than :data:`MIN_REGION_SHARE` of the image in the blend check's regions: skipped).

Both decoders call this with the same sums (the batch one gathers them from the stack with the same integer
coefficients the streaming one accumulates), so the outputs stay identical.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.reconstruct import _ghost_kernels as _g
from appliance.reconstruct.decode_plan import DecodePlan
from appliance.reconstruct.types import DecodedMaps

RADIUS = 10
"""Half-width (px) of the window over which the second copy's code is a plane."""

MIN_INLIERS = 0.5
"""Share of a window's pixels that must lie within 2.5 robust scales of its plane."""

MAX_SCALE_PX = 0.75
"""Largest robust scale (projector px) of the per-pixel second-copy codes around their plane."""

SPAN_PX = 2.0
"""How far (projector px) the direct copy's code may lie from the blend's (a second copy half as strong pulls
the finest set's phase by at most 30 degrees)."""

SEPARATED_VAR_PX2 = 0.02
"""Code variance (projector px^2) a separated pixel's sigma gains per unit of the second copy's strength
relative to the first (B / A): the spread the plane and the median leave (measured on the mirror groove:
errors of RMS 0.08 px at B / A 0.5)."""

NODE_PX = 4
"""Spacing (px) of the nodes where the planes and the second copy's terms are computed."""

LATTICE_PX = 2
"""Spacing (px) of the pixels whose per-pixel fit feeds the planes (every pixel would cost 9x the time, for
planes as good)."""

AMID_SHARE = 0.5
"""A decoded pixel at least this share of whose window the blend check's regions cover is separated too."""

NEAR_PX = 6
"""The second pass looks at decoded pixels this close (px, a square) to separated ones: farther, the planes
extrapolate too far (on the mirror groove's corner band 8-10 px away 4 % of them > 0.5 px off, 0-6 px none)."""

MIN_SPREAD = 0.2
"""... and only when that spread before is at least this: a clean pixel's levels spread by 0.05-0.2 (blur that
varies with the code's local slope), a pixel lit by two copies half as strong as each other by up to 1.1.
Measured beside the mirror groove's matte face: 7 background pixels passed without it, none with it."""

ON_PLANE_PX = 0.3
"""... and takes one whose light is not more consistent as two copies when its direct code continues the
separated pixels' direct codes (their plane at its node) within this (projector px): where the two copies
coincide, the light is as consistent as one copy's. A pixel of another surface (the code jumps) does not."""

EVIDENCE = 0.5
"""A decoded pixel next to separated ones is taken apart when taking the second copy off makes its light
consistent: the spread (ln max / min) of its direct light's level in white - black and in each set's modulation
falls under this share of the spread before (a pixel lit once has none to lose)."""

MIN_REGION_PX = 100
MIN_REGION_SHARE = 1e-3
"""The blend check's pixels must number at least these (and this share of the image) for a separation: a
normal scene's stray marks stay near 1e-4 of the image (the bench's 2 x 5 MP scene: 7e-5), a mirror-like face
gives percents (the mirror groove: 18 %); a window's plane needs tens of them."""

MIN_SAMPLES = 200
"""Decoded pixels needed to measure the clean modulation share of every phase set."""

_SAMPLE_TARGET = 20_000
_PRIOR = 6.0
"""Weight of the prior that the second copy's modulation share is the first's (see ``init_fit``)."""

Sums = Callable[[int, npt.NDArray[np.int64], npt.NDArray[np.int64]], tuple[npt.NDArray[np.float64],
                                                                          npt.NDArray[np.float64]]]
"""``sums(set, rows, cols) -> (S, C)``: a phase set's sums at pixels, as the decoder formed them (real units)."""


def _axis_sets(plan: DecodePlan, axis: str) -> list[int] | None:
    """The phase sets of an axis, coarse to fine, when two copies can be taken apart with them: at least two,
    integer periods, each dividing the coarsest."""
    sets = [s for s, p in enumerate(plan.phase) if p.axis == axis]
    if len(sets) < 2:
        return None
    periods = [plan.phase[s].period for s in sets]
    p0 = periods[0]
    if any(p != round(p) or p <= 0 or p > p0 or round(p0) % round(p) != 0 for p in periods):
        return None
    return sets


def _complex(sums: Sums, sets: list[int], ys: npt.NDArray[np.int64], xs: npt.NDArray[np.int64]) -> tuple[
        npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(re, im) (S, N) of ``C - i S`` per set: the complex number whose angle is 2 pi u / P."""
    re = np.empty((len(sets), len(ys)))
    im = np.empty((len(sets), len(ys)))
    for j, s in enumerate(sets):
        sv, cv = sums(s, ys, xs)
        re[j] = cv
        im[j] = -sv
    return re, im


@dataclass
class _Axis:
    """One coded axis' inputs: its phase sets, their periods and clean modulation shares and the decoded map."""

    index: int
    sets: list[int]
    periods: npt.NDArray[np.float64]
    k: npt.NDArray[np.float64]
    decoded: npt.NDArray[np.float32]
    flag: int


@dataclass
class _Pass:
    """One axis' result over a pixel list."""

    accepted: npt.NDArray[np.bool_]
    direct: npt.NDArray[np.float64]
    second: npt.NDArray[np.float64]
    mods: npt.NDArray[np.float64]
    strength: npt.NDArray[np.float64]
    consistent: npt.NDArray[np.bool_]
    off_plane: npt.NDArray[np.float64]
    slopes1: npt.NDArray[np.float64]
    slopes2: npt.NDArray[np.float64]


def separate(
    out: DecodedMaps,
    v_arg: npt.NDArray[np.float32],
    codes: npt.NDArray[np.float32],
    plan: DecodePlan,
    sums: Sums,
    hi: npt.NDArray[np.generic],
    lo: npt.NDArray[np.generic],
    clip: npt.NDArray[np.uint8],
) -> int:
    """Give the pixels of the blend check's regions their direct code back where two copies of the pattern
    can be taken apart (see the module's text). Decoded pixels amid such a region (where the copies' fine bits
    happen to agree, so the check passed them, but the phase is pulled) are taken apart with them; decoded
    pixels next to the separated ones (the band along a mirror's corner line where the copies nearly coincide)
    in a second pass from the separated pixels' planes, where taking the second copy off makes their light
    consistent.

    Parameters
    ----------
    out : DecodedMaps
        The decode, after the blend check undecoded its regions (``reason`` 1 there); the separated pixels get
        their code, mask, quality (DN), fringe share, levels 0 and reason 0, and ``out.separated`` lists them.
    v_arg : ndarray, shape (H, W) or (0, W), float32
        The v map the decoder writes (no rows: the y axis is not coded).
    codes : ndarray, shape (N, 4), float32
        The blend check's pixels (row, column, u, v of the stronger copy), row-major; separated ones get their
        new codes.
    plan : DecodePlan
        What was decoded.
    sums : callable
        A phase set's sums at pixels (see :data:`Sums`).
    hi, lo : ndarray, shape (H, W)
        White and black (or the stack's max and min) images.
    clip : ndarray, shape (H, W), uint8
        The decoder's clipped-sample flags: a pixel with a clipped phase sample is not separated.

    Returns
    -------
    int
        The pixels given their code back or corrected.
    """
    out.separated = None
    if out.reason is None or out.levels is None or out.fringe is None:
        return 0
    if len(codes) < max(MIN_REGION_PX, MIN_REGION_SHARE * out.mask.size):  # stray marks: no plane to fit
        return 0
    got = _axes(out, v_arg, plan, sums, hi, lo)
    if got is None:
        return 0
    axes, orient = got
    shape = out.mask.shape
    nreg = len(codes)
    ye, xe = _amid(codes, out.mask)
    ys = np.concatenate([codes[:, 0].astype(np.int64), ye])
    xs = np.concatenate([codes[:, 1].astype(np.int64), xe])
    coarse = [np.concatenate([codes[:, 2 + ax.index].astype(np.float64), ax.decoded[ye, xe].astype(np.float64)])
              for ax in axes]  # fmt: skip
    first, r = _run(axes, shape, ys, xs, coarse, sums, hi, lo, clip, nreg, None)
    accepted = np.logical_and.reduce([p.accepted for p in first]) & _oriented(axes, first, orient)
    sep = [_write(out, v_arg, codes, plan, axes, ys, xs, first, accepted, r, nreg)]
    # the second pass: decoded pixels next to the separated ones, judged by the separated pixels' planes
    seeds = np.flatnonzero(accepted)
    yn, xn = _near(ys[seeds], xs[seeds], out.mask, ys, xs)
    if len(seeds) and len(yn):
        ys2 = np.concatenate([ys[seeds], yn])
        xs2 = np.concatenate([xs[seeds], xn])
        coarse2 = [np.concatenate([p.direct[seeds], ax.decoded[yn, xn].astype(np.float64)])
                   for p, ax in zip(first, axes, strict=True)]  # fmt: skip
        known = [(p.direct[seeds], p.second[seeds]) for p in first]
        second, r2 = _run(axes, shape, ys2, xs2, coarse2, sums, hi, lo, clip, len(seeds), known)
        near = (np.logical_and.reduce([p.accepted & (p.consistent | (p.off_plane <= ON_PLANE_PX)) for p in second])
                & _oriented(axes, second, orient))[len(seeds):]  # fmt: skip
        tail = [_tail(p, len(seeds)) for p in second]
        sep.append(_write(out, v_arg, codes, plan, axes, yn, xn, tail, near, r2[len(seeds):], 0))
    sep = [a for a in sep if len(a)]
    if not sep:
        return 0
    allsep = np.concatenate(sep)
    order = np.argsort(allsep[:, 0].astype(np.int64) * shape[1] + allsep[:, 1].astype(np.int64), kind="stable")
    out.separated = np.ascontiguousarray(allsep[order])
    return len(allsep)


def _axes(out: DecodedMaps, v_arg: npt.NDArray[np.float32], plan: DecodePlan, sums: Sums,
          hi: npt.NDArray[np.generic], lo: npt.NDArray[np.generic]) -> tuple[list[_Axis], int] | None:
    """The coded axes, when every one can be taken apart (two or more phase sets whose periods divide the
    coarsest, enough decoded pixels to measure their modulation shares, a clear orientation), and the scene's
    orientation of the code (see :func:`_orientation`)."""
    names = [a for a in ("x", "y") if a in plan.axes]
    if not names:
        return None
    sample = _sample(out.mask)
    if len(sample[0]) < MIN_SAMPLES:
        return None
    rs = _range(hi, lo, *sample)
    keep = rs > 0
    sample, rs = (sample[0][keep], sample[1][keep]), rs[keep]
    if len(rs) < MIN_SAMPLES:
        return None
    axes: list[_Axis] = []
    for a in names:
        sets = _axis_sets(plan, a)
        if sets is None:
            return None
        ai = 0 if a == "x" else 1
        decoded = out.u if a == "x" else v_arg
        sre, sim = _complex(sums, sets, sample[0], sample[1])
        k = np.median(np.hypot(sre, sim) / rs, axis=1)
        if not np.all(k > 0.05):
            return None
        axes.append(_Axis(ai, sets, np.array([plan.phase[s].period for s in sets], np.float64), k, decoded,
                          1 if a == "x" else 2))  # fmt: skip
    orient = _orientation([ax.decoded for ax in axes], [ax.index for ax in axes], out.mask, sample)
    return (axes, orient) if orient != 0 else None


def _run(axes: list[_Axis], shape: tuple[int, int], ys: npt.NDArray[np.int64], xs: npt.NDArray[np.int64],
         coarse: list[npt.NDArray[np.float64]], sums: Sums, hi: npt.NDArray[np.generic], lo: npt.NDArray[np.generic],
         clip: npt.NDArray[np.uint8], members: int,
         known: list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]] | None) -> tuple[
        list[_Pass], npt.NDArray[np.float64]]:
    """Every axis over one pixel list (the first ``members`` make the planes; ``known``: their codes are known);
    and the pixels' white - black."""
    r = _range(hi, lo, ys, xs)
    flags = clip[ys, xs]
    out: list[_Pass] = []
    for j, ax in enumerate(axes):
        cand = (r > 0) & ((flags & ax.flag) == 0) & np.isfinite(coarse[j])
        wre, wim = _complex(sums, ax.sets, ys, xs)
        out.append(_axis(shape, ys, xs, np.where(np.isfinite(coarse[j]), coarse[j], 0.0), r, wre, wim, ax, cand,
                         members, None if known is None else known[j]))  # fmt: skip
    return out, r


def _tail(p: _Pass, start: int) -> _Pass:
    """The entries of a pass from ``start`` on."""
    return _Pass(p.accepted[start:], p.direct[start:], p.second[start:], p.mods[:, start:], p.strength[start:],
                 p.consistent[start:], p.off_plane[start:], p.slopes1[start:], p.slopes2[start:])  # fmt: skip


def _write(out: DecodedMaps, v_arg: npt.NDArray[np.float32], codes: npt.NDArray[np.float32], plan: DecodePlan,
           axes: list[_Axis], ys: npt.NDArray[np.int64], xs: npt.NDArray[np.int64], res: list[_Pass],
           accepted: npt.NDArray[np.bool_], r: npt.NDArray[np.float64], ncodes: int) -> npt.NDArray[np.float32]:
    """The accepted pixels' codes, mask, quality, fringe share, levels and reason into the maps (and the first
    ``ncodes`` entries' into ``codes``; ``r`` every pixel's white - black); returns their (N, 3) row, column and
    code variance (px^2) for ``DecodedMaps.separated``."""
    assert out.levels is not None and out.reason is not None and out.fringe is not None
    idx = np.flatnonzero(accepted)
    yy, xx = ys[idx], xs[idx]
    quality = np.full(len(idx), np.inf)
    rho = np.zeros(len(idx))
    for ax, p in zip(axes, res, strict=True):
        target = out.u if ax.index == 0 else v_arg
        target[yy, xx] = p.direct[idx].astype(np.float32)
        reg = idx[idx < ncodes]
        codes[reg, 2 + ax.index] = p.direct[reg].astype(np.float32)
        for j, s in enumerate(ax.sets):
            quality = np.minimum(quality, 4.0 / plan.phase[s].steps * p.mods[j, idx])
        rho = np.maximum(rho, p.strength[idx])
    out.mask[yy, xx] = True
    out.quality[yy, xx] = quality.astype(np.float32)
    direct = r[idx] / (1.0 + rho)
    out.fringe[yy, xx] = np.minimum(100.0 * quality / np.maximum(direct, 1e-9) + 0.5, 255.0).astype(np.uint8)
    out.levels[:, yy, xx] = 0
    out.reason[yy, xx] = 0
    return np.stack([yy.astype(np.float32), xx.astype(np.float32), (SEPARATED_VAR_PX2 * rho).astype(np.float32)],
                    axis=1)  # fmt: skip


def _near(sy: npt.NDArray[np.int64], sx: npt.NDArray[np.int64], mask: npt.NDArray[np.bool_],
          ys: npt.NDArray[np.int64], xs: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Decoded pixels within :data:`NEAR_PX` of the separated ones (sy, sx), not among (ys, xs)."""
    h, w = mask.shape
    sep = np.zeros((h + 1, w + 1), np.int64)
    sep[sy + 1, sx + 1] = 1
    count = _box(sep.cumsum(0).cumsum(1), h, w, NEAR_PX)[0]
    free = mask.copy()
    free[ys, xs] = False
    yy, xx = np.nonzero(free & (count > 0))
    return yy.astype(np.int64), xx.astype(np.int64)


def _box(integral: npt.NDArray[np.int64], h: int, w: int, radius: int) -> tuple[
        npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(count, area) of a (2 radius + 1)^2 box around every pixel from an (H + 1, W + 1) integral image."""
    y0 = np.clip(np.arange(h) - radius, 0, h)
    y1 = np.clip(np.arange(h) + radius + 1, 0, h)
    x0 = np.clip(np.arange(w) - radius, 0, w)
    x1 = np.clip(np.arange(w) + radius + 1, 0, w)
    count = integral[y1][:, x1] - integral[y0][:, x1] - integral[y1][:, x0] + integral[y0][:, x0]
    area = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    return count, area


def _range(hi: npt.NDArray[np.generic], lo: npt.NDArray[np.generic], ys: npt.NDArray[np.int64],
           xs: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
    """white - black (DN) at pixels."""
    return hi[ys, xs].astype(np.float64) - lo[ys, xs].astype(np.float64)


def _amid(codes: npt.NDArray[np.float32], mask: npt.NDArray[np.bool_]) -> tuple[
        npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Decoded pixels at least :data:`AMID_SHARE` of whose window (radius :data:`RADIUS`) the blend check's
    regions cover: lit by the same two copies, their fine bits agreeing by chance."""
    h, w = mask.shape
    reg = np.zeros((h + 1, w + 1), np.int64)
    reg[codes[:, 0].astype(np.int64) + 1, codes[:, 1].astype(np.int64) + 1] = 1
    count, area = _box(reg.cumsum(0).cumsum(1), h, w, RADIUS)
    yy, xx = np.nonzero(mask & (count >= AMID_SHARE * area))
    return yy.astype(np.int64), xx.astype(np.int64)


def _orientation(decoded: list[npt.NDArray[np.float32]], index: list[int], mask: npt.NDArray[np.bool_],
                 sample: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]) -> int:
    """The scene's orientation of the code over the clean sample: with one coded axis the sign of its slope along
    its own image direction (columns for u, rows for v), with both the sign of the Jacobian determinant
    d(u, v) / d(x, y); +1 or -1 (0: undecided). Light straight from the projector keeps it; one mirror reverses
    it (see :func:`_oriented`)."""
    ys, xs = sample
    h, w = mask.shape
    ok = (xs + 1 < w) & (ys + 1 < h)
    y0, x0 = ys[ok], xs[ok]
    both = mask[y0, x0 + 1] & mask[y0 + 1, x0]
    y0, x0 = y0[both], x0[both]
    grads = []
    for m in decoded:
        base = m[y0, x0].astype(np.float64)
        grads.append((m[y0, x0 + 1] - base, m[y0 + 1, x0] - base))
    if len(decoded) == 1:
        d = grads[0][index[0]]
    else:
        d = grads[0][0] * grads[1][1] - grads[0][1] * grads[1][0]
    d = d[np.isfinite(d)]
    if len(d) < MIN_SAMPLES:
        return 0
    pos = int((d > 0).sum())
    neg = int((d < 0).sum())
    if pos >= 4 * neg:
        return 1
    if neg >= 4 * pos:
        return -1
    return 0


def _oriented(axes: list[_Axis], res: list[_Pass], orient: int) -> npt.NDArray[np.bool_]:
    """Per pixel whether its direct copy keeps the scene's orientation of the code (``orient``) and its second
    copy has the reverse, as light through one planar mirror does: with one coded axis the slope along its own
    image direction, with both the Jacobian determinant (a mirror reverses one direction, not necessarily the
    coded one). Where both copies look the same way nothing says which is direct: not taken apart."""
    if len(axes) == 1:
        j = axes[0].index
        s1, s2 = res[0].slopes1[:, j], res[0].slopes2[:, j]
    else:
        a, b = res[0], res[1]
        s1 = a.slopes1[:, 0] * b.slopes1[:, 1] - a.slopes1[:, 1] * b.slopes1[:, 0]
        s2 = a.slopes2[:, 0] * b.slopes2[:, 1] - a.slopes2[:, 1] * b.slopes2[:, 0]
    return np.asarray((np.sign(s1) == orient) & (np.sign(s2) == -orient), np.bool_)


def _sample(mask: npt.NDArray[np.bool_]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Decoded pixels on a regular grid, about :data:`_SAMPLE_TARGET` of them."""
    total = int(mask.sum())
    step = max(1, int(np.sqrt(total / _SAMPLE_TARGET)))
    yy, xx = np.nonzero(mask[::step, ::step])
    return (yy.astype(np.int64) * step, xx.astype(np.int64) * step)


def _spread(levels: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Per column of (L, N) levels ln(max / min) (inf where one is <= 0)."""
    low = levels.min(axis=0)
    high = levels.max(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(low > 0, np.log(high / np.where(low > 0, low, 1.0)), np.inf)
    return np.asarray(out, np.float64)


def _axis(
    shape: tuple[int, int],
    ys: npt.NDArray[np.int64],
    xs: npt.NDArray[np.int64],
    coarse: npt.NDArray[np.float64],
    r: npt.NDArray[np.float64],
    wre: npt.NDArray[np.float64],
    wim: npt.NDArray[np.float64],
    ax: _Axis,
    candidates: npt.NDArray[np.bool_],
    members: int,
    known: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None,
) -> _Pass:
    """One axis over a pixel list.

    The first ``members`` pixels make the planes and the second copy's terms: with ``known`` their (direct,
    second) codes, else those of the per-pixel fit, run on a :data:`LATTICE_PX` lattice. Planes and terms are
    computed at nodes every :data:`NODE_PX` px and taken by the pixels nearest to each."""
    h, w = shape
    periods, k = ax.periods, ax.k
    p0 = float(periods[0])
    on = (ys[:members] % LATTICE_PX == 0) & (xs[:members] % LATTICE_PX == 0)
    lat = np.flatnonzero(candidates[:members] & on)
    if known is None:
        u1l = np.empty(len(lat))
        u2l = np.empty(len(lat))
        _g.init_fit(coarse[lat], r[lat], np.ascontiguousarray(wre[:, lat]), np.ascontiguousarray(wim[:, lat]), k,
                    periods, _PRIOR, SPAN_PX, u1l, u2l)  # fmt: skip
    else:
        u1l = np.ascontiguousarray(known[0][lat])
        u2l = np.ascontiguousarray(known[1][lat])
    index = np.full(shape, -1, np.int32)
    index[ys[lat], xs[lat]] = np.arange(len(lat), dtype=np.int32)
    ny = np.minimum((ys + NODE_PX // 2) // NODE_PX * NODE_PX, h - 1)
    nx = np.minimum((xs + NODE_PX // 2) // NODE_PX * NODE_PX, w - 1)
    keys, node = np.unique(ny * w + nx, return_inverse=True)
    cy, cx = keys // w, keys % w
    plane2 = np.empty((len(keys), 3))
    inl = np.empty(len(keys))
    sc = np.empty(len(keys))
    _g.wrapped_planes(index, u2l, cy, cx, p0, RADIUS, 0.25 if known is None else 0.05, plane2, inl, sc)
    node_ok = np.isfinite(plane2[:, 0]) & (inl >= MIN_INLIERS) & (sc <= MAX_SCALE_PX)
    pl = np.nan_to_num(plane2)
    u2 = pl[node, 0] + pl[node, 1] * (xs - cx[node]) + pl[node, 2] * (ys - cy[node])
    u2 -= p0 * np.floor(u2 / p0)
    ok_l = node_ok[node[lat]]
    u2_l = np.ascontiguousarray(u2[lat]) if known is None else u2l
    r_l = np.ascontiguousarray(r[lat])
    wre_l, wim_l = np.ascontiguousarray(wre[:, lat]), np.ascontiguousarray(wim[:, lat])
    gre_n = np.empty((len(periods), len(keys)))
    gim_n = np.empty((len(periods), len(keys)))
    agree = np.empty(len(ys))
    mods = np.empty_like(wre)
    direct = np.empty(len(ys))
    rho = 0.5
    cur = u1l
    for _ in range(2 if known is None else 1):
        _g.ghost_terms(index, cy, cx, cur, u2_l, r_l, wre_l, wim_l, k, periods, rho, ok_l, RADIUS, gre_n, gim_n)
        _g.direct_codes(coarse, u2, wre, wim, np.ascontiguousarray(gre_n[:, node]),
                        np.ascontiguousarray(gim_n[:, node]), periods, direct, agree, mods)  # fmt: skip
        if known is None:
            cur = np.ascontiguousarray(direct[lat])
        amp_l = mods[0, lat] / k[0]
        good = ok_l & (amp_l > 0) & np.isfinite(amp_l)
        if good.any():
            rho = min(max(float(np.median((r_l[good] - amp_l[good]) / amp_l[good])), 0.0), 1.0)
    plane1 = np.empty((len(keys), 3))
    inl1 = np.empty(len(keys))
    sc1 = np.empty(len(keys))
    _g.wrapped_planes(index, cur, cy, cx, 0.0, RADIUS, 0.05, plane1, inl1, sc1)
    amp = mods[0] / k[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        strength = np.clip((r - amp) / amp, 0.0, 1.0)
    fin = float(periods[-1])
    gfin = np.asarray(np.isfinite(gre_n).all(axis=0), np.bool_)[node]
    accepted = (candidates & node_ok[node] & gfin & np.isfinite(direct) & (agree <= 0.25 * fin)
                & (np.abs(direct - coarse) <= SPAN_PX) & (amp > 0))  # fmt: skip
    # the light's consistency before and after: the levels r, |W_s| / k_s (one copy) against r - B, |D_s| / k_s
    ghost = np.hypot(gre_n[0], gim_n[0])[node] / k[0]
    before = _spread(np.vstack([r[None], np.hypot(wre, wim) / k[:, None]]))
    after = _spread(np.vstack([(r - ghost)[None], mods / k[:, None]]))
    pl1 = plane1[node]
    off = np.abs(direct - (pl1[:, 0] + pl1[:, 1] * (xs - cx[node]) + pl1[:, 2] * (ys - cy[node])))
    consistent = (after < EVIDENCE * before) & (before >= MIN_SPREAD)
    return _Pass(accepted, direct, u2, mods, np.nan_to_num(strength, nan=1.0), consistent,
                 np.nan_to_num(off, nan=np.inf), np.nan_to_num(plane1[node, 1:]),
                 np.nan_to_num(plane2[node, 1:]))  # fmt: skip
