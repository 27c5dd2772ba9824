"""Batch decoding: a whole frame stack -> :class:`~appliance.reconstruct.types.DecodedMaps` (see
:mod:`appliance.reconstruct.decode` for what is decoded and how), the saturation rule and the reason map.
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from appliance.errors import DecodeError
from appliance.patterns.sequence import Sequence
from appliance.reconstruct import _decode_kernels as _k
from appliance.reconstruct import _ghost_kernels as _gk
from appliance.reconstruct._pool import BufferPool
from appliance.reconstruct.decode_plan import (
    _AXES,
    COEFFICIENT_QUANTUM,
    DEFAULT_PARAMS,
    DecodeParams,
    DecodePlan,
    FrameStack,
    _as_plan,
    _clip_plan,
    _gray_stripe,
    _hist_layout,
    _int_sums,
    _max_value,
    lit_threshold,
)
from appliance.reconstruct.ghosts import Sums, separate
from appliance.reconstruct.types import DecodedMaps, Reason

#: Output blocks of decode() / StreamingDecoder.finish() without ``out`` (a few cameras' maps at once).
_POOL = BufferPool(max_blocks=4)


def _check_out(out: DecodedMaps, shape: tuple[int, int]) -> None:
    for name, dtype in (("u", np.float32), ("v", np.float32), ("mask", np.bool_), ("quality", np.float32)):
        arr = getattr(out, name)
        if arr.shape != shape or arr.dtype != dtype or not arr.flags.c_contiguous:
            raise DecodeError(
                f"decode: out.{name} is {arr.shape} {arr.dtype}: must be a C-contiguous {shape} "
                f"{np.dtype(dtype).name} array"
            )


def empty_maps(shape: tuple[int, int]) -> DecodedMaps:
    """Uninitialised output maps of ``shape`` (H, W), for ``decode(..., out=)``."""
    return DecodedMaps(
        np.empty(shape, np.float32),
        np.empty(shape, np.float32),
        np.empty(shape, np.bool_),
        np.empty(shape, np.float32),
        levels=np.empty((2, *shape), np.uint8),
        reason=np.empty(shape, np.uint8),
        fringe=np.empty(shape, np.uint8),
    )


def _outputs(
    plan: DecodePlan, shape: tuple[int, int], out: DecodedMaps | None
) -> tuple[DecodedMaps, npt.NDArray[np.float32]]:
    """Output maps, and the v buffer the kernel writes (no rows: v is a read-only NaN map, not written)."""
    lev_shape = (2, *shape)
    if out is not None:
        _check_out(out, shape)
        lev = out.levels
        if lev is None or lev.shape != lev_shape or lev.dtype != np.uint8 or not lev.flags.c_contiguous:
            out.levels = np.empty(lev_shape, np.uint8)
        for name in ("reason", "fringe"):
            arr = getattr(out, name)
            if arr is None or arr.shape != shape or arr.dtype != np.uint8 or not arr.flags.c_contiguous:
                setattr(out, name, np.empty(shape, np.uint8))
        return out, out.v
    # outputs are views of blocks reused once the caller drops them (saves their first-touch page faults)
    if "y" in plan.axes:
        u, v, mask, quality, levels, reason, fringe = _POOL.arrays([(shape, np.float32), (shape, np.float32),
                                                                    (shape, np.bool_), (shape, np.float32),
                                                                    (lev_shape, np.uint8), (shape, np.uint8),
                                                                    (shape, np.uint8)])  # fmt: skip
        maps = DecodedMaps(u, v, mask, quality, levels=levels, reason=reason, fringe=fringe)  # type: ignore[arg-type]
        return maps, maps.v
    # the y axis is not coded: v is NaN everywhere, one shared read-only map instead of H x W stores per call
    u, mask, quality, levels, reason, fringe = _POOL.arrays([(shape, np.float32), (shape, np.bool_),
                                                             (shape, np.float32), (lev_shape, np.uint8),
                                                             (shape, np.uint8), (shape, np.uint8)])  # fmt: skip
    maps = DecodedMaps(u, nan_map(shape), mask, quality, levels=levels, reason=reason,  # type: ignore[arg-type]
                       fringe=fringe)  # type: ignore[arg-type]
    return maps, np.empty((0, shape[1]), np.float32)


@functools.lru_cache(maxsize=4)
def nan_map(shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    """A read-only all-NaN float32 map of ``shape`` (H, W), shared: the v map of every decode that codes no y
    axis (and the camera-camera warm-up's, so that it compiles the very kernel variants a scan uses)."""
    nan = np.full(shape, np.nan, np.float32)
    nan.flags.writeable = False
    return nan


def _narrow(plan: DecodePlan, dtype: np.dtype[Any]) -> bool:
    """8-bit frames, at most 15 Gray bits per axis, no mean thresholding, no XOR codes (whose faint mask the
    16-bit lanes do not fold): Gray bits fold in 16-bit lanes."""
    return bool(dtype == np.uint8 and all(g.bits <= 15 and g.xor_base < 0 for g in plan.gray)
                and not plan.mean_frames)


#: Clipped-map flags that drop a decoded pixel: a clipped phase sample biases its coordinate by up to a
#: large share of the period, so the point would be wrong while looking right. (A Gray pair clipped in both
#: frames already fails its contrast test.)
_DROP = int(_k.CLIP_PHASE_X | _k.CLIP_PHASE_Y)


def _saturation_and_reasons(
    out: DecodedMaps,
    v_arg: npt.NDArray[np.float32],
    clip: npt.NDArray[np.uint8],
    hi: npt.NDArray[Any],
    lo: npt.NDArray[Any],
    thr: float,
    dtype: np.dtype[Any],
    params: DecodeParams,
    plan: DecodePlan,
    sums: Sums,
) -> None:
    """Drop the pixels whose needed samples are clipped, give the blend check's pixels whose two copies of the
    pattern come apart their direct code back (:func:`appliance.reconstruct.ghosts.separate`, with the phase
    sums ``sums``), then write every pixel's :class:`Reason`."""
    assert out.levels is not None and out.reason is not None and out.fringe is not None
    # the blend check's regions first (it reads every mark before any is cleared); reason = 1 there until below
    h = out.mask.shape[0]
    flagged, per_row = np.empty(h, np.bool_), np.empty(h, np.int64)
    _k.blend_regions(out.levels, out.reason, flagged, per_row)
    starts = np.zeros(h, np.int64)
    np.cumsum(per_row[:-1], out=starts[1:])
    codes = np.empty((int(per_row.sum()), 4), np.float32)
    _k.blend_undecode(out.levels, out.u, v_arg, v_arg.shape[0] > 0, out.mask, out.quality, out.reason, flagged,
                      starts, codes)  # fmt: skip
    out.blend_codes = codes
    _k.drop_clipped(clip, _DROP, out.u, v_arg, v_arg.shape[0] > 0, out.mask, out.quality, out.levels)
    if params.separate_copies:
        separate(out, v_arg, codes, plan, sums, hi, lo, clip)
    else:
        out.separated = None
    dark = params.min_contrast_dn * _max_value(dtype, params) / 255.0
    _k.decode_reasons(
        hi, lo, float(thr), float(dark), clip, out.mask, out.reason, out.fringe, int(Reason.DECODED),
        int(Reason.SHADOW), int(Reason.TOO_DARK), int(Reason.SATURATED), int(Reason.WEAK_CODE),
        int(Reason.INTERREFLECTION),
    )  # fmt: skip
    if params.partial_cover:
        _k.drop_partial(hi, lo, out.reason, 0, False, _k.COVER_RATIO, out.u, v_arg, v_arg.shape[0] > 0, out.mask,
                        out.quality, out.levels, out.fringe, out.reason, int(Reason.DECODED), int(Reason.SHADOW),
                        int(Reason.TOO_DARK), int(Reason.EDGE))  # fmt: skip


def drop_partial_cover(
    maps: DecodedMaps, level: npt.NDArray[np.float32], choice: npt.NDArray[np.uint8], passes: int
) -> int:
    """The fused maps of several exposure passes: undecode the pixels lit over a small part of their footprint
    beside an unlit one (``_decode_kernels.COVER_RATIO``; reason ``EDGE``), judged on the fused reasons
    and the white level in one scale (each pass's decode leaves this to the fusion: a pixel too dark in one pass
    may decode in a brighter one).

    Parameters
    ----------
    maps : DecodedMaps
        The fused decode, with ``reason``, ``levels`` and ``fringe``; changed in place.
    level : ndarray, shape (H, W), float32
        White-light level per pixel in one scale across the passes (``DecodedMaps.radiance``).
    choice : ndarray, shape (H, W), uint8
        The pass each pixel's result came from (:func:`appliance.reconstruct.hdr.fuse_exposures`): an undecoded
        neighbour is unlit only where the brightest pass gave its verdict (a darker one means the brighter
        clipped it: beside a bright patch, not in a shadow).
    passes : int
        How many passes.

    Returns
    -------
    int
        The pixels undecoded.
    """
    if maps.reason is None or maps.levels is None:
        return 0
    fringe = maps.fringe if maps.fringe is not None else np.zeros(maps.shape, np.uint8)
    # v is NaN where its axis is not coded: clearing it there changes nothing
    return int(_k.drop_partial(level, level, choice, passes - 1, True, _k.COVER_RATIO, maps.u, maps.v, True, maps.mask,
                               maps.quality, maps.levels, fringe, maps.reason, int(Reason.DECODED),
                               int(Reason.SHADOW), int(Reason.TOO_DARK), int(Reason.EDGE)))  # fmt: skip


def reason_counts(maps: DecodedMaps) -> dict[str, int]:
    """Pixels per :class:`Reason` of a decode (``{"decoded": n, "shadow": n, ...}``, zero counts left out).

    Parameters
    ----------
    maps : DecodedMaps
        A decode with ``reason``.

    Returns
    -------
    dict of str to int
        Pixel counts keyed by the reason's plain name; empty when ``maps.reason`` is None.
    """
    from appliance.reconstruct.types import REASON_NAMES

    if maps.reason is None:
        return {}
    counts = np.bincount(maps.reason.ravel(), minlength=len(REASON_NAMES))
    return {REASON_NAMES[i]: int(c) for i, c in enumerate(counts.tolist()) if c and i in REASON_NAMES}


def reason_block(maps: DecodedMaps) -> dict[str, Any]:
    """The sidecar's per-camera reason block: pixels and share of the image per :class:`Reason`.

    Parameters
    ----------
    maps : DecodedMaps
        A decode with ``reason``.

    Returns
    -------
    dict
        ``{"reasons": {name: pixels}, "reason_shares": {name: share of the image's pixels, 0..1}}`` (zero
        counts left out), and ``"separated"``: the decoded pixels lit by two copies of the pattern whose direct
        code was taken apart (:mod:`appliance.reconstruct.ghosts`; absent: none); empty when ``maps.reason`` is
        None.
    """
    counts = reason_counts(maps)
    if not counts:
        return {}
    total = max(int(maps.mask.size), 1)
    block: dict[str, Any] = {"reasons": counts, "reason_shares": {k: round(n / total, 6) for k, n in counts.items()}}
    if maps.separated is not None and len(maps.separated):
        block["separated"] = len(maps.separated)
    return block


#: A reason is said in plain words when it holds at least this share of the lit (not shadowed) pixels.
DOMINANT_REASON_SHARE = 0.2
_ADVICE = {
    Reason.TOO_DARK: "too dark: add a longer exposure (sequence.exposures_us) or run scan3d tune",
    Reason.SATURATED: "saturated: add a shorter exposure (sequence.exposures_us) or run scan3d tune",
    Reason.WEAK_CODE: ("weak or inconsistent codes (stripes finer than the optics resolve, interreflection, "
                       "a moving part): use coarser stripes or longer periods, or run scan3d tune"),
    Reason.INTERREFLECTION: ("lit by two copies of the pattern (a mirror-like face re-projects it onto them, or "
                             "they see it in one): tilt the part or the scanner so the reflection leaves the view, "
                             "or dull the shiny face"),
    Reason.HIDDEN: ("hidden from the projector (lit only by a reflection: a mirror-like face shows the camera a lit "
                    "surface, or lights a face the projector's shadow hides): tilt the part or the scanner so the "
                    "reflection leaves the view, or dull the shiny face"),
    Reason.MIXED: ("next to a clipped pixel (dark and bright parts side by side: the pass that lights the dark "
                   "clips the bright, whose light blurs in): add an exposure between those of "
                   "sequence.exposures_us, or run scan3d tune"),
}


def reason_advice(maps: DecodedMaps, camera: str) -> str | None:
    """One plain-words line when one reason leaves at least :data:`DOMINANT_REASON_SHARE` of the lit pixels
    without a point (too dark, saturated, weak or inconsistent code, two copies of the pattern, hidden from the
    projector, next to a clipped pixel), with what to do; None otherwise.

    Parameters
    ----------
    maps : DecodedMaps
        A decode with ``reason``.
    camera : str
        The camera's name (the line starts with it).
    """
    if maps.reason is None:
        return None
    counts = np.bincount(maps.reason.ravel(), minlength=int(max(Reason)) + 1)
    lit = int(maps.reason.size - counts[Reason.SHADOW])
    if lit <= 0:
        return None
    worst = max(_ADVICE, key=lambda r: int(counts[r]))
    share = int(counts[worst]) / lit
    if share < DOMINANT_REASON_SHARE:
        return None
    return f"{camera}: {100 * share:.0f} % of the lit pixels are {_ADVICE[worst]}"


def decode(
    frames: FrameStack,
    sequence: Sequence | DecodePlan,
    params: DecodeParams = DEFAULT_PARAMS,
    *,
    out: DecodedMaps | None = None,
) -> DecodedMaps:
    """Decode a captured frame stack into projector coordinates.

    Parameters
    ----------
    frames : ndarray, shape (F, H, W), uint8 or uint16
        One camera's frames in the order of ``sequence``.
    sequence : Sequence or DecodePlan
        What each frame shows (a plan from :func:`plan_decode` skips re-planning).
    params : DecodeParams
        Thresholds.
    out : DecodedMaps, optional
        Preallocated C-contiguous (H, W) outputs (see :func:`empty_maps`); filled and returned.

    Returns
    -------
    DecodedMaps
        ``u``, ``v`` (projector px, float32, NaN where undecoded or not coded), ``mask``, ``quality`` (DN).
        Without ``out``, ``v`` of a sequence that codes no rows is a shared read-only all-NaN map.

    Raises
    ------
    PatternError
        The sequence cannot be decoded (see :func:`plan_decode`).
    DecodeError
        ``frames`` has the wrong shape or dtype.
    """
    plan = _as_plan(sequence)
    frames_arr = np.asarray(frames)
    n = len(plan.sequence)
    if frames_arr.ndim != 3 or frames_arr.shape[0] != n:
        raise DecodeError(
            f"decode: frames have shape {frames_arr.shape}: must be ({n}, height, width), one image per "
            "frame of the sequence"
        )
    if frames_arr.dtype not in (np.uint8, np.uint16):
        raise DecodeError(f"decode: frames have dtype {frames_arr.dtype}: must be uint8 or uint16")
    stack = np.ascontiguousarray(frames_arr)
    shape = (int(stack.shape[1]), int(stack.shape[2]))
    out, v_arg = _outputs(plan, shape, out)
    t = plan.tables
    shift, nbins = _hist_layout(stack.dtype, params)
    maxval = 255 if stack.dtype == np.uint8 else 65535
    if plan.white >= 0:
        hist = _k.range_hist(stack[plan.white], stack[plan.black], shift, nbins)
    else:
        hist = _k.range_hist_stack(stack, t.wb, t.used, maxval, shift, nbins)
    thr = lit_threshold(hist, stack.dtype, params)
    assert out.levels is not None and out.fringe is not None
    # exact phase sums: int32 in units of the quantum where they fit (8-bit frames), else float64
    ints = _int_sums(t, maxval)
    sin, cos = (t.ph_sin_q, t.ph_cos_q) if ints else (t.ph_sin, t.ph_cos)
    _k.decode_stack(
        stack, t.wb, t.used, maxval, t.gray_tab, t.mean_idx, t.axis_tab, t.ph_tab,
        t.ph_period, t.ph_idx, sin, cos, COEFFICIENT_QUANTUM if ints else 1.0,
        float(params.relative_contrast), float(params.blend_ratio), float(thr),
        bool(params.finest_bit), numba.get_num_threads(), _narrow(plan, stack.dtype), out.u, v_arg, out.mask,
        out.quality, out.levels, out.fringe,
    )  # fmt: skip
    full = int(_max_value(stack.dtype, params))
    clip = np.zeros(shape, np.uint8)
    phase, pairs = _clip_plan(plan)
    for idx, flag in phase:
        _k.mark_clipped(stack[idx], full, flag, clip)
    for pos, neg, flag in pairs:
        _k.mark_clipped_pair(stack[pos], stack[neg], full, flag, clip)
    if plan.white >= 0:
        hi, lo = stack[plan.white], stack[plan.black]
    else:
        hi, lo = np.empty(shape, stack.dtype), np.empty(shape, stack.dtype)
        _k.stack_range(stack, t.used, hi, lo)
    _saturation_and_reasons(out, v_arg, clip, hi, lo, thr, stack.dtype, params, plan,
                            stack_sums(stack, plan, ints))  # fmt: skip
    out.ignored = list(plan.ignored)
    return out


def stack_sums(stack: npt.NDArray[Any], plan: DecodePlan, ints: bool) -> Sums:
    """The phase sums of a stack at given pixels, formed as the decoders form them (exact integers in units of
    the coefficient quantum where ``ints``, else float64 with the quantised coefficients), in real units."""
    t = plan.tables
    sin_c, cos_c = (t.ph_sin_q.astype(np.int64), t.ph_cos_q.astype(np.int64)) if ints else (t.ph_sin, t.ph_cos)
    acc = np.int64 if ints else np.float64
    quantum = COEFFICIENT_QUANTUM if ints else 1.0

    def sums(s: int, ys: npt.NDArray[np.int64], xs: npt.NDArray[np.int64]) -> tuple[
            npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        so, co = np.empty(len(ys), acc), np.empty(len(ys), acc)
        _gk.gather_stack_sums(stack, ys, xs, t.ph_idx, sin_c, cos_c, int(t.ph_tab[s, 3]), int(t.ph_tab[s, 1]), so, co)
        return so.astype(np.float64) * quantum, co.astype(np.float64) * quantum

    return sums


def stripe_widths(maps: DecodedMaps, sequence: Sequence | DecodePlan) -> dict[str, dict[float, float]]:
    """Distribution of effective code widths over the decoded pixels, per coded axis.

    Parameters
    ----------
    maps : DecodedMaps
        A decode of ``sequence`` (with ``levels``).
    sequence : Sequence or DecodePlan
        What was decoded.

    Returns
    -------
    dict of axis to {width: share}
        ``width`` in projector px: ``stripe * 2**level`` for a Gray-only axis, 0.0 for an axis whose phase
        gives sub-pixel coordinates; ``share`` of the decoded pixels (0..1).
    """
    plan = _as_plan(sequence)
    decoded = maps.mask
    n = int(decoded.sum())
    out: dict[str, dict[float, float]] = {}
    for a, axis in enumerate(_AXES):
        if axis not in plan.axes:
            continue
        if any(p.axis == axis for p in plan.phase) or n == 0:
            out[axis] = {0.0: 1.0} if n else {}
            continue
        stripe = _gray_stripe(plan, axis)
        if maps.levels is None:
            counts = np.array([n], np.int64)
        else:
            lev = np.ascontiguousarray(maps.levels[a], np.uint8)
            counts = _k.level_counts(lev, np.ascontiguousarray(decoded, np.bool_))
        out[axis] = {float(stripe << k): float(c) / n for k, c in enumerate(counts) if c}
    return out
