"""numba kernels of camera-camera triangulation (private; see ``stereo.py``)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from appliance.reconstruct._geom_kernels import NAN32 as _NAN
from appliance.reconstruct._geom_kernels import distort_jac


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def project_dirs(rot, a0, b0, step, hr, wr, kmat, d):  # type: ignore[no-untyped-def]
    """Distorted pixel of every rectified-grid direction ``rot @ (a, b, 1)`` (device frame); NaN behind."""
    out = np.empty((hr, wr, 2), dtype=np.float32)
    fx, sk, cx = kmat[0, 0], kmat[0, 1], kmat[0, 2]
    fy, cy = kmat[1, 1], kmat[1, 2]
    for y in prange(hr):
        b = b0 + y * step
        for x in range(wr):
            a = a0 + x * step
            px = rot[0, 0] * a + rot[0, 1] * b + rot[0, 2]
            py = rot[1, 0] * a + rot[1, 1] * b + rot[1, 2]
            pz = rot[2, 0] * a + rot[2, 1] * b + rot[2, 2]
            if pz <= 1e-9:
                out[y, x, 0] = _NAN
                out[y, x, 1] = _NAN
                continue
            xd, yd, _, _, _, _ = distort_jac(px / pz, py / pz, d)
            out[y, x, 0] = fx * xd + sk * yd + cx
            out[y, x, 1] = fy * yd + cy
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def remap_codes(src, mask, srcmap, max_spread, out):  # type: ignore[no-untyped-def]
    """Bilinear resampling of a code map; NaN unless all 4 neighbours are valid and within ``max_spread``."""
    h, w = src.shape[0], src.shape[1]
    hr, wr = out.shape[0], out.shape[1]
    for y in prange(hr):
        for x in range(wr):
            sx = np.float64(srcmap[y, x, 0])
            sy = np.float64(srcmap[y, x, 1])
            val = _NAN
            if sx >= 0.0 and sy >= 0.0 and sx < w - 1 and sy < h - 1:
                ix = int(sx)
                iy = int(sy)
                if mask[iy, ix] and mask[iy, ix + 1] and mask[iy + 1, ix] and mask[iy + 1, ix + 1]:
                    c00 = src[iy, ix]
                    c01 = src[iy, ix + 1]
                    c10 = src[iy + 1, ix]
                    c11 = src[iy + 1, ix + 1]
                    lo = min(min(c00, c01), min(c10, c11))
                    hi = max(max(c00, c01), max(c10, c11))
                    if hi - lo <= max_spread:  # NaN compares false: rejected
                        tx = sx - ix
                        ty = sy - iy
                        a = c00 + tx * (c01 - c00)
                        b = c10 + tx * (c11 - c10)
                        val = a + ty * (b - a)
            out[y, x] = val
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def crossing_table(rect, code_offset, max_step, out):  # type: ignore[no-untyped-def]
    """Per rectified row, the sub-pixel x where the code crosses each integer (NaN none, inf ambiguous)."""
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
            k0 = math.ceil(lo)
            k1 = math.ceil(hi)
            for k in range(k0, k1):
                idx = k + code_offset
                if idx < 0 or idx >= nk:
                    continue
                if math.isnan(out[y, idx]):
                    out[y, idx] = x + (k - ua) / (ub - ua)
                else:
                    out[y, idx] = np.inf
    return out


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _cross_at(tab, y, w, fu, code_offset, max_gap, max_row_jump):  # type: ignore[no-untyped-def]
    """Sub-pixel x on fractional row ``y + w`` where the code equals ``fu`` (NaN when not consistent)."""
    k = math.floor(fu)
    t = fu - k
    idx = int(k) + code_offset
    if idx < 0 or idx + 1 >= tab.shape[1]:
        return np.nan
    xa0 = np.float64(tab[y, idx])
    xb0 = np.float64(tab[y, idx + 1])
    xa1 = np.float64(tab[y + 1, idx])
    xb1 = np.float64(tab[y + 1, idx + 1])
    if not (abs(xb0 - xa0) <= max_gap and abs(xb1 - xa1) <= max_gap):  # also rejects NaN / inf
        return np.nan
    x0 = xa0 + t * (xb0 - xa0)
    x1 = xa1 + t * (xb1 - xa1)
    if not abs(x1 - x0) <= max_row_jump:
        return np.nan
    return x0 + w * (x1 - x0)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stereo_match(  # type: ignore[no-untyped-def]
    u0,
    v0,
    mask0,
    rect0,
    cross0,
    cross1,
    v1rect,
    use_v,
    code_offset,
    geom,
    rr_t,
    c0,
    r0z,
    t0z,
    proj_r,
    proj_t,
    kp,
    dp,
    use_proj,
    max_code_err,
    max_gap,
    max_row_jump,
    max_lr,
    max_epi,
    zmin,
    zmax,
    out,
):
    """Match every cam0 pixel along its rectified row in cam1 by code and triangulate (world frame, mm).

    ``geom`` = (a0min, a1min, bmin, step, baseline_mm); ``rect0`` holds each pixel's (x, y) on the grid.
    """
    h, w = u0.shape[0], u0.shape[1]
    hr = cross1.shape[0]
    wr1 = v1rect.shape[1]
    a0min, a1min, bmin, step, base = geom[0], geom[1], geom[2], geom[3], geom[4]
    fx, sk, cx = kp[0, 0], kp[0, 1], kp[0, 2]
    fy, cy = kp[1, 1], kp[1, 2]
    for r in prange(h):
        for col in range(w):
            out[r, col, 0] = _NAN
            out[r, col, 1] = _NAN
            out[r, col, 2] = _NAN
            fu = np.float64(u0[r, col])
            xr0 = np.float64(rect0[r, col, 0])
            yr = np.float64(rect0[r, col, 1])
            if not (mask0[r, col] and fu == fu and yr >= 0.0 and yr < hr - 1):
                continue
            iy = int(yr)
            wy = yr - iy
            x1 = _cross_at(cross1, iy, wy, fu, code_offset, max_gap, max_row_jump)
            if x1 != x1:
                continue
            # left-right check: the code must come back to this very pixel on cam0's own row
            xb = _cross_at(cross0, iy, wy, fu, code_offset, max_gap, max_row_jump)
            if not abs(xb - xr0) <= max_lr:
                continue
            if use_v:
                ix = int(x1)
                if ix < 0 or ix + 1 >= wr1 or iy + 2 >= hr:
                    continue
                tx = x1 - ix
                va = v1rect[iy, ix] + tx * (v1rect[iy, ix + 1] - v1rect[iy, ix])
                vb = v1rect[iy + 1, ix] + tx * (v1rect[iy + 1, ix + 1] - v1rect[iy + 1, ix])
                v1 = va + wy * (vb - va)
                dvdy = vb - va
                if not (abs(dvdy) > 1e-6 and abs(np.float64(v0[r, col]) - v1) <= max_epi * abs(dvdy)):
                    continue
            a0 = a0min + xr0 * step
            a1 = a1min + x1 * step
            b = bmin + yr * step
            disp = a0 - a1
            if not disp > 0.0:
                continue
            zr = base / disp
            px = c0[0] + zr * (rr_t[0, 0] * a0 + rr_t[0, 1] * b + rr_t[0, 2])
            py = c0[1] + zr * (rr_t[1, 0] * a0 + rr_t[1, 1] * b + rr_t[1, 2])
            pz = c0[2] + zr * (rr_t[2, 0] * a0 + rr_t[2, 1] * b + rr_t[2, 2])
            depth = r0z[0] * px + r0z[1] * py + r0z[2] * pz + t0z
            if not (depth >= zmin and depth <= zmax):
                continue
            if use_proj:
                qx = proj_r[0, 0] * px + proj_r[0, 1] * py + proj_r[0, 2] * pz + proj_t[0]
                qy = proj_r[1, 0] * px + proj_r[1, 1] * py + proj_r[1, 2] * pz + proj_t[1]
                qz = proj_r[2, 0] * px + proj_r[2, 1] * py + proj_r[2, 2] * pz + proj_t[2]
                if qz <= 0.0:
                    continue
                xd, yd, _, _, _, _ = distort_jac(qx / qz, qy / qz, dp)
                if not abs(fx * xd + sk * yd + cx - fu) <= max_code_err:
                    continue
                if use_v and not abs(fy * yd + cy - np.float64(v0[r, col])) <= max_code_err:
                    continue
            out[r, col, 0] = px
            out[r, col, 1] = py
            out[r, col, 2] = pz
    return out
