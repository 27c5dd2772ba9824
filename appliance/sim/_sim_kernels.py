"""numba kernels of the virtual rig: ray casting against the scene and the per-frame photometry.

Private module: the public wrappers in ``scene.py`` and ``render.py`` check dtypes and shapes.

Scene packing
-------------
Analytic primitives are rows of ``prims`` (float64, (P, 16)) with a type code in ``prim_type``:

- ``PLANE``: point (0:3), unit normal (3:6)
- ``SPHERE``: centre (0:3), radius (3)
- ``BOX``: centre (0:3), half sizes (3:6), rotation local -> world row-major (6:15)
- ``CYLINDER``: centre (0:3), unit axis (3:6), radius (6), half height (7)

Triangles of all meshes are ``tri`` (float64, (M, 9): v0 v1 v2), ordered by a bounding volume hierarchy
(``bvh_min``/``bvh_max`` (B, 3), ``bvh_left``/``bvh_right`` children, ``bvh_start``/``bvh_count`` leaf
triangle ranges; ``bvh_count == 0`` for inner nodes). An empty hierarchy has no nodes.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import get_thread_id as numba_thread_id  # type: ignore[attr-defined]
from numba import njit, prange

import appliance._numba_cache as _numba_cache  # the cache folder, before any kernel is defined

KERNEL_LOCK = threading.Lock()
"""Held around the parallel kernels: numba's fallback 'workqueue' threading layer aborts the process when
two threads launch parallel kernels at once (e.g. two simulated cameras rendering together)."""

PLANE = 0
SPHERE = 1
BOX = 2
CYLINDER = 3

_INF = np.inf
_SQRT1_2 = 0.7071067811865476


# --- analytic primitives ---------------------------------------------------------------------------------


@njit(nogil=True, cache=True)
def _hit_plane(p: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
               t_min: float, nrm: np.ndarray) -> float:
    den = p[3] * dx + p[4] * dy + p[5] * dz
    if den == 0.0:
        return _INF
    t: float = (p[3] * (p[0] - ox) + p[4] * (p[1] - oy) + p[5] * (p[2] - oz)) / den
    if t <= t_min:
        return _INF
    nrm[0] = p[3]
    nrm[1] = p[4]
    nrm[2] = p[5]
    return t


@njit(nogil=True, cache=True)
def _hit_sphere(p: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
                t_min: float, nrm: np.ndarray) -> float:
    cx = ox - p[0]
    cy = oy - p[1]
    cz = oz - p[2]
    r: float = p[3]
    b = cx * dx + cy * dy + cz * dz
    dd = dx * dx + dy * dy + dz * dz
    # distance of the centre from the ray's line, computed stably (no b*b - c cancellation)
    qx = cx - b / dd * dx
    qy = cy - b / dd * dy
    qz = cz - b / dd * dz
    h = r * r - (qx * qx + qy * qy + qz * qz)
    if h < 0.0:
        return _INF
    s = math.sqrt(h * dd)
    # roots of dd t^2 + 2 b t + c = 0, the near one through the stable quadratic formula
    c = cx * cx + cy * cy + cz * cz - r * r
    q = -(b + s) if b >= 0.0 else -(b - s)
    if q == 0.0:
        return _INF
    t0 = q / dd
    t1 = c / q
    if t0 > t1:
        t0, t1 = t1, t0
    t: float = t0 if t0 > t_min else t1
    if t <= t_min:
        return _INF
    nrm[0] = (cx + t * dx) / r
    nrm[1] = (cy + t * dy) / r
    nrm[2] = (cz + t * dz) / r
    return t


@njit(nogil=True, cache=True)
def _hit_box(p: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
             t_min: float, nrm: np.ndarray) -> float:
    # ray in the box frame: x_local = R^T (x - c), R stored row-major in p[6:15]
    rx = ox - p[0]
    ry = oy - p[1]
    rz = oz - p[2]
    lo = (p[6] * rx + p[9] * ry + p[12] * rz, p[7] * rx + p[10] * ry + p[13] * rz,
          p[8] * rx + p[11] * ry + p[14] * rz)
    ld = (p[6] * dx + p[9] * dy + p[12] * dz, p[7] * dx + p[10] * dy + p[13] * dz,
          p[8] * dx + p[11] * dy + p[14] * dz)
    t_near = -_INF
    t_far = _INF
    ax_near = -1
    ax_far = -1
    for k in range(3):
        h = p[3 + k]
        if ld[k] == 0.0:
            if lo[k] < -h or lo[k] > h:
                return _INF
            continue
        ta = (-h - lo[k]) / ld[k]
        tb = (h - lo[k]) / ld[k]
        if ta > tb:
            ta, tb = tb, ta
        if ta > t_near:
            t_near = ta
            ax_near = k
        if tb < t_far:
            t_far = tb
            ax_far = k
    if t_near > t_far:
        return _INF
    if t_near > t_min:
        t = t_near
        ax = ax_near
    elif t_far > t_min:
        t = t_far
        ax = ax_far
    else:
        return _INF
    if ax < 0:
        return _INF
    sgn = 1.0 if lo[ax] + t * ld[ax] > 0.0 else -1.0
    nrm[0] = sgn * p[6 + 3 * 0 + ax]
    nrm[1] = sgn * p[6 + 3 * 1 + ax]
    nrm[2] = sgn * p[6 + 3 * 2 + ax]
    return t


@njit(nogil=True, cache=True)
def _hit_cylinder(p: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
                  t_min: float, nrm: np.ndarray) -> float:
    ax = p[3]
    ay = p[4]
    az = p[5]
    r = p[6]
    hh = p[7]
    cx = ox - p[0]
    cy = oy - p[1]
    cz = oz - p[2]
    oa = cx * ax + cy * ay + cz * az
    da = dx * ax + dy * ay + dz * az
    # components perpendicular to the axis
    px = cx - oa * ax
    py = cy - oa * ay
    pz = cz - oa * az
    qx = dx - da * ax
    qy = dy - da * ay
    qz = dz - da * az
    best = _INF
    kind = 0
    a = qx * qx + qy * qy + qz * qz
    if a > 0.0:
        b = px * qx + py * qy + pz * qz
        c = px * px + py * py + pz * pz - r * r
        disc = b * b - a * c
        if disc >= 0.0:
            s = math.sqrt(disc)
            q = -(b + s) if b >= 0.0 else -(b - s)
            if q != 0.0:
                for t in (q / a, c / q):
                    if t_min < t < best and abs(oa + t * da) <= hh:
                        best = t
                        kind = 1
    if da != 0.0:
        for side in (-1.0, 1.0):
            t = (side * hh - oa) / da
            if t_min < t < best:
                ex = px + t * qx
                ey = py + t * qy
                ez = pz + t * qz
                if ex * ex + ey * ey + ez * ez <= r * r:
                    best = t
                    kind = 2 if side > 0 else 3
    if kind == 1:
        nx = px + best * qx
        ny = py + best * qy
        nz = pz + best * qz
        inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
        nrm[0] = nx * inv
        nrm[1] = ny * inv
        nrm[2] = nz * inv
    elif kind == 2:
        nrm[0] = ax
        nrm[1] = ay
        nrm[2] = az
    elif kind == 3:
        nrm[0] = -ax
        nrm[1] = -ay
        nrm[2] = -az
    return best


@njit(nogil=True, cache=True)
def _hit_prim(kind: int, p: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
              t_min: float, nrm: np.ndarray) -> float:
    if kind == PLANE:
        return _hit_plane(p, ox, oy, oz, dx, dy, dz, t_min, nrm)
    if kind == SPHERE:
        return _hit_sphere(p, ox, oy, oz, dx, dy, dz, t_min, nrm)
    if kind == BOX:
        return _hit_box(p, ox, oy, oz, dx, dy, dz, t_min, nrm)
    if kind == CYLINDER:
        return _hit_cylinder(p, ox, oy, oz, dx, dy, dz, t_min, nrm)
    return _INF


# --- triangles (Möller–Trumbore) and the hierarchy -------------------------------------------------------


@njit(nogil=True, cache=True)
def _hit_triangle(v: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
                  t_min: float) -> float:
    e1x = v[3] - v[0]
    e1y = v[4] - v[1]
    e1z = v[5] - v[2]
    e2x = v[6] - v[0]
    e2y = v[7] - v[1]
    e2z = v[8] - v[2]
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return _INF
    inv = 1.0 / det
    sx = ox - v[0]
    sy = oy - v[1]
    sz = oz - v[2]
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return _INF
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    w = (dx * qx + dy * qy + dz * qz) * inv
    if w < 0.0 or u + w > 1.0:
        return _INF
    t: float = (e2x * qx + e2y * qy + e2z * qz) * inv
    if t <= t_min:
        return _INF
    return t


@njit(nogil=True, cache=True)
def _hit_aabb(bmin: np.ndarray, bmax: np.ndarray, ox: float, oy: float, oz: float,
              ix: float, iy: float, iz: float, t_min: float, t_max: float) -> bool:
    t0 = (bmin[0] - ox) * ix
    t1 = (bmax[0] - ox) * ix
    lo = min(t0, t1)
    hi = max(t0, t1)
    t0 = (bmin[1] - oy) * iy
    t1 = (bmax[1] - oy) * iy
    lo = max(lo, min(t0, t1))
    hi = min(hi, max(t0, t1))
    t0 = (bmin[2] - oz) * iz
    t1 = (bmax[2] - oz) * iz
    lo = max(lo, min(t0, t1))
    hi = min(hi, max(t0, t1))
    return bool(hi >= max(lo, t_min) and lo <= t_max)


@njit(nogil=True, cache=True)
def _safe_inv(d: float) -> float:
    if d == 0.0:
        return 1e300
    return 1.0 / d


@njit(nogil=True, cache=True)
def _cast_one(ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, t_min: float, t_max: float,
              any_hit: bool, prim_type: np.ndarray, prims: np.ndarray, prim_obj: np.ndarray,
              tri: np.ndarray, tri_obj: np.ndarray, bvh_min: np.ndarray, bvh_max: np.ndarray,
              bvh_left: np.ndarray, bvh_right: np.ndarray, bvh_start: np.ndarray, bvh_count: np.ndarray,
              nrm: np.ndarray, tmp: np.ndarray, stack: np.ndarray) -> tuple[float, int]:
    best = t_max
    obj = -1
    for k in range(prim_type.shape[0]):
        t = _hit_prim(prim_type[k], prims[k], ox, oy, oz, dx, dy, dz, t_min, tmp)
        if t < best:
            best = t
            obj = prim_obj[k]
            nrm[0] = tmp[0]
            nrm[1] = tmp[1]
            nrm[2] = tmp[2]
            if any_hit:
                return best, obj
    if bvh_min.shape[0] == 0:
        return best, obj
    ix = _safe_inv(dx)
    iy = _safe_inv(dy)
    iz = _safe_inv(dz)
    best_tri = -1
    top = 0
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        if not _hit_aabb(bvh_min[node], bvh_max[node], ox, oy, oz, ix, iy, iz, t_min, best):
            continue
        cnt = bvh_count[node]
        if cnt > 0:
            s = bvh_start[node]
            for j in range(s, s + cnt):
                t = _hit_triangle(tri[j], ox, oy, oz, dx, dy, dz, t_min)
                if t < best:
                    best = t
                    best_tri = j
                    if any_hit:
                        return best, tri_obj[j]
        elif top + 2 <= stack.shape[0]:
            stack[top] = bvh_left[node]
            stack[top + 1] = bvh_right[node]
            top += 2
    if best_tri >= 0:
        v = tri[best_tri]
        e1x = v[3] - v[0]
        e1y = v[4] - v[1]
        e1z = v[5] - v[2]
        e2x = v[6] - v[0]
        e2y = v[7] - v[1]
        e2z = v[8] - v[2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
        nrm[0] = nx * inv
        nrm[1] = ny * inv
        nrm[2] = nz * inv
        obj = tri_obj[best_tri]
    return best, obj


@njit(nogil=True, cache=True, parallel=True)
def cast_rays(origins: np.ndarray, dirs: np.ndarray, t_min: float, t_max: np.ndarray, any_hit: bool,
              prim_type: np.ndarray, prims: np.ndarray, prim_obj: np.ndarray, tri: np.ndarray,
              tri_obj: np.ndarray, bvh_min: np.ndarray, bvh_max: np.ndarray, bvh_left: np.ndarray,
              bvh_right: np.ndarray, bvh_start: np.ndarray, bvh_count: np.ndarray,
              t_out: np.ndarray, obj_out: np.ndarray, nrm_out: np.ndarray) -> None:
    """Nearest (or any) hit of N rays; ``origins`` (N, 3) or (1, 3), ``t_max`` (N,) or (1,)."""
    n = dirs.shape[0]
    shared_o = origins.shape[0] == 1
    shared_t = t_max.shape[0] == 1
    chunk = 4096
    for c in prange((n + chunk - 1) // chunk):
        nrm = np.zeros(3)
        tmp = np.zeros(3)
        stack = np.empty(64, dtype=np.int64)
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            io = 0 if shared_o else i
            it = 0 if shared_t else i
            t, obj = _cast_one(origins[io, 0], origins[io, 1], origins[io, 2], dirs[i, 0], dirs[i, 1],
                               dirs[i, 2], t_min, t_max[it], any_hit, prim_type, prims, prim_obj, tri,
                               tri_obj, bvh_min, bvh_max, bvh_left, bvh_right, bvh_start, bvh_count, nrm,
                               tmp, stack)
            if obj < 0:
                t_out[i] = np.inf
                obj_out[i] = -1
                nrm_out[i, 0] = 0.0
                nrm_out[i, 1] = 0.0
                nrm_out[i, 2] = 0.0
            else:
                t_out[i] = t
                obj_out[i] = obj
                nrm_out[i, 0] = nrm[0]
                nrm_out[i, 1] = nrm[1]
                nrm_out[i, 2] = nrm[2]


# --- per-frame photometry ----------------------------------------------------------------------------------


def _phi_table() -> np.ndarray:
    x = np.linspace(-_PHI_RANGE, _PHI_RANGE, _PHI_SIZE + 1)
    return np.array([0.5 * math.erfc(-v * _SQRT1_2) for v in x])


_PHI_RANGE = 6.0
_PHI_SIZE = 4096
_PHI_SCALE = _PHI_SIZE / (2.0 * _PHI_RANGE)
_PHI = _phi_table()  # standard normal CDF on [-6, 6]; linear interpolation is good to 3e-7


@njit(nogil=True, cache=True)
def _phi(x: float) -> float:
    t = (x + _PHI_RANGE) * _PHI_SCALE
    if t <= 0.0:
        return 0.0
    if t >= _PHI_SIZE:
        return 1.0
    k = int(t)
    f = t - k
    return float(_PHI[k] + f * (_PHI[k + 1] - _PHI[k]))


@njit(nogil=True, cache=True)
def gray_blurred(u: float, stripe: float, bit: int, sigma: float) -> float:
    """Gray bit ``bit`` of ``floor((u + 0.5) / stripe)`` (pixel centres at integers), blurred by N(0, sigma)

    The bit flips at codes ``2^bit (2m + 1)``: edges at ``run (2m + 1) - 0.5``, ``run = stripe 2^bit``. The
    blurred value is the local bit plus erf terms of the nearby edges, alternating in sign.
    """
    run = stripe * (1 << bit)
    m0 = math.floor(((u + 0.5) / run - 1.0) * 0.5)
    v0 = 1.0 - float(m0 & 1)
    if sigma <= 0.0:
        return v0
    s0 = 1.0 - 2.0 * v0
    period = 2.0 * run
    x_left = run * (2.0 * m0 + 1.0) - 0.5
    d_left = u - x_left
    d_right = x_left + period - u
    acc = 0.0
    sign = 1.0
    reach = 6.0 * sigma
    while d_left < reach or d_right < reach:
        acc += sign * (_phi(-d_left / sigma) + _phi(-d_right / sigma))
        d_left += period
        d_right += period
        sign = -sign
    return v0 + s0 * acc


@njit(nogil=True, cache=True)
def window_1d(u: float, size: int, sigma: float) -> float:
    """Light of a projector of ``size`` pixels (edges at -0.5 and size - 0.5) blurred by N(0, sigma)."""
    if sigma <= 0.0:
        return 1.0 if -0.5 <= u < size - 0.5 else 0.0
    return _phi((u + 0.5) / sigma) - _phi((u - size + 0.5) / sigma)


@njit(nogil=True, cache=True)
def _apply_gamma(light: float, gamma: float) -> float:
    if gamma != 1.0 and light > 0.0:
        return float(light**gamma)
    return light


@njit(nogil=True, cache=True, parallel=True)
def shade_const(level: float, gain: np.ndarray, ambient: np.ndarray, gamma: float, out: np.ndarray) -> None:
    """``out = ambient + gain * level ** gamma`` (white: level 1, black: 0)."""
    light = _apply_gamma(level, gamma)
    for i in prange(out.shape[0]):
        out[i] = ambient[i] + gain[i] * light


@njit(nogil=True, cache=True, parallel=True)
def shade_gray(coord: np.ndarray, gain: np.ndarray, ambient: np.ndarray, stripe: float, bit: int,
               inverted: bool, sigma: float, gamma: float, out: np.ndarray) -> None:
    """``out = ambient + gain * gray_blurred(coord) ** gamma`` (inverted: 1 - the bit)."""
    for i in prange(out.shape[0]):
        g = gain[i]
        if g > 0.0:
            light = gray_blurred(coord[i], stripe, bit, sigma)
            if inverted:
                light = 1.0 - light
            out[i] = ambient[i] + g * _apply_gamma(light, gamma)
        else:
            out[i] = ambient[i]


@njit(nogil=True, cache=True, parallel=True)
def shade_gray_xor(coord: np.ndarray, gain: np.ndarray, ambient: np.ndarray, stripe: float, bit: int, base: int,
                   inverted: bool, sigma: float, gamma: float, out: np.ndarray) -> None:
    """:func:`shade_gray` of Gray bit ``bit`` XOR bit ``base`` (an XOR code frame). Blurred, ``a + b - 2ab`` of the
    two blurred bits: exact where at most one of them has an edge within the blur's reach (Gray bits never
    flip at the same code, so for stripes of at least 6 sigma)."""
    for i in prange(out.shape[0]):
        g = gain[i]
        if g > 0.0:
            a = gray_blurred(coord[i], stripe, bit, sigma)
            b = gray_blurred(coord[i], stripe, base, sigma)
            light = a + b - 2.0 * a * b
            if inverted:
                light = 1.0 - light
            out[i] = ambient[i] + g * _apply_gamma(light, gamma)
        else:
            out[i] = ambient[i]


TRIG_STEPS = 1 << 16
"""Entries per turn of :data:`TRIG` (linear interpolation between them is good to 1.2e-9)."""


def _trig_table() -> np.ndarray:
    """``cos`` and ``sin`` of ``2 pi k / TRIG_STEPS`` for k = 0 .. TRIG_STEPS, shape (TRIG_STEPS + 1, 2), float64."""
    t = 2.0 * np.pi * np.arange(TRIG_STEPS + 1) / TRIG_STEPS
    return np.ascontiguousarray(np.stack([np.cos(t), np.sin(t)], axis=1))


TRIG = _trig_table()


@njit(nogil=True, cache=True, parallel=True)
def shade_phase(coord: np.ndarray, turns_per_px: float, trig: np.ndarray, gain: np.ndarray, ambient: np.ndarray,
                mc: float, ms: float, gamma: float, out: np.ndarray) -> None:
    """``out = ambient + gain * ((1 + mc cos t - ms sin t) / 2) ** gamma`` with ``t = 2 pi turns_per_px coord``:
    m cos(t + phase0) expanded; cos t and sin t interpolated in ``trig`` (:data:`TRIG`, 1 MB, in cache)
    instead of per-pixel tables (8 bytes a pixel per phase period)."""
    steps = float(TRIG_STEPS)
    mask = TRIG_STEPS - 1
    linear = gamma == 1.0  # decided once: a power in the loop (even one never taken) stops it vectorising
    for i in prange(out.shape[0]):
        g = gain[i]
        x = turns_per_px * float(coord[i]) * steps
        f = math.floor(x)
        frac = x - f
        k = int(f) & mask
        c = trig[k, 0] + frac * (trig[k + 1, 0] - trig[k, 0])
        sn = trig[k, 1] + frac * (trig[k + 1, 1] - trig[k, 1])
        light = 0.5 * (1.0 + mc * c - ms * sn)
        out[i] = ambient[i] + (g * light if linear else (g * _apply_gamma(light, gamma) if g > 0.0 else 0.0))


def _normal_table() -> np.ndarray:
    """Inverse normal CDF at ``k / 2**16`` (ends clipped half a step in), scaled to unit variance."""
    from statistics import NormalDist

    n = 1 << 16
    p = np.clip(np.arange(n + 1) / n, 0.5 / n, 1.0 - 0.5 / n)
    inv = NormalDist().inv_cdf
    t = np.array([inv(float(v)) for v in p])
    a, b = t[:-1], t[1:]
    return t / math.sqrt(float(np.mean((a * a + a * b + b * b) / 3.0)))  # piecewise-linear variance -> 1


_NORMAL = _normal_table()
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S16 = np.uint64(16)
_S27 = np.uint64(27)
_S30 = np.uint64(30)
_S31 = np.uint64(31)
_S32 = np.uint64(32)
_LOW16 = np.uint64(0xFFFF)


@njit(nogil=True, cache=True)
def _splitmix64(x: np.uint64) -> np.uint64:
    z = (x ^ (x >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit(nogil=True, cache=True)
def _normal(bits: np.uint64) -> float:
    """A standard normal deviate from 32 random bits: 16 pick a quantile bin, 16 interpolate in it."""
    k = int((bits >> _S16) & _LOW16)
    f = float(bits & _LOW16) * (1.0 / 65536.0)
    return float(_NORMAL[k] + f * (_NORMAL[k + 1] - _NORMAL[k]))


@njit(nogil=True, cache=True)
def _noisy(x: float, z: float, read_var: float, shot_scale: float, scale: float, full: float) -> float:
    var = read_var + shot_scale * max(x, 0.0)
    y = math.floor((x + math.sqrt(var) * z) * scale + 0.5)
    return min(max(y, 0.0), full)


@njit(nogil=True, cache=True, parallel=True)
def add_noise_quantise(clean: np.ndarray, key: np.uint64, read_var: float, shot_scale: float, scale: float,
                       full: float, out: np.ndarray) -> None:
    """``out = clip(rint(scale * (clean + sqrt(read_var + shot_scale * clean) * N(0, 1))), 0, full)``.

    The normal deviates come from a counter-based generator (splitmix64 of ``key`` and the pixel pair
    index through a 65536-bin inverse-CDF table; tails end at 4.4 sigma), so the result depends on
    ``key`` only, not on the thread count.
    """
    n = out.shape[0]
    for j in prange((n + 1) // 2):
        h = _splitmix64(key + np.uint64(j) * _GOLDEN)
        i = 2 * j
        out[i] = _noisy(clean[i], _normal(h >> _S32), read_var, shot_scale, scale, full)
        if i + 1 < n:
            out[i + 1] = _noisy(clean[i + 1], _normal(h), read_var, shot_scale, scale, full)


@njit(nogil=True, cache=True, parallel=True)
def projector_window(u: np.ndarray, v: np.ndarray, width: int, height: int, sigma: float,
                     out: np.ndarray) -> None:
    """Blurred light of the projector's image rectangle at (u, v); 0 where either is not finite."""
    for i in prange(out.shape[0]):
        if math.isfinite(u[i]) and math.isfinite(v[i]):
            out[i] = window_1d(u[i], width, sigma) * window_1d(v[i], height, sigma)
        else:
            out[i] = 0.0


@njit(nogil=True, cache=True, parallel=True)
def affine_rows(a: np.ndarray, m: np.ndarray, t: np.ndarray, out: np.ndarray) -> None:
    """``out[i] = m @ a[i] + t`` for (N, 3) rows (no BLAS: its threads fight numba's on small machines)."""
    for i in prange(a.shape[0]):
        x = a[i, 0]
        y = a[i, 1]
        z = a[i, 2]
        for r in range(3):
            out[i, r] = m[r, 0] * x + m[r, 1] * y + m[r, 2] * z + t[r]


@njit(nogil=True, cache=True, parallel=True)
def project_points(xyz: np.ndarray, R: np.ndarray, T: np.ndarray, K: np.ndarray, d: np.ndarray,
                   uv: np.ndarray, z_out: np.ndarray) -> None:
    """The formula of ``CameraModel.project`` (8 distortion coefficients ``d``); NaN behind the device."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    for i in prange(xyz.shape[0]):
        x = xyz[i, 0]
        y = xyz[i, 1]
        z = xyz[i, 2]
        px = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + T[0]
        py = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + T[1]
        pz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + T[2]
        z_out[i] = pz
        if not pz > 0.0:
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan
            continue
        xn = px / pz
        yn = py / pz
        r2 = xn * xn + yn * yn
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        uv[i, 0] = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        uv[i, 1] = K[1, 1] * yd + K[1, 2]



BLUR_RADIUS = 4
"""Taps either side of the blur kernels (a compile-time constant, so the tap loop unrolls and the pixel loop
vectorises); a wider Gaussian is applied as several narrower ones (their variances add)."""


def gaussian_passes(sigma: float) -> tuple[int, np.ndarray]:
    """``(n, w)``: the Gaussian of ``sigma`` (px) as ``n`` passes of one of ``sigma / sqrt(n)`` whose radius
    ``round(4 sigma / sqrt(n))`` fits :data:`BLUR_RADIUS`; ``w`` its weights, shape (2 BLUR_RADIUS + 1,),
    float32, normalised, zero beyond that radius."""
    n = max(1, math.ceil((4.0 * sigma / (BLUR_RADIUS + 0.5)) ** 2))
    s = sigma / math.sqrt(n)
    r = max(1, min(BLUR_RADIUS, round(4.0 * s)))
    x = np.arange(-BLUR_RADIUS, BLUR_RADIUS + 1, dtype=np.float64)
    w = np.where(np.abs(x) <= r, np.exp(-0.5 * (x / s) ** 2), 0.0)
    return n, (w / w.sum()).astype(np.float32)


def blur_scratch(height: int, width: int) -> np.ndarray:
    """Scratch rows for :func:`gaussian_blur_inplace` of an (H, W) image: one per thread for the horizontal
    pass, then the vertical pass's ring of ``2 BLUR_RADIUS + 1`` rows; float32."""
    rows = max(int(_numba_cache.config.NUMBA_NUM_THREADS), 2 * BLUR_RADIUS + 1)
    return np.empty((rows, width + 2 * BLUR_RADIUS), np.float32)


@njit(nogil=True, cache=True, parallel=True)
def gaussian_blur_inplace(img: np.ndarray, w: np.ndarray, scratch: np.ndarray) -> None:
    """One pass of a separable blur of ``img`` (H, W, float32, C order) in place, borders replicated.

    ``w`` (2 :data:`BLUR_RADIUS` + 1,) symmetric weights (:func:`gaussian_passes`), ``scratch``
    :func:`blur_scratch`. Rows are blurred in parallel (each through its thread's padded copy), columns in
    one pass down the image that keeps the original rows it still needs in a ring.
    """
    h, wd = img.shape
    rad = BLUR_RADIUS
    for y in prange(h):
        buf = scratch[numba_thread_id()]
        for x in range(wd):
            buf[x + rad] = img[y, x]
        for x in range(rad):
            buf[x] = buf[rad]
            buf[wd + rad + x] = buf[wd + rad - 1]
        for x in range(wd):
            acc = w[rad] * buf[x + rad]
            for k in range(rad):
                acc += w[k] * (buf[x + k] + buf[x + 2 * rad - k])
            img[y, x] = acc
    _blur_columns(img, w, scratch)


@njit(nogil=True, cache=True)
def _blur_columns(img: np.ndarray, w: np.ndarray, ring: np.ndarray) -> None:
    """The vertical pass of :func:`gaussian_blur_inplace`: original row ``j`` lives in ``ring[j % n]``."""
    h, wd = img.shape
    rad = BLUR_RADIUS
    n = 2 * rad + 1
    for j in range(min(rad, h)):
        for x in range(wd):
            ring[j % n, x] = img[j, x]
    for y in range(h):
        j = y + rad
        if j < h:  # the last original row this one needs; not yet overwritten
            for x in range(wd):
                ring[j % n, x] = img[j, x]
        row = img[y]
        mid = ring[y % n]
        for x in range(wd):
            row[x] = w[rad] * mid[x]
        for k in range(rad):
            lo = ring[min(max(y - rad + k, 0), h - 1) % n]
            hi = ring[min(max(y + rad - k, 0), h - 1) % n]
            wk = w[k]
            for x in range(wd):
                row[x] += wk * (lo[x] + hi[x])
