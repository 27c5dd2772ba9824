"""numba kernels shared by the reconstruction modules (private): point store, coarse ray rows (the distortion
and its Jacobian: ``geometry/_distortion_kernels.distort_jac``), the span of a row's valid pixels.

Distortion vectors here are always 12 long: ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4`` (OpenCV order, zeros
padded). Camera tables hold normalised undistorted coordinates ``(x/z, y/z)`` in the device frame.
"""

from __future__ import annotations

import numpy as np
from numba import njit

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)

NAN32 = np.float32(np.nan)
_NAN = NAN32


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def store_point(out, r, col, z, mx, my, zmin, zmax, to_world, rwc, cwc):  # type: ignore[no-untyped-def]
    """out[r, col] = the point at depth z on the ray (mx, my, 1), world or camera frame; NaN if z is out of range."""
    if not (z >= zmin and z <= zmax):  # also false for NaN
        out[r, col, 0] = _NAN
        out[r, col, 1] = _NAN
        out[r, col, 2] = _NAN
        return
    px = z * mx
    py = z * my
    if to_world:
        out[r, col, 0] = rwc[0, 0] * px + rwc[0, 1] * py + rwc[0, 2] * z + cwc[0]
        out[r, col, 1] = rwc[1, 0] * px + rwc[1, 1] * py + rwc[1, 2] * z + cwc[1]
        out[r, col, 2] = rwc[2, 0] * px + rwc[2, 1] * py + rwc[2, 2] * z + cwc[2]
    else:
        out[r, col, 0] = px
        out[r, col, 1] = py
        out[r, col, 2] = z

# Rays from a coarse table (every ``step``-th row, Catmull-Rom in between): a row of rays is rebuilt in
# L1/L2 cache instead of streaming a full (H, W, 2) table from memory in each pass.


@njit(nogil=True, cache=True, error_model="numpy")
def ray_row(tx, ty, r, step, mx, my):  # type: ignore[no-untyped-def]
    """Normalised ray (mx, my) of every pixel of row ``r``: Catmull-Rom cubic over the coarse table rows."""
    g = r // step + 1  # table row k holds pixel row (k - 1) * step
    t = np.float64(r - (g - 1) * step) / step
    _cubic_row(tx[g - 1], tx[g], tx[g + 1], tx[g + 2], t, mx)
    _cubic_row(ty[g - 1], ty[g], ty[g + 1], ty[g + 2], t, my)


@njit(nogil=True, cache=True, error_model="numpy")
def ray_span(tx, ty, r, step, mx, my, c0, c1):  # type: ignore[no-untyped-def]
    """:func:`ray_row` for the pixels ``c0 .. c1 - 1`` of row ``r`` only (into ``mx[c0:c1]``, ``my[c0:c1]``)."""
    g = r // step + 1
    t = np.float64(r - (g - 1) * step) / step
    _cubic_row(tx[g - 1][c0:c1], tx[g][c0:c1], tx[g + 1][c0:c1], tx[g + 2][c0:c1], t, mx[c0:c1])
    _cubic_row(ty[g - 1][c0:c1], ty[g][c0:c1], ty[g + 1][c0:c1], ty[g + 2][c0:c1], t, my[c0:c1])


@njit(nogil=True, cache=True, error_model="numpy")
def _cubic_row(p0, p1, p2, p3, t, out):  # type: ignore[no-untyped-def]
    """Catmull-Rom weights (as in ``rays.catmull_rom``), applied per column."""
    w0 = 0.5 * t * (-1.0 + t * (2.0 - t))
    w1 = 1.0 + t * t * (-2.5 + 1.5 * t)
    w2 = 0.5 * t * (1.0 + t * (4.0 - 3.0 * t))
    w3 = 0.5 * t * t * (t - 1.0)
    for c in range(out.shape[0]):
        out[c] = w0 * np.float64(p0[c]) + w1 * np.float64(p1[c]) + w2 * np.float64(p2[c]) + w3 * np.float64(p3[c])


@njit(nogil=True, cache=True, error_model="numpy")
def true_span(m):  # type: ignore[no-untyped-def]
    """(first, last + 1) of the True entries of a bool row; (0, 0) when none (decoded or lit pixels)."""
    w = m.shape[0]
    c0 = 0
    while c0 < w and not m[c0]:
        c0 += 1
    if c0 == w:
        return 0, 0
    c1 = w
    while not m[c1 - 1]:
        c1 -= 1
    return c0, c1
