"""numba kernels of triangulation (private; see ``triangulate.py`` and ``stereo.py``).

Distortion vectors here are always 12 long: ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4`` (OpenCV order, zeros
padded). Camera tables hold normalised undistorted coordinates ``(x/z, y/z)`` in the device frame.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_NAN = np.float32(np.nan)


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


@njit(nogil=True, cache=True, error_model="numpy")
def code_line_table(c_grid, code_grid, kmat, d, epi, axis):  # type: ignore[no-untyped-def]
    """Solve, for every epipolar line ``c`` and projector code, the undistorted coordinate on that line.

    Axis 0 (columns): the line passes through (0, c) and the epipole; returns x where the distorted column
    equals the code. Axis 1 (rows): through (c, 0); returns y where the distorted row equals the code.
    """
    nc = c_grid.shape[0]
    nu = code_grid.shape[0]
    out = np.full((nc, nu), np.nan, dtype=np.float32)
    fx, sk, cx = kmat[0, 0], kmat[0, 1], kmat[0, 2]
    fy, cy = kmat[1, 1], kmat[1, 2]
    for j in range(nc):
        c = c_grid[j]
        if axis == 0:
            p0x, p0y = 0.0, c
            dx, dy = epi[0] - epi[2] * p0x, epi[1] - epi[2] * p0y
            if abs(dx) < 1e-12:
                continue
            dy /= dx
            dx = 1.0
        else:
            p0x, p0y = c, 0.0
            dx, dy = epi[0] - epi[2] * p0x, epi[1] - epi[2] * p0y
            if abs(dy) < 1e-12:
                continue
            dx /= dy
            dy = 1.0
        for i in range(nu):
            target = code_grid[i]
            if axis == 0:
                t = (target - cx - sk * p0y) / (fx + sk * dy)
            else:
                t = (target - cy) / fy
            ok = False
            for _ in range(30):
                x = p0x + t * dx
                y = p0y + t * dy
                xd, yd, j11, j12, j21, j22 = distort_jac(x, y, d)
                if axis == 0:
                    g = fx * xd + sk * yd + cx - target
                    dg = (fx * j11 + sk * j21) * dx + (fx * j12 + sk * j22) * dy
                else:
                    g = fy * yd + cy - target
                    dg = fy * (j21 * dx + j22 * dy)
                if dg == 0.0:
                    break
                step = g / dg
                t -= step
                if abs(step) < 1e-13:
                    ok = True
                    break
            if ok and abs(t) < 5.0:
                out[j, i] = t
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def epipolar_intercepts(norm, rcp, tcp, c0, inv_dc, axis, min_sin):  # type: ignore[no-untyped-def]
    """Per camera pixel: fractional index of its epipolar line in the code-line table (NaN if ill-posed)."""
    h, w = norm.shape[0], norm.shape[1]
    out = np.empty((h, w), dtype=np.float32)
    for r in prange(h):
        for col in range(w):
            mx = np.float64(norm[r, col, 0])
            my = np.float64(norm[r, col, 1])
            bx = rcp[0, 0] * mx + rcp[0, 1] * my + rcp[0, 2]
            by = rcp[1, 0] * mx + rcp[1, 1] * my + rcp[1, 2]
            bz = rcp[2, 0] * mx + rcp[2, 1] * my + rcp[2, 2]
            # homogeneous epipolar line l = T x B in the projector's normalised plane
            l1 = tcp[1] * bz - tcp[2] * by
            l2 = tcp[2] * bx - tcp[0] * bz
            l3 = tcp[0] * by - tcp[1] * bx
            nrm = math.sqrt(l1 * l1 + l2 * l2)
            if axis == 0:
                ok = nrm > 0 and abs(l2) >= min_sin * nrm
                c = -l3 / l2 if ok else np.nan
            else:
                ok = nrm > 0 and abs(l1) >= min_sin * nrm
                c = -l3 / l1 if ok else np.nan
            out[r, col] = (c - c0) * inv_dc
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def tri_plane(code, mask, norm, cidx, table, code0, rcp, tcp, rwc, cwc, to_world, zmin, zmax, axis, out):  # type: ignore[no-untyped-def]
    """Ray / light-surface intersection for one coded axis, organised output (NaN where invalid)."""
    h, w = code.shape[0], code.shape[1]
    nc, nu = table.shape[0], table.shape[1]
    a0 = 0 if axis == 0 else 1
    tc = tcp[2]
    ta = tcp[a0]
    for r in prange(h):
        for col in range(w):
            cu = code[r, col]
            ci = cidx[r, col]
            fu = np.float64(cu) - code0
            fc = np.float64(ci)
            valid = mask[r, col] and fu >= 0.0 and fc >= 0.0 and fu < nu - 1 and fc < nc - 1
            if not valid:  # also false for NaN codes / lines
                out[r, col, 0] = _NAN
                out[r, col, 1] = _NAN
                out[r, col, 2] = _NAN
                continue
            iu = int(fu)
            ic = int(fc)
            tu = fu - iu
            tcf = fc - ic
            q00 = table[ic, iu]
            q01 = table[ic, iu + 1]
            q10 = table[ic + 1, iu]
            q11 = table[ic + 1, iu + 1]
            q0 = q00 + tu * (q01 - q00)
            q1 = q10 + tu * (q11 - q10)
            q = q0 + tcf * (q1 - q0)
            mx = np.float64(norm[r, col, 0])
            my = np.float64(norm[r, col, 1])
            ba = rcp[a0, 0] * mx + rcp[a0, 1] * my + rcp[a0, 2]
            bz = rcp[2, 0] * mx + rcp[2, 1] * my + rcp[2, 2]
            den = ba - bz * q
            z = (tc * q - ta) / den if den != 0.0 else np.nan
            _store_point(out, r, col, z if tc + z * bz > 0.0 else np.nan, mx, my, zmin, zmax, to_world, rwc, cwc)
    return out


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _store_point(out, r, col, z, mx, my, zmin, zmax, to_world, rwc, cwc):  # type: ignore[no-untyped-def]
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


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def tri_ray(u, v, mask, norm, und, origin, kmat, d, rcp, tcp, rwc, cwc, to_world, zmin, zmax, out):  # type: ignore[no-untyped-def]
    """Ray-ray triangulation: the point on the camera ray nearest (in projector px) to the coded ray."""
    h, w = u.shape[0], u.shape[1]
    for r in prange(h):
        for col in range(w):
            mx = np.float64(norm[r, col, 0])
            my = np.float64(norm[r, col, 1])
            z = _z_ray(u[r, col], v[r, col], mx, my, und, origin, kmat, d, rcp, tcp) if mask[r, col] else np.nan
            _store_point(out, r, col, z, mx, my, zmin, zmax, to_world, rwc, cwc)
    return out


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


# --- filters and cloud assembly --------------------------------------------------------------------------


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def filter_depth(xyz, rz, tz, zmin, zmax):  # type: ignore[no-untyped-def]
    """NaN every point whose depth ``rz . p + tz`` is outside [zmin, zmax]; returns how many."""
    h, w = xyz.shape[0], xyz.shape[1]
    removed = np.zeros(h, np.int64)
    for r in prange(h):
        n = 0
        for c in range(w):
            z = rz[0] * xyz[r, c, 0] + rz[1] * xyz[r, c, 1] + rz[2] * xyz[r, c, 2] + tz
            if z == z and not (z >= zmin and z <= zmax):
                xyz[r, c, 0] = _NAN
                xyz[r, c, 1] = _NAN
                xyz[r, c, 2] = _NAN
                n += 1
        removed[r] = n
    return removed.sum()


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def filter_quality(xyz, quality, min_quality):  # type: ignore[no-untyped-def]
    """NaN every valid point whose quality is below ``min_quality`` (or NaN); returns how many."""
    h, w = xyz.shape[0], xyz.shape[1]
    removed = np.zeros(h, np.int64)
    for r in prange(h):
        n = 0
        for c in range(w):
            if xyz[r, c, 2] == xyz[r, c, 2] and not quality[r, c] >= min_quality:
                xyz[r, c, 0] = _NAN
                xyz[r, c, 1] = _NAN
                xyz[r, c, 2] = _NAN
                n += 1
        removed[r] = n
    return removed.sum()


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def isolated_keep(xyz, min_nb, max_jump, keep):  # type: ignore[no-untyped-def]
    """keep[r, c] = valid point with >= ``min_nb`` of its 8 neighbours valid and nearer than ``max_jump``."""
    h, w = xyz.shape[0], xyz.shape[1]
    j2 = max_jump * max_jump
    for r in prange(h):
        for c in range(w):
            x = xyz[r, c, 0]
            y = xyz[r, c, 1]
            z = xyz[r, c, 2]
            if z != z:
                keep[r, c] = False
                continue
            n = 0
            for dr in range(-1, 2):
                rr = r + dr
                if rr < 0 or rr >= h:
                    continue
                for dc in range(-1, 2):
                    cc = c + dc
                    if (dr == 0 and dc == 0) or cc < 0 or cc >= w:
                        continue
                    ex = xyz[rr, cc, 0] - x
                    ey = xyz[rr, cc, 1] - y
                    ez = xyz[rr, cc, 2] - z
                    if ex * ex + ey * ey + ez * ez < j2:  # NaN neighbours compare false
                        n += 1
            keep[r, c] = n >= min_nb
    return keep


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def apply_keep(xyz, keep):  # type: ignore[no-untyped-def]
    """NaN the valid points where ``keep`` is False; returns how many."""
    h, w = xyz.shape[0], xyz.shape[1]
    removed = np.zeros(h, np.int64)
    for r in prange(h):
        n = 0
        for c in range(w):
            if not keep[r, c] and xyz[r, c, 2] == xyz[r, c, 2]:
                xyz[r, c, 0] = _NAN
                xyz[r, c, 1] = _NAN
                xyz[r, c, 2] = _NAN
                n += 1
        removed[r] = n
    return removed.sum()


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


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def row_counts(xyz):  # type: ignore[no-untyped-def]
    """Number of valid points in every row."""
    h, w = xyz.shape[0], xyz.shape[1]
    counts = np.zeros(h + 1, np.int64)
    for r in prange(h):
        n = 0
        for c in range(w):
            if xyz[r, c, 2] == xyz[r, c, 2]:
                n += 1
        counts[r + 1] = n
    return counts


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def compact(xyz, quality, intensity, nrm, starts, o_xyz, o_row, o_col, o_q, o_i, o_n):  # type: ignore[no-untyped-def]
    """Copy the valid points of the organised arrays into the cloud arrays (rows start at ``starts``)."""
    h, w = xyz.shape[0], xyz.shape[1]
    has_n = nrm.shape[0] == h
    for r in prange(h):
        k = starts[r]
        for c in range(w):
            if xyz[r, c, 2] != xyz[r, c, 2]:
                continue
            o_xyz[k, 0] = xyz[r, c, 0]
            o_xyz[k, 1] = xyz[r, c, 1]
            o_xyz[k, 2] = xyz[r, c, 2]
            o_row[k] = r
            o_col[k] = c
            o_q[k] = quality[r, c]
            o_i[k] = intensity[r, c]
            if has_n:
                o_n[k, 0] = nrm[r, c, 0]
                o_n[k, 1] = nrm[r, c, 1]
                o_n[k, 2] = nrm[r, c, 2]
            k += 1


# --- fused depth path: triangulate + neighbour filter to a depth map, then emit the kept points -----------
# Rays come from a coarse table (every ``step``-th row, linear in between): a row of rays is rebuilt in
# L1/L2 cache instead of streaming a full (H, W, 2) table from memory in each pass.


@njit(nogil=True, cache=True, error_model="numpy")
def _ray_row(tx, ty, r, step, mx, my):  # type: ignore[no-untyped-def]
    """Normalised ray (mx, my) of every pixel of row ``r``: Catmull-Rom cubic over the coarse table rows."""
    g = r // step + 1  # table row k holds pixel row (k - 1) * step
    t = np.float64(r - (g - 1) * step) / step
    _cubic_row(tx[g - 1], tx[g], tx[g + 1], tx[g + 2], t, mx)
    _cubic_row(ty[g - 1], ty[g], ty[g + 1], ty[g + 2], t, my)


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
def _plane_row_geometry(mx, my, c_lo, inv_dc, min_sin, rcp, tcp, axis, fc, ba, bz):  # type: ignore[no-untyped-def]
    """Per pixel of a row: fractional epipolar-line index (NaN if ill-posed) and the ray's coefficients."""
    a0 = 0 if axis == 0 else 1
    for c in range(mx.shape[0]):
        x = mx[c]
        y = my[c]
        bxc = rcp[0, 0] * x + rcp[0, 1] * y + rcp[0, 2]
        byc = rcp[1, 0] * x + rcp[1, 1] * y + rcp[1, 2]
        bzc = rcp[2, 0] * x + rcp[2, 1] * y + rcp[2, 2]
        l1 = tcp[1] * bzc - tcp[2] * byc
        l2 = tcp[2] * bxc - tcp[0] * bzc
        l3 = tcp[0] * byc - tcp[1] * bxc
        la = l2 if a0 == 0 else l1
        ok = (la * la >= min_sin * min_sin * (l1 * l1 + l2 * l2)) & (la != 0.0)
        fc[c] = (-l3 / la - c_lo) * inv_dc if ok else np.nan
        ba[c] = bxc if a0 == 0 else byc
        bz[c] = bzc


# Depth on the light surfaces in three loops over a row: two vectorise, the table gather between them is
# a short scalar loop (one long loop with the branches and the gather stays scalar and is ~2x slower).


@njit(nogil=True, cache=True, error_model="numpy")
def _plane_cells(code, mask, fc, nc, nu, code0, cell, tu, tv):  # type: ignore[no-untyped-def]
    """Flat index of each pixel's table cell (-1: undecoded or off the table) and its bilinear weights."""
    for c in range(code.shape[0]):
        fu = np.float64(code[c]) - code0
        f = fc[c]
        ok = mask[c] & (fu >= 0.0) & (f >= 0.0) & (fu < nu - 1) & (f < nc - 1)  # false for NaN too
        fu = fu if ok else 0.0
        f = f if ok else 0.0
        iu = np.int32(fu)
        ic = np.int32(f)
        tu[c] = fu - iu
        tv[c] = f - ic
        cell[c] = ic * np.int32(nu) + iu if ok else np.int32(-1)


@njit(nogil=True, cache=True, error_model="numpy")
def _plane_gather(flat, nu, cell, tu, tv, q):  # type: ignore[no-untyped-def]
    """Bilinear interpolation of the code-line table at each pixel's cell (NaN where none)."""
    for c in range(cell.shape[0]):
        k = cell[c]
        if k < 0:
            q[c] = np.nan
            continue
        q00 = np.float64(flat[k])
        q01 = np.float64(flat[k + 1])
        q10 = np.float64(flat[k + nu])
        q11 = np.float64(flat[k + nu + 1])
        a = q00 + tu[c] * (q01 - q00)
        b = q10 + tu[c] * (q11 - q10)
        q[c] = a + tv[c] * (b - a)


@njit(nogil=True, cache=True, error_model="numpy")
def _plane_depth(q, ba, bz, tc, ta, zmin, zmax, pz):  # type: ignore[no-untyped-def]
    """Depth where the ray meets the light surface through normalised coordinate q (NaN: out of range)."""
    for c in range(q.shape[0]):
        qq = q[c]
        z = (tc * qq - ta) / (ba[c] - bz[c] * qq)
        good = (z >= zmin) & (z <= zmax) & (tc + z * bz[c] > 0.0)  # NaN and inf fail
        pz[c] = z if good else np.nan


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _z_ray(cu, cv, mx, my, und, origin, kmat, d, rcp, tcp):  # type: ignore[no-untyped-def]
    """Depth of the ray (mx, my, 1) nearest (projector px) to the projector ray of (cu, cv); NaN if none."""
    hp, wp = und.shape[0], und.shape[1]
    fx, sk, cx = kmat[0, 0], kmat[0, 1], kmat[0, 2]
    fy, cy = kmat[1, 1], kmat[1, 2]
    fu = np.float64(cu) - origin
    fv = np.float64(cv) - origin
    if not (fu >= 0.0 and fv >= 0.0 and fu < wp - 1 and fv < hp - 1):
        return np.nan
    iu = int(fu)
    iv = int(fv)
    tu = fu - iu
    tv = fv - iv
    a = und[iv, iu, 0] + tu * (und[iv, iu + 1, 0] - und[iv, iu, 0])
    b = und[iv + 1, iu, 0] + tu * (und[iv + 1, iu + 1, 0] - und[iv + 1, iu, 0])
    xn = np.float64(a + tv * (b - a))
    a = und[iv, iu, 1] + tu * (und[iv, iu + 1, 1] - und[iv, iu, 1])
    b = und[iv + 1, iu, 1] + tu * (und[iv + 1, iu + 1, 1] - und[iv + 1, iu, 1])
    yn = np.float64(a + tv * (b - a))
    # one Newton step on the distortion model removes the table's interpolation error
    xd, yd, j11, j12, j21, j22 = distort_jac(xn, yn, d)
    eu = np.float64(cu) - (fx * xd + sk * yd + cx)
    ev = np.float64(cv) - (fy * yd + cy)
    ex = (eu - sk * ev / fy) / fx
    ey = ev / fy
    det = j11 * j22 - j12 * j21
    if det != 0.0:
        xn += (j22 * ex - j12 * ey) / det
        yn += (j11 * ey - j21 * ex) / det
    bx = rcp[0, 0] * mx + rcp[0, 1] * my + rcp[0, 2]
    by = rcp[1, 0] * mx + rcp[1, 1] * my + rcp[1, 2]
    bz = rcp[2, 0] * mx + rcp[2, 1] * my + rcp[2, 2]
    a1 = fx * (bx - xn * bz)
    b1 = fx * (xn * tcp[2] - tcp[0])
    a2 = fy * (by - yn * bz)
    b2 = fy * (yn * tcp[2] - tcp[1])
    nn = a1 * a1 + a2 * a2
    z = (a1 * b1 + a2 * b2) / nn if nn > 0.0 else np.nan
    return z if tcp[2] + z * bz > 0.0 else np.nan


@njit(nogil=True, cache=True, error_model="numpy")
def _depth_row(  # type: ignore[no-untyped-def]
    r, u, v, mask, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und, origin, kmat, d, rcp, tcp,
    axis, zmin, zmax, mx, my, fc, ba, bz, scratch, scratch_i, p,
):
    """Camera-frame point of every pixel of row ``r`` into the padded rows ``p`` (3, W + 2) (NaN: none)."""
    w = mx.shape[0]
    _ray_row(tx, ty, r, step, mx, my)
    px = p[0, 1 : w + 1]
    py = p[1, 1 : w + 1]
    pz = p[2, 1 : w + 1]
    if ray:
        ur = u[r]
        vr = v[r]
        mr = mask[r]
        for c in range(w):
            z = np.nan
            if mr[c]:
                z = _z_ray(ur[c], vr[c], mx[c], my[c], und, origin, kmat, d, rcp, tcp)
            pz[c] = z if (z >= zmin and z <= zmax) else np.nan
    else:
        nc, nu = table.shape[0], table.shape[1]
        cell, tu, tv, q = scratch_i[0], scratch[0], scratch[1], scratch[2]
        _plane_row_geometry(mx, my, c_lo, inv_dc, min_sin, rcp, tcp, axis, fc, ba, bz)
        _plane_cells(u[r] if axis == 0 else v[r], mask[r], fc, nc, nu, code0, cell, tu, tv)
        _plane_gather(table.reshape(nc * nu), nu, cell, tu, tv, q)
        _plane_depth(q, ba, bz, tcp[2], tcp[0] if axis == 0 else tcp[1], zmin, zmax, pz)
    _scale_rays(pz, mx, my, px, py)


@njit(nogil=True, cache=True, error_model="numpy")
def _scale_rays(pz, mx, my, px, py):  # type: ignore[no-untyped-def]
    for c in range(pz.shape[0]):
        z = np.float64(pz[c])
        px[c] = z * mx[c]
        py[c] = z * my[c]


# Neighbour counting visits each pair of neighbouring pixels once (4 pairs per pixel: right, and the three
# below) and credits both ends; every loop runs over whole rows with non-negative indices, so it vectorises.


@njit(nogil=True, cache=True, error_model="numpy")
def _near(px, py, pz, qx, qy, qz, j2, e):  # type: ignore[no-untyped-def]
    """e[c] = 1 where points p[c] and q[c] are nearer than sqrt(j2), else 0 (NaN compares false)."""
    for c in range(e.shape[0]):
        ex = qx[c] - px[c]
        ey = qy[c] - py[c]
        ez = qz[c] - pz[c]
        e[c] = np.int32(ex * ex + ey * ey + ez * ez < j2)


@njit(nogil=True, cache=True, error_model="numpy")
def _add2(n, a, b):  # type: ignore[no-untyped-def]
    for c in range(n.shape[0]):
        n[c] += a[c] + b[c]


@njit(nogil=True, cache=True, error_model="numpy")
def _add1(n, a):  # type: ignore[no-untyped-def]
    for c in range(n.shape[0]):
        n[c] += a[c]


@njit(nogil=True, cache=True, error_model="numpy")
def _pairs_in_row(p, j2, e, n):  # type: ignore[no-untyped-def]
    """Credit both pixels of every near horizontal pair of padded row p (3, W + 2) to n (W + 2,)."""
    w = p.shape[1] - 2
    # e[k]: padded columns k and k + 1 (the pads are NaN: pairs with them never count)
    _near(p[0, 0 : w + 1], p[1, 0 : w + 1], p[2, 0 : w + 1], p[0, 1 : w + 2], p[1, 1 : w + 2], p[2, 1 : w + 2],
          j2, e[: w + 1])  # fmt: skip
    _add2(n[1 : w + 1], e[0:w], e[1 : w + 1])


@njit(nogil=True, cache=True, error_model="numpy")
def _pairs_between_rows(p, q, j2, e, np_, nq):  # type: ignore[no-untyped-def]
    """Credit every near pair (p column c, q column c + off), off = -1, 0, 1, to np_ and nq (padded)."""
    w = p.shape[1] - 2
    for off in range(-1, 2):
        a = 1 + off
        _near(p[0, 1 : w + 1], p[1, 1 : w + 1], p[2, 1 : w + 1], q[0, a : a + w], q[1, a : a + w],
              q[2, a : a + w], j2, e[:w])  # fmt: skip
        _add1(np_[1 : w + 1], e[:w])
        _add1(nq[a : a + w], e[:w])


@njit(nogil=True, cache=True, error_model="numpy")
def _keep_row(pz, n, min_nb, out):  # type: ignore[no-untyped-def]
    """out = the depths of row pz kept by the neighbour count n; returns how many."""
    kept = np.int64(0)
    for c in range(out.shape[0]):
        z = pz[c]
        k = (z == z) & (n[c] >= min_nb)
        out[c] = z if k else np.float32(np.nan)
        kept += np.int64(k)
    return kept


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def depth_filtered(  # type: ignore[no-untyped-def]
    u, v, mask, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und, origin, kmat, d, rcp, tcp,
    axis, zmin, zmax, min_nb, jump, nchunks, nthreads, depth, counts,
):
    """Triangulate to camera-frame depth (H, W) and drop points with < ``min_nb`` near neighbours (NaN).

    ``counts[r + 1]`` receives the number of kept points of row r. Each chunk of rows keeps the points of
    two rows (padded with a NaN column each side) in a small ring, so no organised cloud is written.
    """
    h, w = depth.shape[0], depth.shape[1]
    j2 = np.float32(jump * jump)
    counts[0] = 0
    nthreads = min(nthreads, nchunks)
    for t in prange(nthreads):  # thread t takes chunks t, t + nthreads, ...: valid pixels cluster in rows
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        fc = np.empty(w, np.float64)
        ba = np.empty(w, np.float64)
        bz = np.empty(w, np.float64)
        scratch = np.empty((3, w), np.float64)
        scratch_i = np.empty((1, w), np.int32)
        ring = np.full((2, 3, w + 2), np.nan, np.float32)  # (slot, x/y/z, padded column)
        nb = np.zeros((2, w + 2), np.int32)
        e = np.empty(w + 1, np.int32)
        for ch in range(t, nchunks, nthreads):
            r0 = ch * h // nchunks
            r1 = (ch + 1) * h // nchunks
            _depth_chunk(r0, r1, u, v, mask, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und,
                         origin, kmat, d, rcp, tcp, axis, zmin, zmax, min_nb, j2, mx, my, fc, ba, bz, scratch,
                         scratch_i, ring, nb, e, depth, counts)  # fmt: skip
    return counts


@njit(nogil=True, cache=True, error_model="numpy")
def _depth_chunk(  # type: ignore[no-untyped-def]
    r0, r1, u, v, mask, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und, origin, kmat, d, rcp,
    tcp, axis, zmin, zmax, min_nb, j2, mx, my, fc, ba, bz, scratch, scratch_i, ring, nb, e, depth, counts,
):
    """Rows r0..r1 - 1 of :func:`depth_filtered` (computes rows r0 - 1 and r1 too, for the filter).

    ``ring`` (2, 3, W + 2) holds the points of rows r - 1 and r, ``nb`` (2, W + 2) their neighbour counts;
    row r - 1 is complete once the pairs it shares with row r are counted.
    """
    h, w = depth.shape[0], depth.shape[1]
    for r in range(r0 - 1, r1 + 1):
        s = (r - r0 + 1) % 2
        p = ring[s]
        if r < 0 or r >= h:
            p.fill(np.nan)
        else:
            _depth_row(r, u, v, mask, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und,
                       origin, kmat, d, rcp, tcp, axis, zmin, zmax, mx, my, fc, ba, bz, scratch, scratch_i,
                       p)  # fmt: skip
        if min_nb > 0:
            nb[s].fill(0)
            _pairs_in_row(p, j2, e, nb[s])
            if r > r0 - 1:
                _pairs_between_rows(ring[1 - s], p, j2, e, nb[1 - s], nb[s])
        if r - 1 >= r0:
            counts[r] = _keep_row(ring[1 - s][2, 1 : w + 1], nb[1 - s][1 : w + 1], min_nb, depth[r - 1])
    return counts


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def emit_points(  # type: ignore[no-untyped-def]
    depth, tx, ty, step, quality, intensity, rwc, cwc, to_world, starts, nchunks, nthreads,
    o_xyz, o_row, o_col, o_q, o_i,
):  # fmt: skip
    """Write the points of a depth map (world frame) and their pixel data at ``starts[r]`` per row."""
    h, w = depth.shape[0], depth.shape[1]
    has_i = intensity.shape[0] == h
    nthreads = min(nthreads, nchunks)
    for t in prange(nthreads):  # round-robin chunks: points cluster in rows
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        for ch in range(t, nchunks, nthreads):
            for r in range(ch * h // nchunks, (ch + 1) * h // nchunks):
                if starts[r + 1] == starts[r]:
                    continue
                _ray_row(tx, ty, r, step, mx, my)
                _emit_row(r, depth[r], mx, my, quality[r], intensity[r] if has_i else intensity[0], has_i,
                          rwc, cwc, to_world, starts[r], o_xyz, o_row, o_col, o_q, o_i)  # fmt: skip


@njit(nogil=True, cache=True, error_model="numpy")
def _emit_row(r, dr, mx, my, qr, ir, has_i, rwc, cwc, to_world, k, o_xyz, o_row, o_col, o_q, o_i):  # type: ignore[no-untyped-def]
    for c in range(dr.shape[0]):
        z = np.float64(dr[c])
        if z != z:
            continue
        px = z * mx[c]
        py = z * my[c]
        if to_world:
            o_xyz[k, 0] = rwc[0, 0] * px + rwc[0, 1] * py + rwc[0, 2] * z + cwc[0]
            o_xyz[k, 1] = rwc[1, 0] * px + rwc[1, 1] * py + rwc[1, 2] * z + cwc[1]
            o_xyz[k, 2] = rwc[2, 0] * px + rwc[2, 1] * py + rwc[2, 2] * z + cwc[2]
        else:
            o_xyz[k, 0] = px
            o_xyz[k, 1] = py
            o_xyz[k, 2] = z
        o_row[k] = r
        o_col[k] = c
        o_q[k] = qr[c]
        o_i[k] = ir[c] if has_i else 0
        k += 1


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def organised_from_depth(depth, tx, ty, step, rwc, cwc, to_world, out):  # type: ignore[no-untyped-def]
    """Organised world-frame cloud (H, W, 3) of a depth map (NaN where depth is NaN)."""
    h, w = depth.shape[0], depth.shape[1]
    for r in prange(h):
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        _ray_row(tx, ty, r, step, mx, my)
        for c in range(w):  # NaN depth: NaN point
            _store_point(out, r, c, np.float64(depth[r, c]), mx[c], my[c], -np.inf, np.inf, to_world, rwc, cwc)
    return out
