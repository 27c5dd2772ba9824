"""numba kernels of the lens model (private): OpenCV's distortion with its Jacobian, and its inversion.

Distortion vectors here are always 12 long: ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4`` (OpenCV order, zeros
padded). The triangulation kernels (``reconstruct/_geom_kernels``) use the same :func:`distort_jac`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def distort_jac(x, y, d):  # type: ignore[no-untyped-def]
    """Distorted normalised coords and their 2x2 Jacobian w.r.t. (x, y)."""
    r2 = x * x + y * y
    num = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    den = 1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
    dnum = d[0] + r2 * (2.0 * d[1] + 3.0 * r2 * d[4])
    dden = d[5] + r2 * (2.0 * d[6] + 3.0 * r2 * d[7])
    rad = num / den
    drad = (dnum * den - num * dden) / (den * den)  # d rad / d r2
    xd = x * rad + 2.0 * d[2] * x * y + d[3] * (r2 + 2.0 * x * x) + r2 * (d[8] + r2 * d[9])
    yd = y * rad + d[2] * (r2 + 2.0 * y * y) + 2.0 * d[3] * x * y + r2 * (d[10] + r2 * d[11])
    sx = d[8] + 2.0 * r2 * d[9]
    sy = d[10] + 2.0 * r2 * d[11]
    j11 = rad + 2.0 * x * x * drad + 2.0 * d[2] * y + 6.0 * d[3] * x + 2.0 * x * sx
    j12 = 2.0 * x * y * drad + 2.0 * d[2] * x + 2.0 * d[3] * y + 2.0 * y * sx
    j21 = 2.0 * x * y * drad + 2.0 * d[2] * x + 2.0 * d[3] * y + 2.0 * x * sy
    j22 = rad + 2.0 * y * y * drad + 6.0 * d[2] * y + 2.0 * d[3] * x + 2.0 * y * sy
    return xd, yd, j11, j12, j21, j22


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def undistort_points(xd, yd, d, iterations, out):  # type: ignore[no-untyped-def]
    """Normalised undistorted ``out[i] = (x, y)`` whose distortion (``d``, 12 coefficients) is ``(xd[i], yd[i])``.

    Newton's method on :func:`distort_jac` from the distorted point, ``iterations`` steps at most (ordinary lenses
    settle in 3-6), to 1e-13; NaN where it does not come within 1e-12, or lands past a fold of the model (the
    radial factor or the Jacobian's determinant not positive: no ray of the lens maps there).
    """
    for i in prange(xd.shape[0]):
        tx = xd[i]
        ty = yd[i]
        x = tx
        y = ty
        for _ in range(iterations):
            fx, fy, j11, j12, j21, j22 = distort_jac(x, y, d)
            ex = fx - tx
            ey = fy - ty
            if abs(ex) + abs(ey) <= 1e-13:
                break
            det = j11 * j22 - j12 * j21
            x -= (j22 * ex - j12 * ey) / det
            y -= (j11 * ey - j21 * ex) / det
        fx, fy, j11, j12, j21, j22 = distort_jac(x, y, d)
        r2 = x * x + y * y
        radial = (1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))) / (1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7])))
        if math.hypot(fx - tx, fy - ty) <= 1e-12 and radial > 0.0 and j11 * j22 - j12 * j21 > 0.0:
            out[i, 0] = x
            out[i, 1] = y
        else:
            out[i, 0] = np.nan
            out[i, 1] = np.nan
