"""numba kernels of camera-camera matching (private; see ``stereo.py``).

Codes arrive on rectified rows in *level units*: the value ``k`` (an integer) is a level whose crossing is
tabulated per row. For continuous (phase) codes a level is one projector pixel; for quantised (Gray-only)
codes the levels are the boundaries between neighbouring stripes, so a stripe is the open interval
``(k, k + 1)`` and its centre ``k + 0.5``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.geometry._distortion_kernels import distort_jac
from appliance.reconstruct._filter_kernels import near_neighbours
from appliance.reconstruct._geom_kernels import NAN32 as _NAN


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _dir_pixel(rot, a, b, kmat, d):  # type: ignore[no-untyped-def]
    """Distorted pixel (x, y) of the rectified direction ``rot @ (a, b, 1)`` (device frame); NaN behind."""
    px = rot[0, 0] * a + rot[0, 1] * b + rot[0, 2]
    py = rot[1, 0] * a + rot[1, 1] * b + rot[1, 2]
    pz = rot[2, 0] * a + rot[2, 1] * b + rot[2, 2]
    if pz <= 1e-9:
        return np.nan, np.nan
    xd, yd, _, _, _, _ = distort_jac(px / pz, py / pz, d)
    return kmat[0, 0] * xd + kmat[0, 1] * yd + kmat[0, 2], kmat[1, 1] * yd + kmat[1, 2]


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def project_dirs(rot, a0, b0, step, hr, wr, kmat, d):  # type: ignore[no-untyped-def]
    """Distorted pixel of every rectified-grid direction ``rot @ (a, b, 1)`` (device frame); NaN behind."""
    out = np.empty((hr, wr, 2), dtype=np.float32)
    for y in prange(hr):
        b = b0 + y * step
        for x in range(wr):
            ex, ey = _dir_pixel(rot, a0 + x * step, b, kmat, d)
            out[y, x, 0] = ex
            out[y, x, 1] = ey
    return out


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _bilinear_within(src, ix, iy, tx, ty, max_spread):  # type: ignore[no-untyped-def]
    c00 = src[iy, ix]
    c01 = src[iy, ix + 1]
    c10 = src[iy + 1, ix]
    c11 = src[iy + 1, ix + 1]
    lo = min(min(c00, c01), min(c10, c11))
    hi = max(max(c00, c01), max(c10, c11))
    if not hi - lo <= max_spread:  # NaN compares false: rejected
        return _NAN
    a = c00 + tx * (c01 - c00)
    b = c10 + tx * (c11 - c10)
    return a + ty * (b - a)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _map_at(srcmap, knot, y, x):  # type: ignore[no-untyped-def]
    """Source pixel (sx, sy) of rectified pixel (y, x): bilinear between the map's knots, every ``knot``
    rectified pixels (knot (j, i) is pixel (j * knot, i * knot)); NaN where a knot is NaN (behind the camera)."""
    if knot == 1:
        return np.float64(srcmap[y, x, 0]), np.float64(srcmap[y, x, 1])
    j = y // knot
    i = x // knot
    ty = (y - j * knot) / knot
    tx = (x - i * knot) / knot
    j1 = min(j + 1, srcmap.shape[0] - 1)
    i1 = min(i + 1, srcmap.shape[1] - 1)
    out0 = 0.0
    out1 = 0.0
    for c in range(2):
        c00 = np.float64(srcmap[j, i, c])
        c01 = np.float64(srcmap[j, i1, c])
        c10 = np.float64(srcmap[j1, i, c])
        c11 = np.float64(srcmap[j1, i1, c])
        a = c00 + tx * (c01 - c00)
        b = c10 + tx * (c11 - c10)
        if c == 0:
            out0 = a + ty * (b - a)
        else:
            out1 = a + ty * (b - a)
    return out0, out1


@njit(nogil=True, cache=True, error_model="numpy", fastmath=False)  # exact in fastmath callers too
def _map_row(srcmap, knot, y, out):  # type: ignore[no-untyped-def]
    """Row ``y`` of the map at every pixel into ``out`` (W, 2) float64: for each pixel the very value
    :func:`_map_at` gives (the same operations), a knot interval at a time (no division per pixel)."""
    w = out.shape[0]
    if knot == 1:
        for x in range(w):
            out[x, 0] = srcmap[y, x, 0]
            out[x, 1] = srcmap[y, x, 1]
        return out
    j = y // knot
    ty = (y - j * knot) / knot
    j1 = min(j + 1, srcmap.shape[0] - 1)
    last = srcmap.shape[1] - 1
    for i in range((w + knot - 1) // knot):
        i1 = min(i + 1, last)
        for c in range(2):
            c00 = np.float64(srcmap[j, i, c])
            c01 = np.float64(srcmap[j, i1, c])
            c10 = np.float64(srcmap[j1, i, c])
            c11 = np.float64(srcmap[j1, i1, c])
            for k in range(min(knot, w - i * knot)):
                tx = k / knot
                a = c00 + tx * (c01 - c00)
                b = c10 + tx * (c11 - c10)
                out[i * knot + k, c] = a + ty * (b - a)
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def map_error(rot, a0, b0, step, hr, wr, kmat, d, srcmap, knot, w_img, h_img):  # type: ignore[no-untyped-def]
    """Largest distance (px) between :func:`_map_at` on a map of knots every ``knot`` pixels and the exact
    distorted pixel of each of the (hr, wr) rectified pixels whose exact pixel lies in the (w_img, h_img)
    image (one pixel of margin); inf where the exact pixel is in the image and the interpolated one is NaN."""
    worst = np.zeros(hr)
    for y in prange(hr):
        b = b0 + y * step
        e = 0.0
        for x in range(wr):
            ex, ey = _dir_pixel(rot, a0 + x * step, b, kmat, d)
            if not (ex >= -1.0 and ey >= -1.0 and ex <= w_img and ey <= h_img):  # NaN (behind) fails too
                continue
            sx, sy = _map_at(srcmap, knot, y, x)
            dist = math.sqrt((sx - ex) ** 2 + (sy - ey) ** 2)
            if not dist <= e:  # NaN: the interpolation lost a pixel the camera sees
                e = dist if dist == dist else np.inf
        worst[y] = e
    return worst.max() if hr > 0 else 0.0


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def grid_error(full, srcmap, knot):  # type: ignore[no-untyped-def]
    """Largest distance between :func:`_map_at` on a map of knots every ``knot`` pixels and the ``full`` map
    (H, W, 2) it stands for; inf where one of the two is NaN and the other not."""
    h, w = full.shape[0], full.shape[1]
    worst = np.zeros(h)
    for y in prange(h):
        e = 0.0
        for x in range(w):
            sx, sy = _map_at(srcmap, knot, y, x)
            fx = np.float64(full[y, x, 0])
            fy = np.float64(full[y, x, 1])
            if (fx != fx or fy != fy) and (sx != sx or sy != sy):
                continue  # NaN in both: the same pixel left out
            dist = math.sqrt((sx - fx) ** 2 + (sy - fy) ** 2)
            if not dist <= e:
                e = dist if dist == dist else np.inf
        worst[y] = e
    return worst.max() if h > 0 else 0.0


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def sample_map(srcmap, knot, n, rows, cols):  # type: ignore[no-untyped-def]
    """:func:`_map_at` at the pixels (r * n, c * n) of ``rows`` x ``cols``: (rows, cols, 2) float32."""
    out = np.empty((rows, cols, 2), np.float32)
    for r in prange(rows):
        for c in range(cols):
            x, y = _map_at(srcmap, knot, r * n, c * n)
            out[r, c, 0] = x
            out[r, c, 1] = y
    return out


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _source_cell(sx, sy, mask):  # type: ignore[no-untyped-def]
    """Source pixel (sx, sy) -> (inside, ix, iy, tx, ty): its source cell, whose 4 corners are all decoded."""
    h, w = mask.shape[0], mask.shape[1]
    if not (sx >= 0.0 and sy >= 0.0 and sx < w - 1 and sy < h - 1):
        return False, 0, 0, 0.0, 0.0
    ix = int(sx)
    iy = int(sy)
    ok = mask[iy, ix] and mask[iy, ix + 1] and mask[iy + 1, ix] and mask[iy + 1, ix + 1]
    return ok, ix, iy, sx - ix, sy - iy


ROW_CHUNKS = 64
"""Rows of a parallel kernel are cut into at most this many chunks (each with its own row buffer)."""


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def _remap(src_a, src_b, mask, srcmap, knot, spread_a, spread_b, out_a, out_b, two):  # type: ignore[no-untyped-def]
    """:func:`remap_codes` of ``src_a``, and with ``two`` of ``src_b`` too (the same source cells)."""
    hr, wr = out_a.shape[0], out_a.shape[1]
    nch = min(hr, ROW_CHUNKS)
    for ch in prange(nch):
        row = np.empty((wr, 2))
        for y in range(ch * hr // nch, (ch + 1) * hr // nch):
            _map_row(srcmap, knot, y, row)
            for x in range(wr):
                ok, ix, iy, tx, ty = _source_cell(row[x, 0], row[x, 1], mask)
                out_a[y, x] = _bilinear_within(src_a, ix, iy, tx, ty, spread_a) if ok else _NAN
                if two:
                    out_b[y, x] = _bilinear_within(src_b, ix, iy, tx, ty, spread_b) if ok else _NAN
    return out_a


@njit(nogil=True, cache=True, error_model="numpy")
def remap_codes(src, mask, srcmap, knot, max_spread, out):  # type: ignore[no-untyped-def]
    """Bilinear resampling of a code map; NaN unless all 4 neighbours are valid and within ``max_spread``.
    ``srcmap``: the source pixel of every ``knot``-th rectified pixel (see :func:`_map_at`)."""
    return _remap(src, src, mask, srcmap, knot, max_spread, max_spread, out, out, False)


@njit(nogil=True, cache=True, error_model="numpy")
def remap_pair(src_a, src_b, mask, srcmap, knot, spread_a, spread_b, out_a, out_b):  # type: ignore[no-untyped-def]
    """:func:`remap_codes` of two code maps of one camera (u and v) in one pass: the same values."""
    return _remap(src_a, src_b, mask, srcmap, knot, spread_a, spread_b, out_a, out_b, True)


# per-pixel outcome of the matcher (see stereo.STAGES for the words)
ST_NONE = 0  # not decoded in the reference camera: not a candidate
ST_OUTSIDE = 1  # outside the rows both cameras share
ST_OWN = 2  # the code is not where it should be on its own row (ambiguous, edge, left-right check)
ST_OTHER = 3  # the code is not found, or not consistently, on the other camera's row
ST_EPIPOLAR = 4  # the (u, v) match lies too far off the epipolar line
ST_DEPTH = 5  # behind the cameras or outside the depth range
ST_THREE_VIEW = 6  # the point does not project onto its code in the projector
ST_OK = 7


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def to_levels(rect, lev0, inv_dl):  # type: ignore[no-untyped-def]
    """In place: codes -> level units ``(c - lev0) * inv_dl``."""
    hr, wr = rect.shape[0], rect.shape[1]
    for y in prange(hr):
        for x in range(wr):
            rect[y, x] = (rect[y, x] - lev0) * inv_dl
    return rect


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def level_crossings(rect, code_offset, max_step, out):  # type: ignore[no-untyped-def]
    """Per rectified row, the sub-pixel x where the code crosses each level (NaN none, inf crossed twice)."""
    hr, wr = rect.shape[0], rect.shape[1]
    nk = out.shape[1]
    for y in prange(hr):
        for k in range(nk):
            out[y, k] = _NAN
        for x in range(wr - 1):
            ua = np.float64(rect[y, x])
            ub = np.float64(rect[y, x + 1])
            if not (abs(ub - ua) <= max_step) or ua == ub:
                continue
            lo = min(ua, ub)
            hi = max(ua, ub)
            for k in range(math.ceil(lo), math.ceil(hi)):
                idx = k + code_offset
                if idx < 0 or idx >= nk:
                    continue
                if math.isnan(out[y, idx]):
                    out[y, idx] = x + (k - ua) / (ub - ua)
                else:
                    out[y, idx] = np.inf
    return out


@njit(nogil=True, cache=True, error_model="numpy")
def _line_fits(buf, half, max_res, wt, xf, s, out):  # type: ignore[no-untyped-def]
    """Robust local line fit of every entry of a line: ``buf`` (n + 2 half,) holds it between ``half`` NaN
    each side, ``out`` (n,) receives the fits; ``wt``, ``xf`` (n + 2 half,) and ``s`` (8, n) are scratch.

    The fit at entry i spans entries i + d, |d| <= half, that are finite. The raw value stays where the entry
    is not finite, fewer than 3 entries are, or the fit misses the entry itself by more than ``max_res``; a
    second fit leaves out the entries more than ``max_res`` off the first, where there are any (rare: one
    scalar pass). The sums run over d outside and the entries inside, so the loops vectorise; a NaN / inf
    entry adds exact zeros, so the fits equal a per-entry loop's bit for bit.
    """
    n = out.shape[0]
    for j in range(buf.shape[0]):
        x = buf[j]
        f = (x - x) == 0.0  # finite
        wt[j] = 1.0 if f else 0.0
        xf[j] = x if f else 0.0
    s1, sd, sdd, sx, sdx, a, b, state = s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]
    for i in range(n):
        s1[i] = 0.0
        sd[i] = 0.0
        sdd[i] = 0.0
        sx[i] = 0.0
        sdx[i] = 0.0
    for d in range(-half, half + 1):
        fd = np.float64(d)
        wd = wt[half + d : half + d + n]
        xd = xf[half + d : half + d + n]
        for i in range(n):
            w = wd[i]
            x = xd[i]
            s1[i] += w
            sd[i] += w * fd
            sdd[i] += w * (fd * fd)
            sx[i] += x
            sdx[i] += fd * x
    # state: 0 the first fit, 1 a second fit, 2 the raw value
    for i in range(n):
        det = s1[i] * sdd[i] - sd[i] * sd[i]
        ok = (s1[i] >= 3.0) & (det >= 1e-9)
        dd = det if ok else 1.0
        a[i] = (sx[i] * sdd[i] - sd[i] * sdx[i]) / dd
        b[i] = (s1[i] * sdx[i] - sd[i] * sx[i]) / dd
        x0 = buf[half + i]
        raw = (not ok) | (abs(x0 - a[i]) > max_res) | ((x0 - x0) != 0.0)
        state[i] = 2.0 if raw else 0.0
    for d in range(-half, half + 1):
        fd = np.float64(d)
        wd = wt[half + d : half + d + n]
        bd = buf[half + d : half + d + n]
        for i in range(n):
            off = (wd[i] != 0.0) & (abs(bd[i] - (a[i] + b[i] * fd)) > max_res)
            state[i] = max(state[i], 1.0 if off else 0.0)
    for i in range(n):
        c = i + half
        if state[i] == 0.0:
            out[i] = a[i]
        elif state[i] == 2.0:
            out[i] = buf[c]
        else:
            aa = a[i]
            bb = b[i]
            t1 = 0.0
            td = 0.0
            tdd = 0.0
            tx = 0.0
            tdx = 0.0
            for d in range(-half, half + 1):
                x = buf[c + d]
                if not math.isfinite(x) or abs(x - (aa + bb * d)) > max_res:
                    continue
                t1 += 1.0
                td += d
                tdd += d * d
                tx += x
                tdx += d * x
            det = t1 * tdd - td * td
            out[i] = buf[c] if (t1 < 3.0 or det < 1e-9) else (tx * tdd - td * tdx) / det


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def smooth_crossings(tab, half, along_rows, max_res, out):  # type: ignore[no-untyped-def]
    """Local line fit of each crossing over ``2 half + 1`` neighbouring levels (or rows, ``along_rows``).

    Quantised codes put every crossing within half a pixel of its true place, independently from level to
    level and row to row where stripes and pixel grid are not aligned: the fit averages that out (run once
    along levels, once along rows: a separable plane fit). Entries more than ``max_res`` px off a first fit
    are left out of a second; a centre that is itself such an outlier stays raw. Ambiguous (inf) and
    missing (NaN) entries are copied (see :func:`_line_fits`).
    """
    hr, nk = tab.shape[0], tab.shape[1]
    n = hr if along_rows else nk
    m = nk if along_rows else hr
    nch = min(m, 64)
    for ch in prange(nch):
        buf = np.full(n + 2 * half, np.nan)
        wt = np.empty(n + 2 * half)
        xf = np.empty(n + 2 * half)
        s = np.empty((8, n))
        res = np.empty(n)
        for j in range(ch * m // nch, (ch + 1) * m // nch):
            if along_rows:
                for i in range(n):
                    buf[half + i] = tab[i, j]
            else:
                for i in range(n):
                    buf[half + i] = tab[j, i]
            _line_fits(buf, half, max_res, wt, xf, s, res)
            if along_rows:
                for i in range(n):
                    out[i, j] = res[i]
            else:
                for i in range(n):
                    out[j, i] = res[i]
    return out


# The box mean runs over whole rows, one window offset at a time (each pixel's sum still adds its window in
# order, so the values are those of a per-pixel loop), so that its loops vectorise.


@njit(nogil=True, cache=True, error_model="numpy")
def _window_init(s, lo, hi):  # type: ignore[no-untyped-def]
    for x in range(s.shape[0]):
        s[x] = 0.0
        lo[x] = np.inf
        hi[x] = -np.inf


@njit(nogil=True, cache=True, error_model="numpy")
def _window_add(src, s, lo, hi):  # type: ignore[no-untyped-def]
    for x in range(s.shape[0]):
        c = np.float64(src[x])
        s[x] += c
        lo[x] = min(lo[x], c)
        hi[x] = max(hi[x], c)


@njit(nogil=True, cache=True, error_model="numpy")
def _window_mean(s, lo, hi, n, max_span, out):  # type: ignore[no-untyped-def]
    """out = s / n where the window was all finite (its sum is) and spans at most ``max_span``, else NaN."""
    nf = np.float64(n)
    for x in range(s.shape[0]):
        ok = (hi[x] - lo[x] <= max_span) & (s[x] - s[x] == 0.0)
        out[x] = np.float32(s[x] / nf) if ok else _NAN


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def box_mean(src, radius, max_span, scratch, out):  # type: ignore[no-untyped-def]
    """Separable (2r+1)^2 box mean of a quantised code map where the whole window is valid and spans at
    most ``max_span`` codes per axis pass (no edge inside); NaN elsewhere. ``scratch`` is (H, W)."""
    h, w = src.shape[0], src.shape[1]
    n = 2 * radius + 1
    m = w - 2 * radius  # pixels of a row with the whole window inside
    for y in prange(h):
        s = np.empty(w, np.float64)
        lo = np.empty(w, np.float64)
        hi = np.empty(w, np.float64)
        row = scratch[y]
        for x in range(min(radius, w)):
            row[x] = _NAN
        for x in range(max(0, w - radius), w):
            row[x] = _NAN
        if m > 0:
            _window_init(s[:m], lo[:m], hi[:m])
            for d in range(n):
                _window_add(src[y, d : d + m], s[:m], lo[:m], hi[:m])
            _window_mean(s[:m], lo[:m], hi[:m], n, max_span, row[radius : radius + m])
    for y in prange(h):
        if not radius <= y < h - radius:
            out[y, :] = _NAN
            continue
        s = np.empty(w, np.float64)
        lo = np.empty(w, np.float64)
        hi = np.empty(w, np.float64)
        _window_init(s, lo, hi)
        for d in range(-radius, radius + 1):
            _window_add(scratch[y + d], s, lo, hi)
        _window_mean(s, lo, hi, n, max_span, out[y])
    return out


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _bounds(tab, y, idx, max_gap, extrapolate):  # type: ignore[no-untyped-def]
    """Crossings of levels ``idx`` and ``idx + 1`` on row y; NaN pair where not consistent. With
    ``extrapolate``, one missing (NaN: an edge of the decoded area, not inf: ambiguous) comes from the next
    level's spacing: used on a pixel's own row only, where the pixel itself proves the stripe is there."""
    nk = tab.shape[1]
    xa = np.float64(tab[y, idx])
    xb = np.float64(tab[y, idx + 1])
    if extrapolate and xa != xa and idx >= 0 and idx + 2 < nk and math.isfinite(xb):
        xn = np.float64(tab[y, idx + 2])
        if abs(xn - xb) <= max_gap:
            xa = xb - (xn - xb)
    elif extrapolate and xb != xb and idx >= 1 and math.isfinite(xa):
        xp = np.float64(tab[y, idx - 1])
        if abs(xa - xp) <= max_gap:
            xb = xa + (xa - xp)
    if not abs(xb - xa) <= max_gap:  # also rejects NaN / inf
        return np.nan, np.nan
    return xa, xb


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _cross_at(tab, y, w, fu, code_offset, max_gap, max_row_jump, extrapolate=False):  # type: ignore[no-untyped-def]
    """Sub-pixel x on fractional row ``y + w`` where the code (level units) equals ``fu``; NaN if none
    (``extrapolate``: see :func:`_bounds`)."""
    k = math.floor(fu)
    t = fu - k
    idx = int(k) + code_offset
    if idx < 0 or idx + 1 >= tab.shape[1] or y < 0 or y + 1 >= tab.shape[0]:
        return np.nan
    xa0, xb0 = _bounds(tab, y, idx, max_gap, extrapolate)
    xa1, xb1 = _bounds(tab, y + 1, idx, max_gap, extrapolate)
    if xa0 != xa0 or xa1 != xa1:
        return np.nan
    x0 = xa0 + t * (xb0 - xa0)
    x1 = xa1 + t * (xb1 - xa1)
    if not abs(x1 - x0) <= max_row_jump:
        return np.nan
    return x0 + w * (x1 - x0)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _level_at(tab, y, w, x, k, code_offset, max_gap, max_row_jump):  # type: ignore[no-untyped-def]
    """Continuous level of the point x on fractional row ``y + w`` inside stripe ``(k, k + 1)``; NaN if the
    stripe's boundaries there are missing or inconsistent."""
    idx = k + code_offset
    if idx < 0 or idx + 1 >= tab.shape[1] or y < 0 or y + 1 >= tab.shape[0]:
        return np.nan
    xa0, xb0 = _bounds(tab, y, idx, max_gap, True)
    xa1, xb1 = _bounds(tab, y + 1, idx, max_gap, True)
    if xa0 != xa0 or xa1 != xa1:
        return np.nan
    if not (abs(xa1 - xa0) <= max_row_jump and abs(xb1 - xb0) <= max_row_jump):
        return np.nan
    xa = xa0 + w * (xa1 - xa0)
    xb = xb0 + w * (xb1 - xb0)
    if abs(xb - xa) < 1e-6:
        return np.nan
    return k + (x - xa) / (xb - xa)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _value_slope(img, x, y):  # type: ignore[no-untyped-def]
    """Bilinear value at (x, y) and its slope per row, half the difference of the bilinear values at y - 1
    and y + 1, from the 4 x 2 pixels the three share; NaN where any of the three falls off the image."""
    ix = math.floor(x)
    iy = math.floor(y)
    if ix < 0 or iy < 1 or ix + 1 >= img.shape[1] or iy + 2 >= img.shape[0]:
        return np.nan, np.nan
    tx = x - ix
    ty = y - iy
    r0 = img[iy - 1, ix] + tx * (img[iy - 1, ix + 1] - img[iy - 1, ix])
    r1 = img[iy, ix] + tx * (img[iy, ix + 1] - img[iy, ix])
    r2 = img[iy + 1, ix] + tx * (img[iy + 1, ix + 1] - img[iy + 1, ix])
    r3 = img[iy + 2, ix] + tx * (img[iy + 2, ix + 1] - img[iy + 2, ix])
    va = r0 + ty * (r1 - r0)
    vc = r1 + ty * (r2 - r1)
    vb = r2 + ty * (r3 - r2)
    return vc, 0.5 * (vb - va)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def rect_point(a0, b, disp, base, rr_t, c0, r0z, t0z, zmin, zmax):  # type: ignore[no-untyped-def]
    """World point (mm) of the rectified cam0 direction (a0, b) at disparity ``disp`` (rectified units, baseline
    ``base`` mm): (ok, x, y, z, zr, n2) with ``zr`` = base / disp and ``n2`` = a0^2 + b^2 + 1, so that the range
    from cam0 is ``zr * sqrt(n2)`` mm (``rr_t`` is a rotation); ``ok`` is False behind the cameras or outside
    the depth range ``zmin .. zmax`` (z in cam0's frame)."""
    if not disp > 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    zr = base / disp
    px = c0[0] + zr * (rr_t[0, 0] * a0 + rr_t[0, 1] * b + rr_t[0, 2])
    py = c0[1] + zr * (rr_t[1, 0] * a0 + rr_t[1, 1] * b + rr_t[1, 2])
    pz = c0[2] + zr * (rr_t[2, 0] * a0 + rr_t[2, 1] * b + rr_t[2, 2])
    depth = r0z[0] * px + r0z[1] * py + r0z[2] * pz + t0z
    return depth >= zmin and depth <= zmax, px, py, pz, zr, a0 * a0 + b * b + 1.0


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def put_point(out, status, r, col, ok, px, py, pz):  # type: ignore[no-untyped-def]
    """Write a matched point at (r, col), status ``ST_OK``; or only status ``ST_DEPTH`` when not ``ok``."""
    if not ok:
        status[r, col] = ST_DEPTH
        return False
    out[r, col, 0] = px
    out[r, col, 1] = py
    out[r, col, 2] = pz
    status[r, col] = ST_OK
    return True


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def clear_point(out, epi, sigma, r, col):  # type: ignore[no-untyped-def]
    """No point (yet) at (r, col): NaN xyz, epipolar residual and sigma."""
    out[r, col, 0] = _NAN
    out[r, col, 1] = _NAN
    out[r, col, 2] = _NAN
    epi[r, col] = _NAN
    sigma[r, col] = _NAN


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def cc_match(  # type: ignore[no-untyped-def]
    lev0,
    mask0,
    rect0,
    knot0,
    cross0,
    cross1,
    quantised,
    v0,
    v1rect,
    use_v,
    code_offset,
    geom,
    shift,
    rr_t,
    c0,
    r0z,
    t0z,
    tol,
    zmin,
    zmax,
    quality0,
    noise,
    out,
    epi,
    sigma,
    status,
):
    """Match every cam0 pixel on its rectified row of cam1 and triangulate (world frame, mm).

    ``lev0`` holds the pixels' codes in level units; ``geom`` = (a0min, a1min, bmin, step, baseline_mm);
    ``shift`` = (s0, sx, sy): cam1's row is ``y + s0 + sx * x + sy * y`` (a measured epipolar offset);
    ``tol`` = (max_gap_px, max_row_jump_px, max_own_px, own_margin). ``noise`` = (phase_px, var_quant_px2,
    var_intensity_dn2, 1 / e- per DN, 1 / level step): a continuous code's 1-sigma error is
    ``phase_px sqrt(var_I) / quality`` projector px (the same in both cameras), a quantised code's match is
    off by ``sqrt(var_quant_px2)`` rectified px. ``epi`` receives the epipolar residual (rectified px, NaN
    without v), ``sigma`` each point's 1-sigma error along cam0's ray (mm) and ``status`` the outcome.
    """
    h, w = lev0.shape[0], lev0.shape[1]
    hr = cross1.shape[0]
    a0min, a1min, bmin, step, base = geom[0], geom[1], geom[2], geom[3], geom[4]
    max_gap, max_row_jump, max_own, margin = tol[0], tol[1], tol[2], tol[3]
    nch = min(h, ROW_CHUNKS)
    for ch in prange(nch):
        row = np.empty((w, 2))
        for r in range(ch * h // nch, (ch + 1) * h // nch):
            _map_row(rect0, knot0, r, row)
            for col in range(w):
                clear_point(out, epi, sigma, r, col)
                fu = np.float64(lev0[r, col])
                if not (mask0[r, col] and fu == fu):
                    status[r, col] = ST_NONE
                    continue
                xr0 = row[col, 0]
                yr = row[col, 1]
                y1 = yr + shift[0] + shift[1] * xr0 + shift[2] * yr
                if not (yr >= 0.0 and yr < hr - 1 and y1 >= 0.0 and y1 < hr - 1):
                    status[r, col] = ST_OUTSIDE
                    continue
                iy = int(yr)
                wy = yr - iy
                if quantised:
                    # the pixel's place inside its stripe, from the stripe's boundaries on its own row
                    k = math.floor(fu)
                    fu = _level_at(cross0, iy, wy, xr0, k, code_offset, max_gap, max_row_jump)
                    if not (fu >= k - margin and fu <= k + 1 + margin):
                        status[r, col] = ST_OWN
                        continue
                else:
                    # left-right check: the code must come back to this very pixel on cam0's own row
                    xb = _cross_at(cross0, iy, wy, fu, code_offset, max_gap, max_row_jump, True)
                    if not abs(xb - xr0) <= max_own:
                        status[r, col] = ST_OWN
                        continue
                iy1 = int(y1)
                x1 = _cross_at(cross1, iy1, y1 - iy1, fu, code_offset, max_gap, max_row_jump)
                if x1 != x1:
                    status[r, col] = ST_OTHER
                    continue
                if use_v:
                    fv = np.float64(v0[r, col])
                    vc, dvdy = _value_slope(v1rect, x1, y1)
                    if abs(dvdy) > 1e-6 and fv == fv:
                        epi[r, col] = (fv - vc) / dvdy
                a0 = a0min + xr0 * step
                ok, px, py, pz, zr, n2 = rect_point(a0, bmin + yr * step, a0 - (a1min + x1 * step), base, rr_t, c0,
                                                    r0z, t0z, zmin, zmax)  # fmt: skip
                if not put_point(out, status, r, col, ok, px, py, pz):
                    continue
                # 1-sigma of cam1's match position (rect px), from the code noise and cam1's code gradient there
                if quantised:
                    sx = math.sqrt(noise[1])
                else:
                    q = np.float64(quality0[r, col])
                    var_i = noise[2] + max(0.5 * q, 0.0) * noise[3]
                    su = noise[0] * math.sqrt(var_i) / q * noise[4] if q > 0.0 else np.inf  # level units
                    xa = _cross_at(cross1, iy1, y1 - iy1, math.floor(fu), code_offset, max_gap, max_row_jump)
                    xb = _cross_at(cross1, iy1, y1 - iy1, math.floor(fu) + 1.0, code_offset, max_gap, max_row_jump)
                    per_level = abs(xb - xa) if xa == xa and xb == xb else 1.0
                    sx = math.sqrt(2.0) * su * per_level
                sigma[r, col] = zr * zr * math.sqrt(n2) / base * sx * step  # d(range)/d(disparity) = range zr / base
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def three_view_error(xyz, u0, v0, use_v, proj_r, proj_t, kp, dp, out):  # type: ignore[no-untyped-def]
    """|projected code - decoded code| (projector px, the larger axis) of each point; NaN without a point."""
    h, w = u0.shape[0], u0.shape[1]
    fx, sk, cx = kp[0, 0], kp[0, 1], kp[0, 2]
    fy, cy = kp[1, 1], kp[1, 2]
    for r in prange(h):
        for col in range(w):
            out[r, col] = _NAN
            px = np.float64(xyz[r, col, 0])
            if px != px:
                continue
            py = np.float64(xyz[r, col, 1])
            pz = np.float64(xyz[r, col, 2])
            qx = proj_r[0, 0] * px + proj_r[0, 1] * py + proj_r[0, 2] * pz + proj_t[0]
            qy = proj_r[1, 0] * px + proj_r[1, 1] * py + proj_r[1, 2] * pz + proj_t[1]
            qz = proj_r[2, 0] * px + proj_r[2, 1] * py + proj_r[2, 2] * pz + proj_t[2]
            if qz <= 0.0:
                out[r, col] = np.inf
                continue
            xd, yd, _, _, _, _ = distort_jac(qx / qz, qy / qz, dp)
            e = abs(fx * xd + sk * yd + cx - np.float64(u0[r, col]))
            if use_v:
                e = max(e, abs(fy * yd + cy - np.float64(v0[r, col])))
            out[r, col] = e
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def reject(xyz, err, limit, code, status):  # type: ignore[no-untyped-def]
    """Points whose |err| exceeds ``limit`` (NaN err passes) become NaN with status ``code``."""
    h, w = err.shape[0], err.shape[1]
    for r in prange(h):
        for col in range(w):
            e = abs(np.float64(err[r, col]))
            if status[r, col] == ST_OK and e > limit:
                xyz[r, col, 0] = _NAN
                xyz[r, col, 1] = _NAN
                xyz[r, col, 2] = _NAN
                status[r, col] = code
    return xyz


@njit(nogil=True, cache=True, error_model="numpy")
def sample_codes(code, mask, stride, out):  # type: ignore[no-untyped-def]
    """The finite codes of the decoded pixels of every ``stride``-th row and column, in row order, into
    ``out`` (float32, at least ceil(H / stride) * ceil(W / stride) long); returns how many."""
    h, w = code.shape[0], code.shape[1]
    n = 0
    for r in range(0, h, stride):
        cr = code[r]
        mr = mask[r]
        for c in range(0, w, stride):
            x = cr[c]
            if mr[c] and x - x == 0.0:  # finite
                out[n] = x
                n += 1
    return n


@njit(nogil=True, cache=True, error_model="numpy")
def half_pixel_counts(vals):  # type: ignore[no-untyped-def]
    """Counts of the half-pixel values ``k / 2`` among float32 ``vals`` (index k), with the share of values
    that lie within 1e-3 of a half pixel; an empty count array when any value is below 0 or at 2**23 px and
    above (the caller then sorts)."""
    n = vals.shape[0]
    hi = 0.0
    on = 0
    for i in range(n):
        h2 = np.float64(vals[i]) * 2.0
        k = np.rint(h2)
        if not (k >= 0.0 and k < 16777216.0):
            return 0.0, np.zeros(0, np.int64)
        hi = max(hi, k)
        on += abs(h2 - k) < 2e-3
    cnt = np.zeros(int(hi) + 1, np.int64)
    for i in range(n):
        h2 = np.float64(vals[i]) * 2.0
        k = np.rint(h2)
        if abs(h2 - k) < 2e-3:
            cnt[int(k)] += 1
    return on / max(n, 1), cnt


@njit(nogil=True, cache=True, error_model="numpy")
def on_grid_share(vals, origin, step):  # type: ignore[no-untyped-def]
    """Share of float32 ``vals`` within 1e-3 steps of ``origin + k * step`` (k integer)."""
    n = vals.shape[0]
    on = 0
    for i in range(n):
        k = (np.float64(vals[i]) - origin) / step
        on += abs(k - np.rint(k)) < 1e-3
    return on / max(n, 1)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def mean_step(code, along, every, limit):  # type: ignore[no-untyped-def]
    """Mean |change| of ``code`` between neighbouring pixels along rows (``along`` 1, every ``every``-th row)
    or columns (0, between rows ``i * every`` and ``i * every + 1``, every column: the rows are read whole),
    over finite changes below ``limit``; NaN when there are none."""
    h, w = code.shape[0], code.shape[1]
    nr = (h + every - 1) // every if along == 1 else (h - 2) // every + 1
    sums = np.zeros(nr, np.float64)
    counts = np.zeros(nr, np.int64)
    for i in prange(nr):
        s = 0.0
        n = 0
        if along == 1:
            row = code[i * every]
            for c in range(w - 1):
                d = abs(np.float64(row[c + 1]) - np.float64(row[c]))
                if d < limit:  # False for NaN
                    s += d
                    n += 1
        else:
            a = code[i * every]
            b = code[i * every + 1]
            for c in range(w):
                d = abs(np.float64(b[c]) - np.float64(a[c]))
                if d < limit:
                    s += d
                    n += 1
        sums[i] = s
        counts[i] = n
    n_all = counts.sum()
    return sums.sum() / n_all if n_all > 0 else np.nan


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def status_counts(status, n, out):  # type: ignore[no-untyped-def]
    """Counts of each status value 0..n-1, per row (the caller sums); ``out`` is (H, n) int64."""
    h, w = status.shape[0], status.shape[1]
    for r in prange(h):
        row = status[r]
        for s in range(n):  # one compare-and-add pass per value: vectorised, no store-to-load chain per pixel
            t = np.uint8(s)
            acc = np.int32(0)
            for col in range(w):
                acc += np.int32(row[col] == t)
            out[r, s] = acc
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def isolated_keep_sigma(xyz, sigma, min_nb, const_mm, k_sigma, k_footprint, inv_f, max_sigma, keep):  # type: ignore[no-untyped-def]
    """Keep a point with >= ``min_nb`` of its 8 neighbours within its own jump limit and sigma <= max_sigma.

    The limit of a point is ``const_mm + k_sigma * sigma + k_footprint * z / f`` (``inv_f`` = 1 / f px; a NaN
    sigma adds nothing).
    """
    h, w = xyz.shape[0], xyz.shape[1]
    for r in prange(h):
        for c in range(w):
            keep[r, c] = False
            z = np.float64(xyz[r, c, 2])
            s = np.float64(sigma[r, c])
            if z != z or (s == s and not s <= max_sigma):
                continue
            if min_nb <= 0:  # every point has at least 0 near neighbours: no need to count them
                keep[r, c] = True
                continue
            lim = const_mm + k_footprint * abs(z) * inv_f + (k_sigma * s if s == s else 0.0)
            keep[r, c] = near_neighbours(xyz, r, c, lim * lim) >= min_nb
    return keep


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def agree_keep_sigma(xyz, sigma, max_disagree, min_agree, const_mm, k_sigma, k_footprint, inv_f, max_sigma, keep):  # type: ignore[no-untyped-def]
    """Keep a point whose valid 8-neighbours agree with it: at most ``max_disagree`` lie beyond the jump limit
    of the pair and at least ``min_agree`` within it; missing neighbours count neither way (a hole does not
    grow), and sigma <= max_sigma.

    The limit of a pair is ``const_mm + k_sigma * hypot(sigma, sigma_nb) + k_footprint * z / f`` (``inv_f`` =
    1 / f px; NaN sigmas add nothing).
    """
    h, w = xyz.shape[0], xyz.shape[1]
    for r in prange(h):
        for c in range(w):
            keep[r, c] = False
            z = np.float64(xyz[r, c, 2])
            s = np.float64(sigma[r, c])
            if z != z or (s == s and not s <= max_sigma):
                continue
            s2 = s * s if s == s else 0.0
            base = const_mm + k_footprint * abs(z) * inv_f
            agree = 0
            disagree = 0
            for dr in range(-1, 2):
                rr = r + dr
                if rr < 0 or rr >= h:
                    continue
                for dc in range(-1, 2):
                    cc = c + dc
                    if (dr == 0 and dc == 0) or cc < 0 or cc >= w:
                        continue
                    zn = np.float64(xyz[rr, cc, 2])
                    if zn != zn:
                        continue
                    sn = np.float64(sigma[rr, cc])
                    lim = base + k_sigma * math.sqrt(s2 + (sn * sn if sn == sn else 0.0))
                    ex = np.float64(xyz[rr, cc, 0]) - np.float64(xyz[r, c, 0])
                    ey = np.float64(xyz[rr, cc, 1]) - np.float64(xyz[r, c, 1])
                    ez = zn - z
                    if ex * ex + ey * ey + ez * ez < lim * lim:
                        agree += 1
                    else:
                        disagree += 1
            keep[r, c] = agree >= min_agree and disagree <= max_disagree
    return keep


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def drop_unkept(xyz, sigma, keep):  # type: ignore[no-untyped-def]
    """NaN the points and sigmas where ``keep`` is False (in place); returns how many pixels are kept."""
    h, w = keep.shape[0], keep.shape[1]
    kept = np.zeros(h, np.int64)
    for r in prange(h):
        n = np.int64(0)
        for c in range(w):
            k = keep[r, c]
            n += np.int64(k)
            if not k:
                xyz[r, c, 0] = _NAN
                xyz[r, c, 1] = _NAN
                xyz[r, c, 2] = _NAN
                sigma[r, c] = _NAN
        kept[r] = n
    return kept.sum()


@njit(nogil=True, cache=True)
def mark_codes(u, v, mask, grid, table):  # type: ignore[no-untyped-def]
    """Count in ``table`` (ncv, ncu), uint8, up to 255, the pixels of every (u, v) code cell in the image.

    ``grid`` = (origin u, 1 / step u, origin v, 1 / step v): cell = floor((code - origin) / step + 0.5).
    """
    ncv, ncu = table.shape[0], table.shape[1]
    table[:, :] = 0
    for r in range(u.shape[0]):
        for c in range(u.shape[1]):
            a, b = u[r, c], v[r, c]
            if mask[r, c] and a == a and b == b:
                iu = math.floor((a - grid[0]) * grid[1] + 0.5)
                iv = math.floor((b - grid[2]) * grid[3] + 0.5)
                if 0 <= iu < ncu and 0 <= iv < ncv and table[iv, iu] < 255:
                    table[iv, iu] += 1


@njit(nogil=True, cache=True, parallel=True)
def seen_by_both(u, v, mask, grid, table, reach_u, reach_v, least, seen):  # type: ignore[no-untyped-def]
    """``seen`` = decoded here and a code cell within (reach_u, reach_v) cells decoded by at least ``least``
    pixels of the other camera (``table`` of :func:`mark_codes`); returns how many pixels."""
    h, w = u.shape[0], u.shape[1]
    ncv, ncu = table.shape[0], table.shape[1]
    per = np.zeros(h, np.int64)
    for r in prange(h):
        n = np.int64(0)
        for c in range(w):
            a, b = u[r, c], v[r, c]
            hit = False
            if mask[r, c] and a == a and b == b:
                iu = math.floor((a - grid[0]) * grid[1] + 0.5)
                iv = math.floor((b - grid[2]) * grid[3] + 0.5)
                for jv in range(max(iv - reach_v, 0), min(iv + reach_v + 1, ncv)):
                    for ju in range(max(iu - reach_u, 0), min(iu + reach_u + 1, ncu)):
                        if table[jv, ju] >= least:
                            hit = True
            seen[r, c] = hit
            n += np.int64(hit)
        per[r] = n
    return per.sum()


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _row_entry(yr, a, origin, inv_step, hr, nl):  # type: ignore[no-untyped-def]
    """The (row, level) entry of the tables of :func:`mark_rows` for code ``a`` on rectified row ``yr``
    (rounded); (-1, -1) outside them."""
    iy = math.floor(yr + 0.5)
    il = math.floor((a - origin) * inv_step)
    if 0 <= iy < hr and 0 <= il < nl:
        return iy, il
    return -1, -1


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def mark_rows(u1, mask1, rect1, knot1, origin, inv_step, table, near):  # type: ignore[no-untyped-def]
    """One coded axis: ``table`` (rows, levels) uint8 = 1 where cam1 decodes a code on a rectified row (its
    pixel's rectified row rounded; ``rect1`` / ``knot1`` a map of :func:`_map_row`), level
    ``floor((u - origin) * inv_step)``, else 0; then the marks grown by one level (into ``near``, same shape) and
    one row (back into ``table``): ``table`` = 1 within one row and one level of a mark. (Two threads may store 1
    in one entry: the same value, so no mark is lost.)"""
    h, w = u1.shape[0], u1.shape[1]
    hr, nl = table.shape[0], table.shape[1]
    for r in prange(hr):
        for j in range(nl):
            table[r, j] = 0
    nch = min(h, ROW_CHUNKS)
    for ch in prange(nch):
        row = np.empty((w, 2))
        for r in range(ch * h // nch, (ch + 1) * h // nch):
            _map_row(rect1, knot1, r, row)
            for c in range(w):
                a = np.float64(u1[r, c])
                yr = row[c, 1]
                if mask1[r, c] and a == a and yr == yr:
                    iy, il = _row_entry(yr, a, origin, inv_step, hr, nl)
                    if iy >= 0:
                        table[iy, il] = 1
    for r in prange(hr):
        for j in range(nl):
            near[r, j] = table[r, j] | (table[r, j - 1] if j > 0 else 0) | (table[r, j + 1] if j + 1 < nl else 0)
    for r in prange(hr):
        for j in range(nl):
            table[r, j] = near[r, j] | (near[r - 1, j] if r > 0 else 0) | (near[r + 1, j] if r + 1 < hr else 0)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def seen_on_rows(u0, mask0, rect0, knot0, origin, inv_step, near, xyz, seen):  # type: ignore[no-untyped-def]
    """One coded axis: ``seen`` = a decoded cam0 pixel whose code cam1 decodes on the same rectified row, within
    one row and one level (``near``: the ``table`` :func:`mark_rows` leaves); returns (how many pixels, how many
    of them hold a point in ``xyz``). A projector column meets an epipolar plane in one ray from the projector,
    whose first surface point is what both cameras see there."""
    h, w = u0.shape[0], u0.shape[1]
    hr, nl = near.shape[0], near.shape[1]
    per = np.zeros((h, 2), np.int64)
    nch = min(h, ROW_CHUNKS)
    for ch in prange(nch):
        row = np.empty((w, 2))
        for r in range(ch * h // nch, (ch + 1) * h // nch):
            _map_row(rect0, knot0, r, row)
            n = np.int64(0)
            k = np.int64(0)
            for col in range(w):
                a = np.float64(u0[r, col])
                yr = row[col, 1]
                hit = False
                if mask0[r, col] and a == a and yr == yr:
                    iy, il = _row_entry(yr, a, origin, inv_step, hr, nl)
                    hit = iy >= 0 and near[iy, il] != 0
                seen[r, col] = hit
                n += np.int64(hit)
                k += np.int64(hit and xyz[r, col, 2] == xyz[r, col, 2])
            per[r, 0] = n
            per[r, 1] = k
    return per[:, 0].sum(), per[:, 1].sum()


@njit(nogil=True, cache=True, parallel=True)
def count_points_in(xyz, seen):  # type: ignore[no-untyped-def]
    """How many pixels where ``seen`` holds a point (finite z)."""
    h, w = seen.shape[0], seen.shape[1]
    per = np.zeros(h, np.int64)
    for r in prange(h):
        n = np.int64(0)
        for c in range(w):
            if seen[r, c] and xyz[r, c, 2] == xyz[r, c, 2]:
                n += 1
        per[r] = n
    return per.sum()
