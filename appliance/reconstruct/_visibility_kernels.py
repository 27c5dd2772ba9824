"""numba kernels of the projector visibility check (private; see :mod:`appliance.reconstruct.visibility`).

A front buffer holds, per cell of the projector's normalised image plane (``x/z``, ``y/z`` in the projector
frame, undistorted: a cell is a bundle of projector rays, whatever the lens), the smallest projector-frame depth
``z`` of the points in it (float32, shape (cells,), +inf where none), a back buffer the largest (-inf where
none). Points come as camera depth maps (the
depth kernel's output, rays from the camera's row table) or as projector-frame points. The grid is ``grid`` =
(x0, y0, 1 / cell, columns, rows) in normalised units.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.reconstruct._geom_kernels import ray_row


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _cell(px, py, pz, grid):  # type: ignore[no-untyped-def]
    """Index of the cell of a projector-frame point (mm), or -1 when behind the projector or off the grid."""
    if not pz > 0.0:
        return -1
    inv = 1.0 / pz
    fx = math.floor((px * inv - grid[0]) * grid[2])
    fy = math.floor((py * inv - grid[1]) * grid[2])
    if not (0.0 <= fx < grid[3] and 0.0 <= fy < grid[4]):
        return -1
    return int(fy) * int(grid[3]) + int(fx)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _pixel_cell(x, y, z, rcp, tcp, grid):  # type: ignore[no-untyped-def]
    """Cell index (-1: none) and projector-frame depth (mm) of the camera-frame point ``z * (x, y, 1)``."""
    px = (rcp[0, 0] * x + rcp[0, 1] * y + rcp[0, 2]) * z + tcp[0]
    py = (rcp[1, 0] * x + rcp[1, 1] * y + rcp[1, 2]) * z + tcp[1]
    pz = (rcp[2, 0] * x + rcp[2, 1] * y + rcp[2, 2]) * z + tcp[2]
    return _cell(px, py, pz, grid), pz


@njit(nogil=True, cache=True, error_model="numpy")
def _fill_rows(depth, tx, ty, step, rcp, tcp, grid, stride, front, back, r0, r1):  # type: ignore[no-untyped-def]
    """Push the finite depths of every ``stride``-th row from r0 to r1 - 1 and every ``stride``-th column of a
    camera's map (mm, camera frame) into ``front`` (minimum) and ``back`` (maximum)."""
    w = depth.shape[1]
    mx = np.empty(w, np.float64)
    my = np.empty(w, np.float64)
    for r in range(r0 + (-r0) % stride, r1, stride):
        row = depth[r]
        ray_row(tx, ty, r, step, mx, my)
        for c in range(0, w, stride):
            z = row[c]
            if not z == z:
                continue
            i, pz = _pixel_cell(mx[c], my[c], z, rcp, tcp, grid)
            if i >= 0:
                if pz < front[i]:
                    front[i] = pz
                if pz > back[i]:
                    back[i] = pz


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def fill_from_depth(depth, tx, ty, step, rcp, tcp, grid, stride, fronts, backs):  # type: ignore[no-untyped-def]
    """Push every ``stride``-th depth (both ways) of a camera's map into the buffers ``fronts`` / ``backs``
    (B, cells): each of B row bands into its own (no shared writes), :func:`merge_fronts` then combines them."""
    h = depth.shape[0]
    nb = fronts.shape[0]
    for b in prange(nb):
        _fill_rows(depth, tx, ty, step, rcp, tcp, grid, stride, fronts[b], backs[b], b * h // nb, (b + 1) * h // nb)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def merge_fronts(fronts, backs, slope):  # type: ignore[no-untyped-def]
    """``fronts[0]`` / ``backs[0]`` = the minimum / maximum over the B buffers, cell by cell; returns the number of
    cells whose depths spread beyond ``slope`` times the front's (0: no point can be hidden)."""
    n = fronts.shape[1]
    nb = fronts.shape[0]
    spread = 0
    for i in prange(n):
        f = fronts[0, i]
        k = backs[0, i]
        for b in range(1, nb):
            f = min(f, fronts[b, i])
            k = max(k, backs[b, i])
        fronts[0, i] = f
        backs[0, i] = k
        if k > f + slope * f:
            spread += 1
    return spread


@njit(nogil=True, cache=True, error_model="numpy")
def fill_from_points(pts, grid, front):  # type: ignore[no-untyped-def]
    """Push projector-frame points (N, 3) mm into the front buffer (NaN rows skipped): evidence of a surface in
    front, never itself hidden."""
    for k in range(pts.shape[0]):
        px, py, pz = pts[k, 0], pts[k, 1], pts[k, 2]
        if not (px == px and py == py and pz == pz):
            continue
        i = _cell(px, py, pz, grid)
        if i >= 0 and pz < front[i]:
            front[i] = np.float32(pz)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def drop_hidden(  # type: ignore[no-untyped-def]
    depth, sigma, tx, ty, step, rcp, tcp, grid, front, slope, sigmas, reason, has_r, r_hidden, dropped
):
    """Drop every point of a camera's depth map that lies behind the nearest depth of its projector cell by more
    than ``slope * pz + sigmas * sigma`` (mm; ``slope``: the cell's footprint per mm of depth over the tangent of
    the steepest surface allowed, ``sigma`` the point's 1-sigma error, 0 where NaN): depth and sigma NaN, reason
    ``r_hidden`` (when ``has_r``), ``dropped[r]`` the points dropped in row r."""
    h, w = depth.shape
    for r in prange(h):
        dropped[r] = 0
        row = depth[r]
        mx = np.empty(w, np.float64)
        my = np.empty(w, np.float64)
        ray_row(tx, ty, r, step, mx, my)
        for c in range(w):
            z = row[c]
            if not z == z:
                continue
            i, pz = _pixel_cell(mx[c], my[c], z, rcp, tcp, grid)
            if i < 0:
                continue
            s = sigma[r, c]
            if pz > front[i] + slope * pz + (sigmas * s if s == s else 0.0):
                row[c] = np.float32(np.nan)
                sigma[r, c] = np.float32(np.nan)
                if has_r:
                    reason[r, c] = r_hidden
                dropped[r] += 1
