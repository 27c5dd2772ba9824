"""numba kernels of camera-camera matching by code cells (private; see ``stereo.py``).

With both axes coded and quantised (Gray only), a pair of codes ``(u, v)`` names one cell of the projector
(``ku x kv`` codes when the stripes are finer than a camera pixel). Each camera sees a cell as a small patch
of pixels, and the centroids of the two patches are images of one and the same surface region (centroids are
preserved by the locally affine map between the views). The matching is then a lookup, not a search:

1. ``cell_sums`` adds up, per cell and per camera, the pixels and their rectified coordinates.
2. ``cell_raw`` takes each cell's disparity (cam0 centroid minus cam1 centroid, along the rectified rows)
   and its epipolar residual (cam1 row minus cam0 row); ``cell_window`` fits a plane ``d = d0 + gx dx + gy dy``
   to the disparities of the cell and its neighbours in a square window (weighted by their pixel counts),
   about the cell's own cam0 centroid, and ``cell_fits_robust`` refits the cells whose window holds a
   disparity jump from their neighbours on the same surface.
3. ``cell_match`` gives every cam0 pixel the disparity of its cell's plane at its own position, and
   triangulates.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.reconstruct._geom_kernels import NAN32 as _NAN
from appliance.reconstruct._stereo_kernels import (
    ST_NONE,
    ST_OTHER,
    ST_OUTSIDE,
    ST_OWN,
    _map_at,
    _map_row,
    clear_point,
    put_point,
    rect_point,
)

FAST = {"contract", "arcp", "reassoc", "nsz", "afn"}
"""fastmath flags of the per-pixel triangulation: fused multiply-adds, reciprocals and reassociation, but no
'nnan' / 'ninf' (the kernels test for NaN)."""

EXACT_HELPERS = ("_row_cells", "_row_cells_split", "_map_row")
"""Helpers that ``cell_match`` (fastmath) calls and that set ``fastmath=False`` themselves. numba compiles a callee
that does not set the option with its caller's fastmath flags, and keeps one version per signature: whichever
kernel compiled it first would decide, for every kernel, whether a code on a cell edge stays in its cell (a fused
multiply-add moved the lowest edge to -6e-8 and dropped it) and how the rectification map rounds."""

FIT_COLS = 6
"""Columns of a cell's fit: d0, gx, gy (disparity plane about the cell's cam0 centroid, rectified px), the
variance of d0 per unit variance (px^2 per px^2 at unit weight), mean epipolar residual (px), total weight."""


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _floor_div(i, k, inv_k):  # type: ignore[no-untyped-def]
    """i // k for int32 0 <= i < 2**24 and k >= 1 (``inv_k`` = 1 / k in float32): a float32 quotient, then an
    exact integer correction (selects only, so a loop over pixels vectorises; an integer division does not)."""
    q = np.int32(np.float32(i) * inv_k)
    q = q + np.int32(1) if (q + np.int32(1)) * k <= i else q
    return q - np.int32(1) if q * k > i else q


@njit(nogil=True, cache=True, error_model="numpy", fastmath=False)  # never inherited: see EXACT_HELPERS
def _row_cells(ur, vr, mr, grid, ncu, ncv, kr):  # type: ignore[no-untyped-def]
    """Cell index of every pixel of a row (int32, -1: none) from its float32 codes ``ur``, ``vr`` and mask
    ``mr`` under ``grid`` = (origin_u, 1/step_u, origin_v, 1/step_v, ku, kv), in one vectorised pass. Every
    kernel looks cells up here, in float32 (the codes' own precision), so that a code on a cell boundary (a
    coarser stripe's centre) falls in one and the same cell everywhere."""
    ou, iu = np.float32(grid[0]), np.float32(grid[1])
    ov, iv = np.float32(grid[2]), np.float32(grid[3])
    ku, kv = np.int32(grid[4]), np.int32(grid[5])
    hu, hv = np.float32(ncu * ku), np.float32(ncv * kv)
    half = np.float32(0.5)
    nu = np.int32(ncu)
    none = np.int32(-1)
    if ku == 1 and kv == 1:
        for c in range(kr.shape[0]):
            fi = (ur[c] - ou) * iu + half
            fj = (vr[c] - ov) * iv + half
            good = mr[c] & (fi >= 0.0) & (fj >= 0.0) & (fi < hu) & (fj < hv)  # NaN codes fail too
            kr[c] = np.int32(fj if good else 0.0) * nu + np.int32(fi if good else 0.0) if good else none
        return
    iku, ikv = np.float32(1.0) / np.float32(ku), np.float32(1.0) / np.float32(kv)
    for c in range(kr.shape[0]):
        fi = (ur[c] - ou) * iu + half
        fj = (vr[c] - ov) * iv + half
        good = mr[c] & (fi >= 0.0) & (fj >= 0.0) & (fi < hu) & (fj < hv)
        cu = _floor_div(np.int32(fi if good else 0.0), ku, iku)
        cv = _floor_div(np.int32(fj if good else 0.0), kv, ikv)
        kr[c] = cv * nu + cu if good else none


@njit(nogil=True, cache=True, error_model="numpy")
def _sums_one(u, v, mask, rect, knot, grid, ncu, ncv, cnt, acc):  # type: ignore[no-untyped-def]
    for k in range(cnt.shape[0]):
        cnt[k] = 0
        acc[k, 0] = 0.0
        acc[k, 1] = 0.0
    h, w = u.shape[0], u.shape[1]
    kr = np.empty(w, np.int32)
    row = np.empty((w, 2))
    hl = w - w // 2  # the left half's length (the right half's or one more)
    for r in range(h):
        _row_cells(u[r], v[r], mask[r], grid, ncu, ncv, kr)  # first the cells (vectorised), then a tight scatter
        _map_row(rect, knot, r, row)
        # the left and the right half of the row in turn: two independent chains of additions (neighbouring
        # pixels often share a cell, and each addition to it waits for the last); no branch on a cell's first
        # pixel (the cell changes every pixel or two, unpredictably)
        for c in range(hl):
            for half in range(2):
                cc = c + half * hl
                if cc < w:
                    k = kr[cc]
                    a = np.float32(row[cc, 0])
                    if k >= 0 and a == a:
                        acc[k, 0] += a
                        acc[k, 1] += np.float32(row[cc, 1])
                        cnt[k] += 1


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def cell_sums(u0, v0, mask0, rect0, knot0, u1, v1, mask1, rect1, knot1, grid, ncu, ncv, cnt0, acc0, cnt1, acc1):  # type: ignore[no-untyped-def]
    """Per cell: pixel count (``cnt``, int32, (N,)) and sums of rectified (x, y) (``acc``, float32, (N, 2)) of
    both cameras, one camera per thread."""
    for t in prange(2):
        if t == 0:
            _sums_one(u0, v0, mask0, rect0, knot0, grid, ncu, ncv, cnt0, acc0)
        else:
            _sums_one(u1, v1, mask1, rect1, knot1, grid, ncu, ncv, cnt1, acc1)


SPLIT_UNIT = 4
"""``cell_sums_split``: counts per whole pixel (a pixel on a boundary of both axes counts a quarter to each of
its four cells)."""


@njit(nogil=True, cache=True, error_model="numpy", fastmath=False)  # never inherited: see EXACT_HELPERS
def _row_cells_split(ur, vr, mr, grid, ncu, ncv, kr, sr):  # type: ignore[no-untyped-def]
    """As ``_row_cells``, and per pixel (``sr``, uint8) whether its code lies half way between two cells (the
    centre of a coarser stripe: a pixel that dropped its finest Gray bits, on the edge between the two halves
    of that stripe): bit 0 along u (``kr`` is then the upper cell, ``kr - 1`` the lower one), bit 1 along v
    (``kr - ncu``). A code half way between two codes of one cell (``ku``, ``kv`` > 1) is not split. float32
    selects only, so that the loop vectorises."""
    ou, iu = np.float32(grid[0]), np.float32(grid[1])
    ov, iv = np.float32(grid[2]), np.float32(grid[3])
    ku, kv = np.int32(grid[4]), np.int32(grid[5])
    iku, ikv = np.float32(1.0) / np.float32(ku), np.float32(1.0) / np.float32(kv)
    hu, hv = np.float32(ncu * ku), np.float32(ncv * kv)
    half = np.float32(0.5)
    eps = np.float32(1e-3)
    zero = np.float32(0.0)
    nu = np.int32(ncu)
    for c in range(kr.shape[0]):
        fi = (ur[c] - ou) * iu + half
        fj = (vr[c] - ov) * iv + half
        mi = np.floor(fi + half)  # the nearest whole number
        mj = np.floor(fj + half)
        on_i = (abs(fi - mi) < eps) & (mi < hu)
        on_j = (abs(fj - mj) < eps) & (mj < hv)
        ti = mi if on_i else np.floor(fi)
        tj = mj if on_j else np.floor(fj)
        good = mr[c] & (fi >= zero) & (fj >= zero) & (ti < hu) & (tj < hv)  # NaN codes fail too
        ii = np.int32(ti if good else zero)
        jj = np.int32(tj if good else zero)
        cu = _floor_div(ii, ku, iku)
        cv = _floor_div(jj, kv, ikv)
        kr[c] = cv * nu + cu if good else np.int32(-1)
        su = good & on_i & (ii >= ku) & (ii == cu * ku)
        sv = good & on_j & (jj >= kv) & (jj == cv * kv)
        sr[c] = np.uint8(su) | (np.uint8(sv) << np.uint8(1))


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _add(cnt, acc, k, q, a, b):  # type: ignore[no-untyped-def]
    cnt[k] += q
    acc[k, 0] += np.float32(q) * a
    acc[k, 1] += np.float32(q) * b


@njit(nogil=True, cache=True, error_model="numpy")
def _sums_split_one(u, v, mask, rect, knot, grid, ncu, ncv, cnt, acc):  # type: ignore[no-untyped-def]
    for k in range(cnt.shape[0]):
        cnt[k] = 0
        acc[k, 0] = 0.0
        acc[k, 1] = 0.0
    h, w = u.shape[0], u.shape[1]
    kr = np.empty(w, np.int32)
    sr = np.empty(w, np.uint8)
    row = np.empty((w, 2))
    nu = np.int32(ncu)
    for r in range(h):
        _row_cells_split(u[r], v[r], mask[r], grid, ncu, ncv, kr, sr)
        _map_row(rect, knot, r, row)
        for c in range(w):
            k = kr[c]
            a = np.float32(row[c, 0])
            if k < 0 or a != a:
                continue
            b = np.float32(row[c, 1])
            s = sr[c]
            if s == 0:
                _add(cnt, acc, k, np.int32(4), a, b)
            elif s == 1:
                _add(cnt, acc, k, np.int32(2), a, b)
                _add(cnt, acc, k - 1, np.int32(2), a, b)
            elif s == 2:
                _add(cnt, acc, k, np.int32(2), a, b)
                _add(cnt, acc, k - nu, np.int32(2), a, b)
            else:
                _add(cnt, acc, k, np.int32(1), a, b)
                _add(cnt, acc, k - 1, np.int32(1), a, b)
                _add(cnt, acc, k - nu, np.int32(1), a, b)
                _add(cnt, acc, k - nu - 1, np.int32(1), a, b)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def cell_sums_split(u0, v0, mask0, rect0, knot0, u1, v1, mask1, rect1, knot1, grid, ncu, ncv, cnt0, acc0, cnt1, acc1):  # type: ignore[no-untyped-def]
    """As ``cell_sums``, but a pixel whose code lies half way between two cells (``_row_cells_split``) counts
    half to each (a quarter to each of four on both axes): counts in ``SPLIT_UNIT`` per pixel, ``acc`` the
    sums of rectified (x, y) with those weights. Rounding such a code into one cell (``cell_sums``) moves that
    cell's centroid towards its neighbour by up to half the band of such pixels, differently in the two
    cameras; split, the error is second order in the band's width."""
    for t in prange(2):
        if t == 0:
            _sums_split_one(u0, v0, mask0, rect0, knot0, grid, ncu, ncv, cnt0, acc0)
        else:
            _sums_split_one(u1, v1, mask1, rect1, knot1, grid, ncu, ncv, cnt1, acc1)


RAW_W, RAW_D, RAW_E, RAW_HI, RAW_LO, RAW_X, RAW_Y = 0, 1, 2, 3, 4, 5, 6
N_RAW = 7
"""Planes of ``cell_raw``'s output: weight, disparity, epipolar residual, disparity or -inf, or +inf, cam0's
centroid x and y (NaN where cam0 misses the cell)."""
N_MOM = 8
"""Planes of a moment pass: sum w, w du, w du^2, w d, w du d, w e (du: lattice offset), max d, min d."""


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _one_sided(cnt0, cnt1, k):  # type: ignore[no-untyped-def]
    return (cnt0[k] == 0) != (cnt1[k] == 0)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _unmatched(raw, cv, cu):  # type: ignore[no-untyped-def]
    """A cell that is not matched: no weight, and out of the window's disparity span."""
    raw[RAW_W, cv, cu] = 0.0
    raw[RAW_D, cv, cu] = 0.0
    raw[RAW_E, cv, cu] = 0.0
    raw[RAW_HI, cv, cu] = -np.inf
    raw[RAW_LO, cv, cu] = np.inf


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def cell_raw(cnt0, acc0, cnt1, acc1, ncu, ncv, edge, unit, raw):  # type: ignore[no-untyped-def]
    """Per cell seen by both cameras: weight ``n0 n1 / (n0 + n1)`` (inverse variance of the disparity, up to a
    constant; n in pixels: the counts over ``unit``, the counts per pixel), disparity (cam0 centroid x - cam1
    centroid x), epipolar residual (cam1 centroid y - cam0 centroid y), in rectified grid px; weight 0
    elsewhere. ``raw`` is (N_RAW, ncv, ncu) float32 (``RAW_*``)."""
    for cv in prange(ncv):
        for cu in range(ncu):
            k = cv * ncu + cu
            n0 = cnt0[k]
            n1 = cnt1[k]
            if n0 == 0:
                raw[RAW_X, cv, cu] = _NAN
                raw[RAW_Y, cv, cu] = _NAN
            else:
                f0 = 1.0 / np.float64(n0)
                raw[RAW_X, cv, cu] = np.float64(acc0[k, 0]) * f0
                raw[RAW_Y, cv, cu] = np.float64(acc0[k, 1]) * f0
            if n0 == 0 or n1 == 0:
                _unmatched(raw, cv, cu)
                continue
            if edge and (
                (cu > 0 and _one_sided(cnt0, cnt1, k - 1))
                or (cu + 1 < ncu and _one_sided(cnt0, cnt1, k + 1))
                or (cv > 0 and _one_sided(cnt0, cnt1, k - ncu))
                or (cv + 1 < ncv and _one_sided(cnt0, cnt1, k + ncu))
            ):  # partly hidden from one camera: its two centroids are not images of one region
                _unmatched(raw, cv, cu)
                continue
            f0 = 1.0 / np.float64(n0)
            f1 = 1.0 / np.float64(n1)
            d = np.float64(acc0[k, 0]) * f0 - np.float64(acc1[k, 0]) * f1
            raw[RAW_W, cv, cu] = np.float64(n0) * np.float64(n1) / (np.float64(n0 + n1) * unit)
            raw[RAW_D, cv, cu] = d
            raw[RAW_E, cv, cu] = np.float64(acc1[k, 1]) * f1 - np.float64(acc0[k, 1]) * f0
            raw[RAW_HI, cv, cu] = d
            raw[RAW_LO, cv, cu] = d
    return raw


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _tap(dst, src, f, off, lo, hi):  # type: ignore[no-untyped-def]
    """dst[x] += f * src[x + off] for x in lo .. hi - 1 (one vectorised loop: views, no index arithmetic)."""
    dv = dst[lo:hi]
    sv = src[lo + off : hi + off]
    for x in range(dv.shape[0]):
        dv[x] += f * sv[x]


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _tap2(dst, a, b, f, off, lo, hi):  # type: ignore[no-untyped-def]
    """dst[x] += f * a[x + off] * b[x + off]."""
    dv = dst[lo:hi]
    av = a[lo + off : hi + off]
    bv = b[lo + off : hi + off]
    for x in range(dv.shape[0]):
        dv[x] += f * av[x] * bv[x]


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _tap_max(dst, src, off, lo, hi):  # type: ignore[no-untyped-def]
    dv = dst[lo:hi]
    sv = src[lo + off : hi + off]
    for x in range(dv.shape[0]):
        dv[x] = np.fmax(dv[x], sv[x])


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _tap_min(dst, src, off, lo, hi):  # type: ignore[no-untyped-def]
    dv = dst[lo:hi]
    sv = src[lo + off : hi + off]
    for x in range(dv.shape[0]):
        dv[x] = np.fmin(dv[x], sv[x])


@njit(nogil=True, cache=True, error_model="numpy")
def _row_moments(raw, cv, radius, mom):  # type: ignore[no-untyped-def]
    """The along-u window moments of cell row ``cv`` of ``raw`` into ``mom`` (N_MOM, ncu), see ``N_MOM``."""
    ncu = raw.shape[2]
    for p in range(N_MOM):
        v = np.float32(-np.inf if p == 6 else (np.inf if p == 7 else 0.0))
        row = mom[p]
        for x in range(ncu):
            row[x] = v
    w = raw[RAW_W, cv]
    d = raw[RAW_D, cv]
    for du in range(-radius, radius + 1):
        lo = max(0, -du)
        hi = min(ncu, ncu - du)
        fd = np.float32(du)
        _tap(mom[0], w, np.float32(1.0), du, lo, hi)
        _tap(mom[1], w, fd, du, lo, hi)
        _tap(mom[2], w, fd * fd, du, lo, hi)
        _tap2(mom[3], w, d, np.float32(1.0), du, lo, hi)
        _tap2(mom[4], w, d, fd, du, lo, hi)
        _tap2(mom[5], w, raw[RAW_E, cv], np.float32(1.0), du, lo, hi)
        _tap_max(mom[6], raw[RAW_HI, cv], du, lo, hi)
        _tap_min(mom[7], raw[RAW_LO, cv], du, lo, hi)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _slide(acc, mom, jv, sign):  # type: ignore[no-untyped-def]
    """Add (``sign`` 1) or remove (-1) row ``jv``'s moments to the running column sums ``acc`` (N_ACC, ncu):
    m0, m1, m2, m3, m4, m5 and j m0, j m1, j m3, j^2 m0 (j: the absolute cell row, float64 keeps them exact
    enough to subtract)."""
    fj = np.float64(jv)
    for x in range(acc.shape[1]):
        m0 = sign * np.float64(mom[0, x])
        m1 = sign * np.float64(mom[1, x])
        m3 = sign * np.float64(mom[3, x])
        acc[0, x] += m0
        acc[1, x] += m1
        acc[2, x] += sign * np.float64(mom[2, x])
        acc[3, x] += m3
        acc[4, x] += sign * np.float64(mom[4, x])
        acc[5, x] += sign * np.float64(mom[5, x])
        acc[6, x] += fj * m0
        acc[7, x] += fj * m1
        acc[8, x] += fj * m3
        acc[9, x] += fj * fj * m0


N_ACC = 10
"""Running column sums of :func:`_slide`."""


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _lattice_step(raw, ncu, ncv, cu, cv, along_u):  # type: ignore[no-untyped-def]
    """cam0's centroid step per lattice step at cell (cu, cv), along u or v: central, else one-sided."""
    xc = np.float64(raw[RAW_X, cv, cu])
    yc = np.float64(raw[RAW_Y, cv, cu])
    xp = yp = xm = ym = np.nan
    if along_u:
        if cu + 1 < ncu:
            xp, yp = np.float64(raw[RAW_X, cv, cu + 1]), np.float64(raw[RAW_Y, cv, cu + 1])
        if cu > 0:
            xm, ym = np.float64(raw[RAW_X, cv, cu - 1]), np.float64(raw[RAW_Y, cv, cu - 1])
    else:
        if cv + 1 < ncv:
            xp, yp = np.float64(raw[RAW_X, cv + 1, cu]), np.float64(raw[RAW_Y, cv + 1, cu])
        if cv > 0:
            xm, ym = np.float64(raw[RAW_X, cv - 1, cu]), np.float64(raw[RAW_Y, cv - 1, cu])
    if xp == xp and xm == xm:
        return 0.5 * (xp - xm), 0.5 * (yp - ym)
    if xp == xp:
        return xp - xc, yp - yc
    if xm == xm:
        return xc - xm, yc - ym
    return np.nan, np.nan


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _store_plane(fits, k, d0, gu, gv, inv00, e, m, raw, ncu, ncv, cu, cv):  # type: ignore[no-untyped-def]
    """Store a fitted plane in lattice coordinates as a plane in cam0's rectified pixels about the centroid."""
    jxu, jyu = _lattice_step(raw, ncu, ncv, cu, cv, True)
    jxv, jyv = _lattice_step(raw, ncu, ncv, cu, cv, False)
    det = jxu * jyv - jxv * jyu
    gx = 0.0
    gy = 0.0
    if det == det and abs(det) > 1e-6:
        # d = d0 + (gu, gv) . dq with dp = J dq: (gx, gy) = J^-T (gu, gv)
        gx = (jyv * gu - jyu * gv) / det
        gy = (-jxv * gu + jxu * gv) / det
    fits[k, 0] = d0
    fits[k, 1] = gx
    fits[k, 2] = gy
    fits[k, 3] = inv00
    fits[k, 4] = e
    fits[k, 5] = m


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _plane_solve(sw, su, sv, suu, suv, svv, sd, sdu, sdv):  # type: ignore[no-untyped-def]
    """Weighted least squares of d on (1, du, dv) from its sums: (ok, d0, gu, gv, [inverse normal matrix]_00);
    ``ok`` False when the normal matrix is (near) singular (the cells lie on a line)."""
    c00 = suu * svv - suv * suv
    c01 = sv * suv - su * svv
    c02 = su * suv - sv * suu
    det = sw * c00 + su * c01 + sv * c02
    if not det > 1e-6 * sw * sw * sw:
        return False, 0.0, 0.0, 0.0, 0.0
    c11 = sw * svv - sv * sv
    c12 = su * sv - sw * suv
    c22 = sw * suu - su * su
    idet = 1.0 / det
    d0 = (c00 * sd + c01 * sdu + c02 * sdv) * idet
    gu = (c01 * sd + c11 * sdu + c12 * sdv) * idet
    gv = (c02 * sd + c12 * sdu + c22 * sdv) * idet
    return True, d0, gu, gv, c00 * idet


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def cell_window(raw, radius, span, nch, fits):  # type: ignore[no-untyped-def]
    """The plane of every cell whose (2 radius + 1)^2 window holds no jump (disparities within ``span`` px),
    from the window's weighted moments: along u per cell row (:func:`_row_moments`), then along v as running
    sums over the window's rows (each row added once and removed once). ``fits[k, 5]`` = -1 marks a cell that
    needs the robust fit, NaN ``fits[k, 0]`` one seen by a single camera. ``fits`` is (N, FIT_COLS) float32,
    see there; the cell rows are taken in ``nch`` contiguous chunks."""
    ncv, ncu = raw.shape[1], raw.shape[2]
    nw = 2 * radius + 1
    for ch in prange(nch):
        a = ch * ncv // nch
        b = (ch + 1) * ncv // nch
        if a >= b:
            continue
        ring = np.empty((nw, N_MOM, ncu), np.float32)  # row moments, row j in slot j % nw
        acc = np.zeros((N_ACC, ncu), np.float64)
        hi = np.empty(ncu, np.float32)
        lo = np.empty(ncu, np.float32)
        for jv in range(max(0, a - radius), min(ncv, a + radius)):
            _row_moments(raw, jv, radius, ring[jv % nw])
            _slide(acc, ring[jv % nw], jv, 1.0)
        for cv in range(a, b):
            jn = cv + radius
            if jn < ncv:
                _row_moments(raw, jn, radius, ring[jn % nw])
                _slide(acc, ring[jn % nw], jn, 1.0)
            hi[:] = -np.inf
            lo[:] = np.inf
            for jv in range(max(0, cv - radius), min(ncv, cv + radius + 1)):
                _tap_max(hi, ring[jv % nw, 6], 0, 0, ncu)
                _tap_min(lo, ring[jv % nw, 7], 0, 0, ncu)
            c = np.float64(cv)
            for cu in range(ncu):
                k = cv * ncu + cu
                if raw[RAW_W, cv, cu] == 0.0:
                    fits[k, 0] = _NAN
                    fits[k, 5] = 0.0
                    continue
                if not hi[cu] - lo[cu] <= span:
                    fits[k, 0] = _NAN
                    fits[k, 5] = -1.0
                    continue
                sw = acc[0, cu]
                sjw = acc[6, cu]
                sv = sjw - c * sw  # sum of w dv about this row
                suv = acc[7, cu] - c * acc[1, cu]
                svv = acc[9, cu] - 2.0 * c * sjw + c * c * sw
                sdv = acc[8, cu] - c * acc[3, cu]
                ok, d0, gu, gv, inv00 = _plane_solve(sw, acc[1, cu], sv, acc[2, cu], suv, svv, acc[3, cu],
                                                     acc[4, cu], sdv)  # fmt: skip
                if not ok:
                    fits[k, 0] = _NAN
                    fits[k, 5] = -1.0
                    continue
                _store_plane(fits, k, d0, gu, gv, inv00, acc[5, cu] / sw, sw, raw, ncu, ncv, cu, cv)
            jo = cv - radius
            if jo >= 0:
                _slide(acc, ring[jo % nw], jo, -1.0)
    return fits


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def cell_fits_robust(raw, ncu, ncv, jump, fits):  # type: ignore[no-untyped-def]
    """The plane of every cell marked by ``cell_window`` (a jump in its window), over its 3 x 3 neighbours whose
    disparity lies within ``jump`` px of its own (the same surface); their weighted mean with 3; none (NaN)
    with fewer."""
    for cv in prange(ncv):
        for cu in range(ncu):
            k = cv * ncu + cu
            if fits[k, 5] != -1.0:
                continue
            d0 = np.float64(raw[RAW_D, cv, cu])
            sw = su = sv = suu = suv = svv = sd = sud = svd = se = 0.0
            m = 0
            for dv in range(-1, 2):
                jv = cv + dv
                if jv < 0 or jv >= ncv:
                    continue
                for du in range(-1, 2):
                    ju = cu + du
                    if ju < 0 or ju >= ncu:
                        continue
                    wk = np.float64(raw[RAW_W, jv, ju])
                    dd = np.float64(raw[RAW_D, jv, ju]) - d0
                    if wk == 0.0 or not abs(dd) <= jump:
                        continue
                    m += 1
                    sw += wk
                    su += wk * du
                    sv += wk * dv
                    suu += wk * du * du
                    suv += wk * du * dv
                    svv += wk * dv * dv
                    sd += wk * dd
                    sud += wk * du * dd
                    svd += wk * dv * dd
                    se += wk * np.float64(raw[RAW_E, jv, ju])
            ok = False
            a0 = gu = gv = inv00 = 0.0
            if m >= 4:
                ok, a0, gu, gv, inv00 = _plane_solve(sw, su, sv, suu, suv, svv, sd, sud, svd)
            if not ok:
                if m < 3:  # not on one surface with any two neighbours: on an edge (its patches mix two surfaces)
                    fits[k, 0] = _NAN
                    fits[k, 5] = 0.0
                    continue
                a0 = sd / sw
                gu = gv = 0.0
                inv00 = 1.0 / sw
            _store_plane(fits, k, d0 + a0, gu, gv, inv00, se / sw, sw, raw, ncu, ncv, cu, cv)
    return fits


@njit(nogil=True, cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def cell_match(  # type: ignore[no-untyped-def]
    u0,
    v0,
    mask0,
    rect0,
    knot0,
    grid,
    ncu,
    ncv,
    cen_x,
    cen_y,
    fits,
    own_px,
    var_unit,
    geom,
    rr_t,
    c0,
    r0z,
    t0z,
    zmin,
    zmax,
    out,
    epi,
    sigma,
    status,
    split=False,
):
    """Every cam0 pixel: the disparity of its cell's plane at the pixel, triangulated (world frame, mm).

    ``split``: a pixel whose code lies half way between cells (``_row_cells_split``) takes the one of them
    whose cam0 centroid is nearest.

    ``cen_x``, ``cen_y`` (N,): cam0's centroid of each cell (the ``RAW_X``/``RAW_Y`` planes, flat).
    ``own_px``: a pixel further than this from its cell's cam0 centroid is not where its code says (a code
    seen twice, or an edge) and is rejected. ``geom`` = (a0min, a1min, bmin, step, baseline_mm). ``epi``
    receives the cell's epipolar residual (rectified px), ``sigma`` each point's 1-sigma error along cam0's
    ray (mm) and ``status`` the outcome (the codes of ``_stereo_kernels``).
    """
    h, w = u0.shape[0], u0.shape[1]
    a0min, a1min, bmin, step, base = geom[0], geom[1], geom[2], geom[3], geom[4]
    own2 = np.float32(own_px * own_px)
    da = a0min - a1min
    sfac = math.sqrt(var_unit) * step / base  # d(range)/d(disparity) = range zr / base = zr^2 sqrt(n2) / base
    nch = min(h, 32)
    for ch in prange(nch):
        kr = np.empty(w, np.int32)
        sr = np.zeros(w, np.uint8)
        row = np.empty((w, 2))
        for r in range(ch * h // nch, (ch + 1) * h // nch):
            _map_row(rect0, knot0, r, row)
            if split:
                _row_cells_split(u0[r], v0[r], mask0[r], grid, ncu, ncv, kr, sr)
            else:
                _row_cells(u0[r], v0[r], mask0[r], grid, ncu, ncv, kr)
            for col in range(w):
                clear_point(out, epi, sigma, r, col)
                k = kr[col]
                if k < 0:
                    status[r, col] = ST_NONE
                    continue
                xr0 = np.float32(row[col, 0])  # the pixel's offset from its cell in float32: fewer conversions
                yr = np.float32(row[col, 1])
                s = sr[col]
                if s != 0 and xr0 == xr0:  # between cells: the nearest centroid of cam0 that has a plane
                    best = np.float32(np.inf)
                    kb = k
                    for alt in range(4):
                        if (alt & 1 and not s & 1) or (alt & 2 and not s & 2):
                            continue
                        ka = k - (alt & 1) - (alt >> 1) * ncu
                        ca = cen_x[ka]
                        if ca == ca and fits[ka, 0] == fits[ka, 0]:
                            da2 = (xr0 - ca) * (xr0 - ca) + (yr - cen_y[ka]) * (yr - cen_y[ka])
                            if da2 < best:
                                best = da2
                                kb = ka
                    k = kb
                cx = cen_x[k]
                if xr0 != xr0 or cx != cx:
                    status[r, col] = ST_OUTSIDE
                    continue
                dx = xr0 - cx
                dy = yr - cen_y[k]
                if dx * dx + dy * dy > own2:
                    status[r, col] = ST_OWN
                    continue
                d = fits[k, 0]
                if d != d:
                    status[r, col] = ST_OTHER
                    continue
                disp = da + np.float64(d + fits[k, 1] * dx + fits[k, 2] * dy) * step
                epi[r, col] = fits[k, 4]
                ok, px, py, pz, zr, n2 = rect_point(a0min + xr0 * step, bmin + yr * step, disp, base, rr_t, c0, r0z,
                                                    t0z, zmin, zmax)  # fmt: skip
                if not put_point(out, status, r, col, ok, px, py, pz):
                    continue
                sigma[r, col] = np.float32(zr * zr * sfac) * math.sqrt(np.float32(n2) * fits[k, 3])  # float32 sqrt
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def sub_plane(epi, rect0, knot0, shift):  # type: ignore[no-untyped-def]
    """epi -= s0 + sx x + sy y (a fitted epipolar offset, rectified px; (x, y) from ``rect0``, knots every
    ``knot0`` px) in place; NaN stays NaN."""
    h, w = epi.shape[0], epi.shape[1]
    for r in prange(h):
        for c in range(w):
            x, y = _map_at(rect0, knot0, r, c)
            epi[r, c] -= shift[0] + shift[1] * np.float32(x) + shift[2] * np.float32(y)
    return epi


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def code_max(u, v, mask):  # type: ignore[no-untyped-def]
    """Largest decoded u and v (0 where none, or where every decoded code lies below 0), in one pass.

    The maxima run over the codes' float32 bits as int32: for values at or above 0 the order is the same, a
    value below 0 is a negative integer and loses to the start, 0, as it does to 0.0. An integer maximum
    vectorises; a float one runs a pixel at a time (3.4x slower: 1.3 against 0.4 ms for 1920x1280)."""
    h, w = u.shape[0], u.shape[1]
    top = np.empty((h, 2), np.int32)
    for r in prange(h):
        mr = mask[r]
        for a in range(2):
            bits = (u[r] if a == 0 else v[r]).view(np.int32)
            m = np.int32(0)
            for c in range(w):
                m = max(m, bits[c] if mr[c] else np.int32(0))
            top[r, a] = m
    best = np.zeros(2, np.int32)
    for r in range(h):
        best[0] = max(best[0], top[r, 0])
        best[1] = max(best[1], top[r, 1])
    hi = best.view(np.float32)
    return np.float64(hi[0]), np.float64(hi[1])


@njit(nogil=True, cache=True, error_model="numpy")
def sample_level_codes(code, mask, levels, stride, out, out_lev):  # type: ignore[no-untyped-def]
    """The finite codes of the decoded pixels of every ``stride``-th row and column, in row order, into
    ``out`` (float32), with each one's count of dropped finest Gray bits (``levels``, uint8 (H, W)) into
    ``out_lev`` (uint8; both at least ceil(H / stride) * ceil(W / stride) long); returns how many, and how many
    of them kept every bit (level 0)."""
    h, w = code.shape[0], code.shape[1]
    n = 0
    n0 = 0
    for r in range(0, h, stride):
        cr = code[r]
        mr = mask[r]
        lr = levels[r]
        for c in range(0, w, stride):
            x = cr[c]
            if mr[c] and x - x == 0.0:  # finite
                out[n] = x
                out_lev[n] = lr[c]
                n0 += lr[c] == 0
                n += 1
    return n, n0


@njit(nogil=True, cache=True, error_model="numpy")
def on_level_grid_share(vals, levs, origin, step):  # type: ignore[no-untyped-def]
    """Share of float32 ``vals`` within 1e-3 steps of the centre of a stripe of their own level ``levs``
    (uint8): a code that dropped its ``L`` finest bits is the centre of ``2**L`` stripes,
    ``origin + (k + (2**L - 1) / 2) * step`` (k integer)."""
    n = vals.shape[0]
    on = 0
    for i in range(n):
        lev = min(np.int64(levs[i]), np.int64(30))
        k = (np.float64(vals[i]) - origin) / step - 0.5 * np.float64((np.int64(1) << lev) - 1)
        on += abs(k - np.rint(k)) < 1e-3
    return on / max(n, 1)
