"""numba kernels of camera-projector triangulation (private; see ``triangulate.py``).

Ray / light-surface (one coded axis) through the code-line table, ray-ray (both axes), and the fused depth
path: triangulate + neighbour filter to a depth map, then emit the kept points.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.geometry._distortion_kernels import distort_jac
from appliance.reconstruct._filter_kernels import keep_row, pairs_between_spans, pairs_in_span
from appliance.reconstruct._geom_kernels import NAN32 as _NAN
from appliance.reconstruct._geom_kernels import ray_row, ray_span, store_point, true_span


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
            store_point(out, r, col, z if tc + z * bz > 0.0 else np.nan, mx, my, zmin, zmax, to_world, rwc, cwc)
    return out

@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def tri_ray(u, v, mask, norm, und, origin, kmat, d, rcp, tcp, rwc, cwc, to_world, zmin, zmax, out):  # type: ignore[no-untyped-def]
    """Ray-ray triangulation: the point on the camera ray nearest (in projector px) to the coded ray."""
    h, w = u.shape[0], u.shape[1]
    for r in prange(h):
        for col in range(w):
            mx = np.float64(norm[r, col, 0])
            my = np.float64(norm[r, col, 1])
            z = _z_ray(u[r, col], v[r, col], mx, my, und, origin, kmat, d, rcp, tcp)[0] if mask[r, col] else np.nan
            store_point(out, r, col, z, mx, my, zmin, zmax, to_world, rwc, cwc)
    return out

# --- fused depth path -----------------------------------------------------------------------------------


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
def _plane_gather(flat, nu, cell, tu, tv, q, dq):  # type: ignore[no-untyped-def]
    """Bilinear interpolation of the code-line table at each pixel's cell, and its slope per code px."""
    for c in range(cell.shape[0]):
        k = cell[c]
        if k < 0:
            q[c] = np.nan
            dq[c] = np.nan
            continue
        q00 = np.float64(flat[k])
        q01 = np.float64(flat[k + 1])
        q10 = np.float64(flat[k + nu])
        q11 = np.float64(flat[k + nu + 1])
        d0 = q01 - q00
        d1 = q11 - q10
        a = q00 + tu[c] * d0
        b = q10 + tu[c] * d1
        q[c] = a + tv[c] * (b - a)
        dq[c] = d0 + tv[c] * (d1 - d0)


@njit(nogil=True, cache=True, error_model="numpy")
def _plane_depth(q, dq, ba, bz, tc, ta, pz, gz):  # type: ignore[no-untyped-def]
    """Depth where the ray meets the light surface through q (NaN: behind), and |dz / du| (mm per code px)."""
    for c in range(q.shape[0]):
        qq = q[c]
        den = ba[c] - bz[c] * qq
        z = (tc * qq - ta) / den
        good = tc + z * bz[c] > 0.0  # NaN and inf fail
        pz[c] = z if good else np.nan
        gz[c] = abs((tc * ba[c] - ta * bz[c]) / (den * den) * dq[c])


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _z_ray(cu, cv, mx, my, und, origin, kmat, d, rcp, tcp):  # type: ignore[no-untyped-def]
    """Depth of the ray (mx, my, 1) nearest (projector px) to the projector ray of (cu, cv); NaN if none.

    Also returns ``g``: the depth error per px of equal, independent code errors on both axes (mm / px),
    ``Zp sqrt(a1^2 + a2^2) / (a1^2 + a2^2)`` from the linearised least squares (Zp: projector-frame depth),
    and ``e``: how far (u, v) lies off the pixel's epipolar line (projector px, the least-squares residual
    ``|a1 b2 - a2 b1| / (|a| Zp)``); NaN where there is no point.
    """
    hp, wp = und.shape[0], und.shape[1]
    fx, sk, cx = kmat[0, 0], kmat[0, 1], kmat[0, 2]
    fy, cy = kmat[1, 1], kmat[1, 2]
    fu = np.float64(cu) - origin
    fv = np.float64(cv) - origin
    if not (fu >= 0.0 and fv >= 0.0 and fu < wp - 1 and fv < hp - 1):
        return np.nan, np.nan, np.nan
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
    if not nn > 0.0:
        return np.nan, np.nan, np.nan
    z = (a1 * b1 + a2 * b2) / nn
    zp = tcp[2] + z * bz
    rn = math.sqrt(nn)
    return (z if zp > 0.0 else np.nan), zp / rn, abs(a1 * b2 - a2 * b1) / (rn * zp)


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def code_noise_var(q, w, has_w, g2, svar, rvar, inv_e):  # type: ignore[no-untyped-def]
    """A pixel's code variance from the camera noise (px^2): ``g2 (rvar + A inv_e) / q^2 + svar`` with the mean
    level ``A = w - q / 2`` (``q / 2`` without a white image); see ``uncertainty.CodeNoise``."""
    a = np.float64(w) - 0.5 * q if has_w else 0.5 * q
    return g2 * (rvar + max(a, 0.0) * inv_e) / (q * q) + svar


@njit(nogil=True, cache=True, error_model="numpy")
def _finish_row(pz, gz, er, mx, my, qr, wr, has_w, noise, epi, zmin, zmax, jump, inv_f, px, py, ps, pj, pw):  # type: ignore[no-untyped-def]
    """Epipolar check, depth range, 1-sigma error along the ray (mm), jump limit and x, y of every point of a row.

    ``noise`` = (phase_px, stripe var, read + rounding var, 1 / e- per DN), see ``uncertainty.CodeNoise``:
    ``sigma = |dz/du| sqrt(su2 (1 + x^2 + y^2))``, ``su2 = phase_px^2 (read var + A / e-) / q^2 + stripe var``
    (the code variance per axis, px^2) with the mean level ``A = white - q / 2`` (``q / 2`` without white).
    ``epi`` = (k^2, floor^2 px^2, on): with both axes coded (on = 1), a point whose epipolar residual ``er``
    (px) exceeds ``sqrt(k^2 su2 + floor^2)`` is dropped (never with an unknown su2). The jump limit is
    ``jump[0] + jump[1] z inv_f + jump[2] sigma`` (the sigma term left out when ``jump[2]`` is 0: sigma may be
    unknown). Dropped and out-of-range depths become NaN; ``pw`` gets each pixel's outcome (0 a point, 1 no
    point in range, 2 off the epipolar line). Returns how many points were triangulated, how many passed the
    epipolar check and how many of those are in range.
    """
    g2 = noise[0] * noise[0]
    svar, rvar, inv_e = noise[1], noise[2], noise[3]
    j0, jf, js = jump[0], jump[1] * inv_f, jump[2]
    use_s = js != 0.0
    k2, f2, use_e = epi[0], epi[1], epi[2] != 0.0
    n_t = np.int64(0)
    n_e = np.int64(0)
    n_r = np.int64(0)
    for c in range(pz.shape[0]):
        z = np.float64(pz[c])
        q = np.float64(qr[c])
        x = mx[c]
        y = my[c]
        su2 = code_noise_var(q, wr[c] if has_w else 0.0, has_w, g2, svar, rvar, inv_e)
        sg = gz[c] * math.sqrt(su2 * (1.0 + x * x + y * y))
        fin = z == z
        e = np.float64(er[c]) if use_e else 0.0
        off = fin & (e * e > k2 * su2 + f2)  # false for an unknown (NaN) su2
        cons = fin & ~off
        inr = cons & (z >= zmin) & (z <= zmax)
        n_t += np.int64(fin)
        n_e += np.int64(cons)
        n_r += np.int64(inr)
        pw[c] = np.float32(0.0) if inr else (np.float32(2.0) if off else np.float32(1.0))
        z = z if inr else np.float64(np.nan)
        pz[c] = z
        ps[c] = sg
        pj[c] = j0 + jf * z + (js * sg if use_s else 0.0)
        px[c] = z * x
        py[c] = z * y
    return n_t, n_e, n_r


@njit(nogil=True, cache=True, error_model="numpy")
def _count_true(m):  # type: ignore[no-untyped-def]
    n = np.int64(0)
    for c in range(m.shape[0]):
        n += np.int64(m[c])
    return n


@njit(nogil=True, cache=True, error_model="numpy")
def _clear(p, lo, hi):  # type: ignore[no-untyped-def]
    """NaN padded columns lo .. hi - 1 of every channel of ring row p."""
    for k in range(p.shape[0]):
        for c in range(lo, hi):
            p[k, c] = np.float32(np.nan)


@njit(nogil=True, cache=True, error_model="numpy")
def _depth_row(  # type: ignore[no-untyped-def]
    r, c0, c1, u, v, mask, quality, white, has_w, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und,
    origin, kmat, d, rcp, tcp, axis, zmin, zmax, noise, epi, jump, inv_f, mx, my, fc, ba, bz, scratch, scratch_i,
    p, st,
):
    """Camera-frame points of pixels c0 .. c1 - 1 of row ``r`` into padded columns 1 + c0 .. of ``p`` (6, W + 2).

    Channels: x, y, z, sigma, jump limit (NaN: no point), outcome (see ``_finish_row``). ``st`` (4,) receives
    the row's decoded, triangulated, epipolar-consistent and in-range counts. Every stage runs over the
    decoded span of the row only.
    """
    ray_span(tx, ty, r, step, mx, my, c0, c1)
    mxs, mys = mx[c0:c1], my[c0:c1]
    px = p[0, 1 + c0 : 1 + c1]
    py = p[1, 1 + c0 : 1 + c1]
    pz = p[2, 1 + c0 : 1 + c1]
    ps = p[3, 1 + c0 : 1 + c1]
    pj = p[4, 1 + c0 : 1 + c1]
    pw = p[5, 1 + c0 : 1 + c1]
    gz = scratch[3, c0:c1]
    er = scratch[0, c0:c1]  # the epipolar residual (ray-ray; the light-surface path reuses the row as scratch)
    mr = mask[r, c0:c1]
    if ray:
        ur = u[r, c0:c1]
        vr = v[r, c0:c1]
        for c in range(c1 - c0):
            z = np.nan
            g = np.nan
            e = np.nan
            if mr[c]:
                z, g, e = _z_ray(ur[c], vr[c], mxs[c], mys[c], und, origin, kmat, d, rcp, tcp)
            pz[c] = z
            gz[c] = g
            er[c] = e
    else:
        nc, nu = table.shape[0], table.shape[1]
        cell, tu, tv, q = scratch_i[0, c0:c1], scratch[0, c0:c1], scratch[1, c0:c1], scratch[2, c0:c1]
        fcs, bas, bzs = fc[c0:c1], ba[c0:c1], bz[c0:c1]
        _plane_row_geometry(mxs, mys, c_lo, inv_dc, min_sin, rcp, tcp, axis, fcs, bas, bzs)
        _plane_cells(u[r, c0:c1] if axis == 0 else v[r, c0:c1], mr, fcs, nc, nu, code0, cell, tu, tv)
        _plane_gather(table.reshape(nc * nu), nu, cell, tu, tv, q, tu)  # the slope overwrites tu
        _plane_depth(q, tu, bas, bzs, tcp[2], tcp[0] if axis == 0 else tcp[1], pz, gz)
    st[0] = _count_true(mr)
    wr = white[r, c0:c1] if has_w else white[0]
    st[1], st[2], st[3] = _finish_row(pz, gz, er, mxs, mys, quality[r, c0:c1], wr, has_w, noise, epi, zmin, zmax,
                                      jump, inv_f, px, py, ps, pj, pw)  # fmt: skip


class DepthParams(NamedTuple):
    """The scalar settings of one :func:`depth_filtered` call (numba reads it as a typed tuple; build it with
    these Python types so that every call has the one signature the warm-up compiled)."""

    has_w: bool
    """A white image is given (it weights each point's sigma); else ``white`` is a (1, 1) placeholder."""
    step: int
    """Rows between two entries of the ray row tables ``tx`` / ``ty`` (px)."""
    ray: bool
    """Both axes coded: ray-ray triangulation (``und``, ``origin``); else light plane through ``table``."""
    code0: float
    """Projector code of the code-line table's first column (projector px)."""
    c_lo: float
    """Epipolar-line coordinate of the table's first row."""
    inv_dc: float
    """1 / the table's row spacing (rows per unit of epipolar-line coordinate)."""
    min_sin: float
    """Sine of the smallest angle between a camera ray and a projector light plane that is triangulated."""
    origin: float
    """Ray-ray: the code origin subtracted before the undistortion lookup (projector px)."""
    axis: int
    """Coded axis of the light planes: 0 columns (x), 1 rows (y)."""
    zmin: float
    """Nearest depth kept (mm, camera frame)."""
    zmax: float
    """Farthest depth kept (mm, camera frame)."""
    max_sigma: float
    """Points whose 1-sigma error exceeds this are dropped after the neighbour filter (mm; inf: none)."""
    inv_f: float
    """1 / the camera's focal length (1/px): a pixel's footprint at depth z is z * inv_f (mm)."""
    min_nb: int
    """Near neighbours (of 8) a point needs to be kept."""
    nchunks: int
    """Row chunks the rows are split into (each keeps a two-row ring)."""
    nthreads: int
    """Threads that take the chunks in turn."""
    has_r: bool
    """Write every decoded pixel's outcome into ``reason``."""


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def depth_filtered(  # type: ignore[no-untyped-def]
    u, v, mask, quality, white, tx, ty, table, und, kmat, d, rcp, tcp, noise, epi, jump, p, depth, sigma, counts,
    stats, spans, reason, rcodes,
):
    """Triangulate to camera-frame depth and sigma (H, W), dropping points with < ``p.min_nb`` near neighbours.

    ``p`` is a :class:`DepthParams` (the scalars); the arrays are as below.

    Points off their epipolar line (both axes; ``epi``, see ``_finish_row``) and out of range are dropped
    first. A neighbour is near when closer than the mean of the two points' limits ``jump[0] + jump[1] z
    inv_f + jump[2] sigma`` (mm); after that filter, points with sigma over ``p.max_sigma`` are dropped.
    ``counts[r + 1]`` receives the kept points of row r, ``stats[r]`` (6,) its decoded, triangulated,
    epipolar-consistent, in-range, with-neighbours and kept counts, ``spans[r]`` the columns (first, last +
    1) that may hold points. With ``p.has_r``, ``reason`` (H, W) gets on every decoded pixel ``rcodes`` =
    (point, out of range, off the epipolar line, filtered)[outcome]; other pixels are not touched. Each chunk
    of rows keeps the points of two rows (padded with a NaN column each side) in a small ring, so no
    organised cloud is written; every row is processed over its decoded span only.
    """
    has_w, step, ray = p.has_w, p.step, p.ray
    code0, c_lo, inv_dc, min_sin, origin = p.code0, p.c_lo, p.inv_dc, p.min_sin, p.origin
    axis, zmin, zmax, max_sigma, inv_f = p.axis, p.zmin, p.zmax, p.max_sigma, p.inv_f
    min_nb, nchunks, has_r = p.min_nb, p.nchunks, p.has_r
    h, w = depth.shape[0], depth.shape[1]
    counts[0] = 0
    nthreads = min(p.nthreads, nchunks)
    for t in prange(nthreads):  # thread t takes chunks t, t + nthreads, ...: valid pixels cluster in rows
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        fc = np.empty(w, np.float64)
        ba = np.empty(w, np.float64)
        bz = np.empty(w, np.float64)
        scratch = np.empty((4, w), np.float64)
        scratch_i = np.empty((1, w), np.int32)
        ring = np.full((2, 6, w + 2), np.nan, np.float32)  # (slot, x/y/z/sigma/jump/outcome, padded column)
        held = np.zeros((2, 2), np.int64)  # padded columns [lo, hi) of each slot that may hold points
        nb = np.zeros((2, w + 2), np.int32)
        e = np.empty(w + 1, np.int32)
        st = np.zeros(4, np.int64)
        for ch in range(t, nchunks, nthreads):
            r0 = ch * h // nchunks
            r1 = (ch + 1) * h // nchunks
            _depth_chunk(r0, r1, u, v, mask, quality, white, has_w, tx, ty, step, ray, table, code0, c_lo,
                         inv_dc, min_sin, und, origin, kmat, d, rcp, tcp, axis, zmin, zmax, noise, epi, max_sigma,
                         jump, inv_f, min_nb, mx, my, fc, ba, bz, scratch, scratch_i, ring, held, nb, e, st, depth,
                         sigma, counts, stats, spans, reason, has_r, rcodes)  # fmt: skip
    return counts


@njit(nogil=True, cache=True, error_model="numpy")
def _depth_chunk(  # type: ignore[no-untyped-def]
    r0, r1, u, v, mask, quality, white, has_w, tx, ty, step, ray, table, code0, c_lo, inv_dc, min_sin, und,
    origin, kmat, d, rcp, tcp, axis, zmin, zmax, noise, epi, max_sigma, jump, inv_f, min_nb, mx, my, fc, ba, bz,
    scratch, scratch_i, ring, held, nb, e, st, depth, sigma, counts, stats, spans, reason, has_r, rcodes,
):
    """Rows r0..r1 - 1 of :func:`depth_filtered` (computes rows r0 - 1 and r1 too, for the filter).

    ``ring`` (2, 6, W + 2) holds the points of rows r - 1 and r, ``nb`` (2, W + 2) their neighbour counts,
    ``held`` the padded column span of each slot; row r - 1 is complete once the pairs it shares with row r
    are counted. Outside a slot's span the ring is NaN and its counts are never read.
    """
    h, w = depth.shape[0], depth.shape[1]
    for r in range(r0 - 1, r1 + 1):
        s = (r - r0 + 1) % 2
        p = ring[s]
        c0, c1 = (0, 0) if (r < 0 or r >= h) else true_span(mask[r])
        lo, hi = c0 + 1, c1 + 1
        # clear what the slot held two rows ago outside the new span (the span itself is overwritten)
        o0, o1 = held[s, 0], held[s, 1]
        if hi <= lo:
            _clear(p, o0, o1)
            lo, hi = 0, 0
        else:
            _clear(p, o0, min(o1, lo))
            _clear(p, max(o0, hi), o1)
            _depth_row(r, c0, c1, u, v, mask, quality, white, has_w, tx, ty, step, ray, table, code0, c_lo,
                       inv_dc, min_sin, und, origin, kmat, d, rcp, tcp, axis, zmin, zmax, noise, epi, jump, inv_f,
                       mx, my, fc, ba, bz, scratch, scratch_i, p, st)  # fmt: skip
        held[s, 0], held[s, 1] = lo, hi
        if 0 <= r < h and r0 <= r < r1:
            if hi > lo:
                stats[r, 0], stats[r, 1], stats[r, 2], stats[r, 3] = st[0], st[1], st[2], st[3]
            else:
                stats[r, 0], stats[r, 1], stats[r, 2], stats[r, 3] = 0, 0, 0, 0
            spans[r, 0], spans[r, 1] = c0, c1
        if min_nb > 0:
            for c in range(lo, hi):
                nb[s, c] = 0
            pairs_in_span(p, e, nb[s], lo, hi)
            if r > r0 - 1:
                pairs_between_spans(ring[1 - s], p, e, nb[1 - s], nb[s], held[1 - s, 0], held[1 - s, 1], lo, hi)
        if r - 1 >= r0:
            q = ring[1 - s]
            if min_nb > 0:
                _border_neighbours(nb[1 - s], r - 1, h, w, held[1 - s, 0], held[1 - s, 1])
            k_nb, k = keep_row(q[2, 1 : w + 1], q[3, 1 : w + 1], nb[1 - s][1 : w + 1], min_nb, max_sigma,
                               depth[r - 1], sigma[r - 1])  # fmt: skip
            counts[r] = k
            stats[r - 1, 4] = k_nb
            stats[r - 1, 5] = k
            if has_r:
                _row_reasons(q[5], depth[r - 1], mask[r - 1], held[1 - s, 0] - 1, held[1 - s, 1] - 1, rcodes,
                             reason[r - 1])  # fmt: skip
    return counts


@njit(nogil=True, cache=True, error_model="numpy")
def _border_neighbours(nbr, r, h, w, lo, hi):  # type: ignore[no-untyped-def]
    """A pixel on the image's border has no neighbour beyond it: those count as near (3 on a side, 5 in a
    corner), so the filter judges the neighbours that exist and the border keeps its points. ``nbr`` padded
    (W + 2,), counts of row ``r`` in padded columns ``lo .. hi - 1``."""
    if r == 0 or r == h - 1:
        for c in range(lo, hi):
            nbr[c] += 3
    nbr[1] += 3
    nbr[w] += 3


@njit(nogil=True, cache=True, error_model="numpy")
def _row_reasons(outcome, dr, mr, c0, c1, rcodes, out):  # type: ignore[no-untyped-def]
    """Reason of each decoded pixel of columns c0 .. c1 - 1 of a finished row: ``rcodes[outcome]``, and
    ``rcodes[3]`` (filtered) for a point the neighbour or sigma filter removed. ``outcome`` is padded."""
    for c in range(c0, c1):
        if mr[c]:
            k = np.int64(outcome[c + 1])
            out[c] = rcodes[3] if (k == 0) & (dr[c] != dr[c]) else rcodes[k]


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def emit_points(  # type: ignore[no-untyped-def]
    depth, sigma, spans, tx, ty, step, quality, intensity, rwc, cwc, to_world, starts, nchunks, nthreads,
    o_xyz, o_row, o_col, o_q, o_i, o_s,
):  # fmt: skip
    """Write the points of a depth map (world frame) and their pixel data at ``starts[r]`` per row.

    Row r's points lie in columns ``spans[r, 0] .. spans[r, 1] - 1`` (``spans`` of shape (1, 2): anywhere).
    """
    h, w = depth.shape[0], depth.shape[1]
    has_i = intensity.shape[0] == h
    has_s = sigma.shape[0] == h
    has_sp = spans.shape[0] == h
    nthreads = min(nthreads, nchunks)
    for t in prange(nthreads):  # round-robin chunks: points cluster in rows
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        for ch in range(t, nchunks, nthreads):
            for r in range(ch * h // nchunks, (ch + 1) * h // nchunks):
                if starts[r + 1] == starts[r]:
                    continue
                c0, c1 = (spans[r, 0], spans[r, 1]) if has_sp else (0, w)
                ray_span(tx, ty, r, step, mx, my, c0, c1)
                _emit_row(r, c0, c1, depth[r], sigma[r] if has_s else sigma[0], has_s, mx, my, quality[r],
                          intensity[r] if has_i else intensity[0], has_i, rwc, cwc, to_world, starts[r], starts[r + 1],
                          o_xyz, o_row, o_col, o_q, o_i, o_s)  # fmt: skip


@njit(nogil=True, cache=True, error_model="numpy")
def _emit_row(  # type: ignore[no-untyped-def]
    r, c0, c1, dr, sr, has_s, mx, my, qr, ir, has_i, rwc, cwc, to_world, k, kend, o_xyz, o_row, o_col, o_q, o_i,
    o_s,
):  # fmt: skip
    """Points of columns c0 .. c1 - 1 of row r into indices k .. kend - 1, without a branch per pixel.

    Every pixel is written at ``k`` and ``k`` advances only past a point, so a pixel without one is
    overwritten by the next point; the loop ends with the row's last point (``kend``), so nothing is
    written past the row's range.
    """
    r00, r01, r02 = rwc[0, 0], rwc[0, 1], rwc[0, 2]
    r10, r11, r12 = rwc[1, 0], rwc[1, 1], rwc[1, 2]
    r20, r21, r22 = rwc[2, 0], rwc[2, 1], rwc[2, 2]
    t0, t1, t2 = cwc[0], cwc[1], cwc[2]
    nan = np.float32(np.nan)
    for c in range(c0, c1):
        if k >= kend:
            break
        z = np.float64(dr[c])
        px = z * mx[c]
        py = z * my[c]
        if to_world:
            o_xyz[k, 0] = r00 * px + r01 * py + r02 * z + t0
            o_xyz[k, 1] = r10 * px + r11 * py + r12 * z + t1
            o_xyz[k, 2] = r20 * px + r21 * py + r22 * z + t2
        else:
            o_xyz[k, 0] = px
            o_xyz[k, 1] = py
            o_xyz[k, 2] = z
        o_row[k] = r
        o_col[k] = c
        o_q[k] = qr[c]
        o_i[k] = ir[c] if has_i else 0
        o_s[k] = sr[c] if has_s else nan
        k += np.int64(z == z)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def organised_from_depth(depth, tx, ty, step, rwc, cwc, to_world, out):  # type: ignore[no-untyped-def]
    """Organised world-frame cloud (H, W, 3) of a depth map (NaN where depth is NaN)."""
    h, w = depth.shape[0], depth.shape[1]
    for r in prange(h):
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        ray_row(tx, ty, r, step, mx, my)
        for c in range(w):  # NaN depth: NaN point
            store_point(out, r, c, np.float64(depth[r, c]), mx[c], my[c], -np.inf, np.inf, to_world, rwc, cwc)
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def u8_histogram(img, nchunks, step, out):  # type: ignore[no-untyped-def]
    """Counts of each value 0..255 of every ``step``-th row of a uint8 image ``img`` (H, W) into ``out`` (256,)
    int64; ``nchunks`` row chunks counted in parallel."""
    h = img.shape[0]
    part = np.zeros((nchunks, 256), np.int64)
    for ch in prange(nchunks):
        y0 = ch * h // nchunks
        y0 += (-y0) % step
        for y in range(y0, (ch + 1) * h // nchunks, step):
            row = img[y]
            for x in range(row.shape[0]):
                part[ch, row[x]] += 1
    for k in range(256):
        t = np.int64(0)
        for ch in range(nchunks):
            t += part[ch, k]
        out[k] = t


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _widen(zr, sr, c, b, q, wv, has_w, g2, svar, rvar, inv_e, max_sigma):  # type: ignore[no-untyped-def]
    """Widen the sigma of the point at column ``c`` of a row by the code variance ``b`` (px^2); True when that
    takes it over ``max_sigma`` (its depth and sigma are then NaN)."""
    su2n = code_noise_var(np.float64(q), wv, has_w, g2, svar, rvar, inv_e)
    s = np.float64(sr[c]) * math.sqrt(1.0 + b / su2n)
    if s > max_sigma:
        zr[c] = np.float32(np.nan)
        sr[c] = np.float32(np.nan)
        return True
    sr[c] = np.float32(s)
    return False


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def indirect_bias(  # type: ignore[no-untyped-def]
    depth, sigma, quality, white, has_w, fringe, has_f, ftab, eoff, ecols, evar, has_e, noise, max_sigma, reason,
    has_r, r_filtered, dropped, widened,
):  # fmt: skip
    """Widen every point's sigma by the bias of indirect light and drop those then over ``max_sigma`` (mm).

    A point's sigma (its code noise, see ``_finish_row``: ``su2n`` px^2 from ``quality``, ``white`` and
    ``noise``) becomes ``sigma sqrt(1 + (ftab[fringe] + e) / su2n)``: the code variance gains the table's
    bias variance (when ``has_f``) and the pixel's extra variance ``e`` (px^2; when ``has_e``, given sparsely:
    row ``r``'s entries are ``eoff[r] .. eoff[r + 1] - 1`` of ``ecols`` (ascending columns) and ``evar``), and
    the derivative along the ray is unchanged. A point whose widened sigma exceeds ``max_sigma`` loses its depth
    and sigma (NaN), gets reason ``r_filtered`` (when ``has_r``), and counts in ``dropped[r]`` (its row);
    ``widened[r]`` counts the row's points whose sigma the indirect term grew (kept or not).
    """
    h, w = depth.shape
    g2 = noise[0] * noise[0]
    svar, rvar, inv_e = noise[1], noise[2], noise[3]
    for r in prange(h):
        dropped[r] = 0
        widened[r] = 0
        zr = depth[r]
        sr = sigma[r]
        k = eoff[r] if has_e else 0
        kend = eoff[r + 1] if has_e else 0
        if not has_f:  # the sparse entries alone
            for j in range(k, kend):
                c = ecols[j]
                b = np.float64(evar[j])
                if b == 0.0 or not zr[c] == zr[c]:
                    continue
                if _widen(zr, sr, c, b, quality[r, c], white[r, c] if has_w else 0.0, has_w, g2, svar, rvar, inv_e,
                          max_sigma):  # fmt: skip
                    if has_r:
                        reason[r, c] = r_filtered
                    dropped[r] += 1
            continue
        fr = fringe[r]
        for c in range(w):
            # the 1-byte share first: most pixels have no bias, and their depth is not read
            b = ftab[fr[c]]
            bf = b
            while k < kend and ecols[k] < c:
                k += 1
            if k < kend and ecols[k] == c:
                b += np.float64(evar[k])
            if b == 0.0 or not zr[c] == zr[c]:
                continue
            if bf > 0.0:
                widened[r] += 1
            if _widen(zr, sr, c, b, quality[r, c], white[r, c] if has_w else 0.0, has_w, g2, svar, rvar, inv_e,
                      max_sigma):  # fmt: skip
                if has_r:
                    reason[r, c] = r_filtered
                dropped[r] += 1
