"""Numba kernel of the albedo-edge correction (see :mod:`appliance.reconstruct.albedo_edges`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)

#: The level's slope across a pixel is the central difference, at most this many times the smaller one-sided
#: difference. Beside a sharp albedo step the central difference spans the step: on the second pixel from it
#: (0.5 px blur, albedo 0.95 beside 0.03) it reads a pull of 0.4 camera px where the light-weighted centroid
#: moves 0.02 px, as the step's light reaches that pixel only through the blur's far tail. There the two
#: one-sided differences differ 200-fold; on the pixel next to the step, whose pull the central difference
#: gets right (0.80 against 0.77 px), 4.2-fold; on an even slope they are equal. On the dark-and-shiny render
#: (tune's three exposures, periods [16, 8]): RMS 0.102 -> 0.081 mm, dark pixels two from a bright patch
#: 0.36 -> 0.10 mm (limits 3 / 6 / 8 / 12: 0.099 / 0.081 / 0.081 / 0.083 mm).
SLOPE_LIMIT = 6.0

NEGLIGIBLE_PX = 0.05
"""A centroid shift along a direction under this (camera px) needs no code slope there."""


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _slope(a2, a, b, c, c2, ok):  # type: ignore[no-untyped-def]
    """The code's slope at ``b`` over two pixels each side (``a2 a b c c2`` in a line, ``ok``: all decoded; the
    codes next to an albedo edge carry its shift, those two pixels away much less), or NaN where that is not one
    smooth surface: a pixel undecoded, or the two halves' slopes differing by more than 1 projector px per pixel
    plus half their sizes (a depth step)."""
    if not ok:
        return np.nan
    dl = 0.5 * (np.float64(b) - np.float64(a2))
    dr = 0.5 * (np.float64(c2) - np.float64(b))
    if abs(dl - dr) <= 1.0 + 0.5 * (abs(dl) + abs(dr)):
        return 0.5 * (dl + dr)
    return np.nan


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _slope_near(a, b, c, ok_a, ok_c):  # type: ignore[no-untyped-def]
    """The code's slope at ``b`` from its nearest decoded neighbours (``a`` before, ``c`` after): the smaller
    one-sided difference when both agree in sign, the one there is, else NaN."""
    if ok_a and ok_c:
        dl = np.float64(b) - np.float64(a)
        dr = np.float64(c) - np.float64(b)
        if dl * dr <= 0.0:
            return 0.0
        return dl if abs(dl) < abs(dr) else dr
    if ok_a:
        return np.float64(b) - np.float64(a)
    if ok_c:
        return np.float64(c) - np.float64(b)
    return np.nan


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _slope_at(a2, a, b, c, c2, ok_a2, ok_a, ok_c, ok_c2):  # type: ignore[no-untyped-def]
    """:func:`_slope` over two pixels each side, else :func:`_slope_near`."""
    s = _slope(a2, a, b, c, c2, ok_a2 and ok_a and ok_c and ok_c2)
    return s if s == s else _slope_near(a, b, c, ok_a, ok_c)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _pull(d, slope):  # type: ignore[no-untyped-def]
    """The code shift of a centroid shift ``d`` (camera px) along a direction of code ``slope`` (NaN: unknown;
    then 0 where ``d`` is under :data:`NEGLIGIBLE_PX`, else NaN)."""
    if slope == slope:
        return d * slope
    return 0.0 if abs(d) < NEGLIGIBLE_PX else np.nan


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _row_span(r, h):  # type: ignore[no-untyped-def]
    """The rows above and below ``r`` (clamped) and the factor of their difference (one-sided at the border)."""
    ru, rd = max(r - 1, 0), min(r + 1, h - 1)
    return ru, rd, (np.float32(1.0) / np.float32(rd - ru) if rd > ru else np.float32(0.0))


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _col_span(c, w):  # type: ignore[no-untyped-def]
    """The columns left and right of ``c`` (clamped) and the factor of their difference."""
    cl, cr = max(c - 1, 0), min(c + 1, w - 1)
    return cl, cr, (np.float32(0.5) if cr - cl == 2 else np.float32(1.0))


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _limited(lo, mid, hi, f):  # type: ignore[no-untyped-def]
    """The level's slope across a pixel (``lo``, ``mid``, ``hi``: before, at, after it; ``f`` the central
    difference's factor): the central difference, at most :data:`SLOPE_LIMIT` times the smaller one-sided one,
    and 0 at a local extreme (see :data:`SLOPE_LIMIT`). No branch: it vectorises."""
    a = hi - mid
    b = mid - lo
    cen = f * (a + b)
    lim = np.float32(SLOPE_LIMIT) * min(abs(a), abs(b))
    same = np.float32(a * b > np.float32(0.0))
    return same * np.float32(math.copysign(min(abs(cen), lim), cen)), cen


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _worth(row, up, down, m, c, cl, cr, rx, ry, lim2):  # type: ignore[no-untyped-def]
    """Pixel ``c`` of a row (``row``, the rows ``up`` and ``down`` of the level, mask row ``m``): whether it is
    decoded and its level slope worth a correction, ``|grad|^2 >= lim2 level^2`` with ``level > 0`` (no
    division and no branch: most pixels lie on an even surface; ``grad`` the central difference), and the slope
    (DN per px, x and y: limited, see :func:`_limited`; then central)."""
    level = np.float32(row[c])
    gx, cx = _limited(np.float32(row[cl]), level, np.float32(row[cr]), rx)
    gy, cy = _limited(np.float32(up[c]), level, np.float32(down[c]), ry)
    return m[c] & (cx * cx + cy * cy >= lim2 * level * level) & (level > np.float32(0.0)), gx, gy, cx, cy


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def edge_count(mask, rad, lim2, counts):  # type: ignore[no-untyped-def]
    """``counts[r]``: row ``r``'s pixels worth a correction (see :func:`_worth`)."""
    h, w = mask.shape
    lim = np.float32(lim2)
    half = np.float32(0.5)
    for r in prange(h):
        ru, rd, ry = _row_span(r, h)
        a, b, d, m = rad[r], rad[ru], rad[rd], mask[r]
        n = np.int64(0)
        for c in range(1, w - 1):  # the inner columns: fixed neighbours, a loop without branches (it vectorises)
            n += np.int64(_worth(a, b, d, m, c, c - 1, c + 1, half, ry, lim)[0])
        for c in range(0, w, max(w - 1, 1)):  # the two border columns (one column: once)
            cl, cr, rx = _col_span(c, w)
            n += np.int64(_worth(a, b, d, m, c, cl, cr, rx, ry, lim)[0])
        counts[r] = n


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def edge_shift(  # type: ignore[no-untyped-def]
    u, v, mask, rad, s2, lim2, max_shift, kappa, min_report2, has_u, has_v, offsets, cols, du, dv, evar, moved
):  # fmt: skip
    """The correction of every pixel :func:`edge_count` counted (``offsets`` its running sum), stored sparsely.

    Row ``r``'s pixels go to entries ``offsets[r] ..`` (ascending columns ``cols``): the code shifts ``du``,
    ``dv`` (projector px) ``= d . grad(code)``, with ``d = s2 grad(rad) / rad`` (camera px, its length at most
    ``max_shift``), and the variance ``evar`` (px^2) ``= ((kappa + |d|) x`` the larger shift of the two axes
    ``)^2`` (the formula is first order in the share of light from aside). A pixel without a code slope along
    a direction its shift needs (see :func:`_slope_at`, :func:`_pull`) gets 0 shifts and 0 variance.
    ``moved[r]`` counts the row's pixels whose squared shift exceeds ``min_report2``. ``has_u`` / ``has_v``:
    the axis is coded (an uncoded one's shift is 0).
    """
    h, w = u.shape
    lim = np.float32(lim2)
    for r in prange(h):
        ru, rd, ry = _row_span(r, h)
        a, b, d, mr = rad[r], rad[ru], rad[rd], mask[r]
        k = offsets[r]
        m = 0
        for c in range(w):
            if k == offsets[r + 1]:  # every pixel edge_count counted in the row is done (most rows: none)
                break
            cl, cr, rx = _col_span(c, w)
            ok, gx, gy, cx, cy = _worth(a, b, d, mr, c, cl, cr, rx, ry, lim)
            if not ok:
                continue
            cols[k] = c
            pu, pv, e = _correct_pixel(u, v, mask, r, c, np.float64(gx), np.float64(gy), np.float64(cx),
                                       np.float64(cy), np.float64(rad[r, c]), s2, max_shift, kappa, has_u,
                                       has_v)  # fmt: skip
            du[k] = np.float32(pu)
            dv[k] = np.float32(pv)
            evar[k] = np.float32(e)
            if max(pu * pu, pv * pv) > min_report2:
                m += 1
            k += 1
        moved[r] = m


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def shift_codes(code, offsets, cols, delta, old):  # type: ignore[no-untyped-def]
    """``code`` minus the sparse ``delta`` in place; ``old`` keeps the values it had (for :func:`put_codes`)."""
    for r in prange(code.shape[0]):
        for k in range(offsets[r], offsets[r + 1]):
            c = cols[k]
            old[k] = code[r, c]
            code[r, c] = np.float32(np.float64(code[r, c]) - np.float64(delta[k]))


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def put_codes(code, offsets, cols, values):  # type: ignore[no-untyped-def]
    """The sparse ``values`` written back into ``code`` (undoes :func:`shift_codes` exactly)."""
    for r in prange(code.shape[0]):
        for k in range(offsets[r], offsets[r + 1]):
            code[r, cols[k]] = values[k]


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _correct_pixel(u, v, mask, r, c, gx, gy, cx, cy, level, s2, max_shift, kappa, has_u, has_v):  # type: ignore[no-untyped-def]
    """The code shifts (u, v; projector px) of one pixel with level slope (``gx``, ``gy``) and their variance
    (px^2) from the central slope (``cx``, ``cy``: where the limit cut the slope, the pull lies between the
    two); see :func:`edge_shift`. The code's slopes are read once for both."""
    h, w = u.shape
    # neighbours off the image count as undecoded (their index clamped to the pixel's own)
    cl, cr, ru, rd = max(c - 1, 0), min(c + 1, w - 1), max(r - 1, 0), min(r + 1, h - 1)
    c2l, c2r, r2u, r2d = max(c - 2, 0), min(c + 2, w - 1), max(r - 2, 0), min(r + 2, h - 1)
    ml2, ml, mr, mr2 = c >= 2 and mask[r, c2l], c >= 1 and mask[r, cl], c + 1 < w and mask[r, cr], (
        c + 2 < w and mask[r, c2r])
    mu2, mu, md, md2 = r >= 2 and mask[r2u, c], r >= 1 and mask[ru, c], r + 1 < h and mask[rd, c], (
        r + 2 < h and mask[r2d, c])
    sux = suy = svx = svy = 0.0
    if has_u:
        sux = _slope_at(u[r, c2l], u[r, cl], u[r, c], u[r, cr], u[r, c2r], ml2, ml, mr, mr2)
        suy = _slope_at(u[r2u, c], u[ru, c], u[r, c], u[rd, c], u[r2d, c], mu2, mu, md, md2)
    if has_v:
        svx = _slope_at(v[r, c2l], v[r, cl], v[r, c], v[r, cr], v[r, c2r], ml2, ml, mr, mr2)
        svy = _slope_at(v[r2u, c], v[ru, c], v[r, c], v[rd, c], v[r2d, c], mu2, mu, md, md2)
    pu, pv, _e = _pulls(gx, gy, level, s2, max_shift, kappa, sux, suy, svx, svy, has_u, has_v)
    _u, _v, e = _pulls(cx, cy, level, s2, max_shift, kappa, sux, suy, svx, svy, has_u, has_v)
    return pu, pv, e


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _pulls(gx, gy, level, s2, max_shift, kappa, sux, suy, svx, svy, has_u, has_v):  # type: ignore[no-untyped-def]
    """The code shifts and their variance for level slope (``gx``, ``gy``) and code slopes ``s..`` (u, v along
    x, y); (0, 0, 0) where a slope the shift needs is unknown."""
    dx = s2 * gx / level
    dy = s2 * gy / level
    n = math.sqrt(dx * dx + dy * dy)
    if n > max_shift:
        dx *= max_shift / n
        dy *= max_shift / n
    pu = 0.0
    pv = 0.0
    if has_u:
        pu = _pull(dx, sux) + _pull(dy, suy)
        if not pu == pu:  # no slope where the shift matters: the formula cannot be applied
            return 0.0, 0.0, 0.0
    if has_v:
        pv = _pull(dx, svx) + _pull(dy, svy)
        if not pv == pv:
            return 0.0, 0.0, 0.0
    k = kappa + min(n, max_shift)  # first order fails as more of the light comes from aside
    return pu, pv, k * k * max(pu * pu, pv * pv)
