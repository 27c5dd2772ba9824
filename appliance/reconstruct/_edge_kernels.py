"""Numba kernel of the albedo-edge correction (see :mod:`appliance.reconstruct.albedo_edges`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)

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


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def edge_shift(u, v, mask, rad, s2, max_shift, kappa, min_report2, has_u, has_v, uo, vo, evar, counts):  # type: ignore[no-untyped-def]
    """Correct every decoded pixel's code for the light its neighbours blur into it.

    ``uo``/``vo`` = ``u``/``v`` minus ``d . grad(code)``, with ``d = s2 grad(rad) / rad`` (camera px, its length
    at most ``max_shift``); ``evar`` (px^2) gets ``(kappa + |d|)^2`` times the larger squared correction of
    the two axes (the formula is first order in the share of light from aside); ``counts[r]`` the row's pixels
    whose squared correction exceeds ``min_report2``. Undecoded pixels, and pixels without a code slope along a
    direction their shift needs (see :func:`_slope_at`, :func:`_pull`), keep their codes (``evar`` 0); at the
    image border the slopes are one-sided. ``has_u`` / ``has_v``: the axis is coded (an uncoded one is not
    written).
    """
    h, w = u.shape
    for r in prange(h):
        counts[r] = 0
        for c in range(w):
            if has_u:
                uo[r, c] = u[r, c]
            if has_v:
                vo[r, c] = v[r, c]
            evar[r, c] = np.float32(0.0)
            if not mask[r, c]:
                continue
            level = np.float64(rad[r, c])
            if not level > 0.0:
                continue
            # at the image's border the level's slope is one-sided
            cl, cr, ru, rd = max(c - 1, 0), min(c + 1, w - 1), max(r - 1, 0), min(r + 1, h - 1)
            gx = (np.float64(rad[r, cr]) - np.float64(rad[r, cl])) / (cr - cl)
            gy = (np.float64(rad[rd, c]) - np.float64(rad[ru, c])) / (rd - ru)
            dx = s2 * gx / level
            dy = s2 * gy / level
            n = math.sqrt(dx * dx + dy * dy)
            if n == 0.0:
                continue
            if n > max_shift:
                dx *= max_shift / n
                dy *= max_shift / n
            # neighbours off the image count as undecoded (their index clamped to the pixel's own)
            c2l, c2r, r2u, r2d = max(c - 2, 0), min(c + 2, w - 1), max(r - 2, 0), min(r + 2, h - 1)
            ml2, ml, mr, mr2 = c >= 2 and mask[r, c2l], c >= 1 and mask[r, cl], c + 1 < w and mask[r, cr], (
                c + 2 < w and mask[r, c2r])
            mu2, mu, md, md2 = r >= 2 and mask[r2u, c], r >= 1 and mask[ru, c], r + 1 < h and mask[rd, c], (
                r + 2 < h and mask[r2d, c])
            p2 = 0.0
            pu = 0.0
            pv = 0.0
            if has_u:
                pu = _pull(dx, _slope_at(u[r, c2l], u[r, cl], u[r, c], u[r, cr], u[r, c2r], ml2, ml, mr, mr2))
                pu += _pull(dy, _slope_at(u[r2u, c], u[ru, c], u[r, c], u[rd, c], u[r2d, c], mu2, mu, md, md2))
                if not pu == pu:  # no slope where the shift matters: the formula cannot be applied
                    continue
                p2 = pu * pu
            if has_v:
                pv = _pull(dx, _slope_at(v[r, c2l], v[r, cl], v[r, c], v[r, cr], v[r, c2r], ml2, ml, mr, mr2))
                pv += _pull(dy, _slope_at(v[r2u, c], v[ru, c], v[r, c], v[rd, c], v[r2d, c], mu2, mu, md, md2))
                if not pv == pv:
                    continue
                vo[r, c] = np.float32(np.float64(v[r, c]) - pv)
                p2 = max(p2, pv * pv)
            if has_u:
                uo[r, c] = np.float32(np.float64(u[r, c]) - pu)
            k = kappa + min(n, max_shift)  # first order fails as more of the light comes from aside
            evar[r, c] = np.float32(k * k * p2)
            if p2 > min_report2:
                counts[r] += 1
