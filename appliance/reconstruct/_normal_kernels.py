"""numba kernels of normal estimation (private; see ``filters.estimate_normals``)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.reconstruct._geom_kernels import NAN32 as _NAN


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _smallest_eigvec(a00, a01, a02, a11, a12, a22):  # type: ignore[no-untyped-def]
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (zeros if undefined).

    Eigenvalues in closed form (trigonometric solution of the characteristic cubic); the vector is the
    longest cross product of two rows of ``A - lambda I``, which is the numerically best conditioned one.
    """
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if not p2 > 0.0:
        return 0.0, 0.0, 0.0
    p = math.sqrt(p2 / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    r = det / (2.0 * p * p * p)
    r = min(1.0, max(-1.0, r))
    lam = q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)  # the smallest of the three
    m00, m11, m22 = a00 - lam, a11 - lam, a22 - lam
    # rows (m00 a01 a02), (a01 m11 a12), (a02 a12 m22)
    x0, y0, z0 = a01 * a12 - a02 * m11, a02 * a01 - m00 * a12, m00 * m11 - a01 * a01
    x1, y1, z1 = a01 * m22 - a02 * a12, a02 * a02 - m00 * m22, m00 * a12 - a01 * a02
    x2, y2, z2 = m11 * m22 - a12 * a12, a12 * a02 - a01 * m22, a01 * a12 - m11 * a02
    n0 = x0 * x0 + y0 * y0 + z0 * z0
    n1 = x1 * x1 + y1 * y1 + z1 * z1
    n2 = x2 * x2 + y2 * y2 + z2 * z2
    if n1 > n0 and n1 >= n2:
        x0, y0, z0, n0 = x1, y1, z1, n1
    elif n2 > n0:
        x0, y0, z0, n0 = x2, y2, z2, n2
    if not n0 > 0.0:
        return 0.0, 0.0, 0.0
    s = 1.0 / math.sqrt(n0)
    return x0 * s, y0 * s, z0 * s


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def normals(xyz, eye, radius, max_dist, min_points, out):  # type: ignore[no-untyped-def]
    """Unit normals by a plane fit (principal axes) to the valid points of a (2 radius + 1)^2 pixel window.

    Only neighbours within ``max_dist`` (mm) of the centre point take part, so a fit never spans a depth
    step; with fewer than ``min_points`` of them the normal is NaN. Normals are turned towards ``eye``.
    """
    h, w = xyz.shape[0], xyz.shape[1]
    d2max = max_dist * max_dist
    for r in prange(h):
        for c in range(w):
            out[r, c, 0] = _NAN
            out[r, c, 1] = _NAN
            out[r, c, 2] = _NAN
            cx = np.float64(xyz[r, c, 0])
            cy = np.float64(xyz[r, c, 1])
            cz = np.float64(xyz[r, c, 2])
            if cz != cz:
                continue
            n = 0
            sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
            for rr in range(max(r - radius, 0), min(r + radius + 1, h)):
                for cc in range(max(c - radius, 0), min(c + radius + 1, w)):
                    dx = np.float64(xyz[rr, cc, 0]) - cx  # relative to the centre: no cancellation
                    dy = np.float64(xyz[rr, cc, 1]) - cy
                    dz = np.float64(xyz[rr, cc, 2]) - cz
                    if dx * dx + dy * dy + dz * dz < d2max:  # false for NaN
                        n += 1
                        sx += dx
                        sy += dy
                        sz += dz
                        sxx += dx * dx
                        sxy += dx * dy
                        sxz += dx * dz
                        syy += dy * dy
                        syz += dy * dz
                        szz += dz * dz
            if n < min_points:
                continue
            mx, my, mz = sx / n, sy / n, sz / n
            nx, ny, nz = _smallest_eigvec(sxx / n - mx * mx, sxy / n - mx * my, sxz / n - mx * mz,
                                          syy / n - my * my, syz / n - my * mz, szz / n - mz * mz)  # fmt: skip
            if nx == 0.0 and ny == 0.0 and nz == 0.0:
                continue
            if nx * (eye[0] - cx) + ny * (eye[1] - cy) + nz * (eye[2] - cz) < 0.0:
                nx, ny, nz = -nx, -ny, -nz
            out[r, c, 0] = nx
            out[r, c, 1] = ny
            out[r, c, 2] = nz
    return out
