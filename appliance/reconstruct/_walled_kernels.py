"""numba kernels of the check for regions walled in by reflections (private; see
:mod:`appliance.reconstruct.walled`)."""

from __future__ import annotations

import numpy as np
from numba import njit

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)


@njit(nogil=True, cache=True)
def region_edges(lab, wall_lab, big, edges, walled, area):  # type: ignore[no-untyped-def]
    """Per region of points its area, its boundary edges (4-neighbours without a point, the image border
    included) and those whose outside pixel lies within 2 pixels of a big wall region."""
    h, w = lab.shape
    for r in range(h):
        for c in range(w):
            k = lab[r, c]
            if k == 0:
                continue
            area[k] += 1
            for d in range(4):
                rr = r + 1 if d == 0 else (r - 1 if d == 1 else r)
                cc = c + 1 if d == 2 else (c - 1 if d == 3 else c)
                inside = 0 <= rr < h and 0 <= cc < w
                if inside and lab[rr, cc] != 0:
                    continue
                edges[k] += 1
                if inside and _near_wall(wall_lab, big, rr, cc, h, w):
                    walled[k] += 1


@njit(nogil=True, cache=True, inline="always")
def _near_wall(wall_lab, big, r, c, h, w):  # type: ignore[no-untyped-def]
    """Whether a pixel within 2 of (r, c) (a 5 x 5 square) belongs to a big wall region."""
    for y in range(max(r - 2, 0), min(r + 3, h)):
        for x in range(max(c - 2, 0), min(c + 3, w)):
            if big[wall_lab[y, x]] != 0:
                return True
    return False


@njit(nogil=True, cache=True)
def drop_regions(lab, drop, depth, sigma, reason, value, per_row):  # type: ignore[no-untyped-def]
    """NaN depth and sigma, ``value`` as reason, for the pixels of the dropped regions; counted per row."""
    h, w = lab.shape
    for r in range(h):
        n = 0
        for c in range(w):
            if drop[lab[r, c]] != 0:
                depth[r, c] = np.nan
                sigma[r, c] = np.nan
                reason[r, c] = value
                n += 1
        per_row[r] = n


@njit(nogil=True, cache=True)
def drop_isolated(depth, sigma, reason, has_reason, value, per_row):  # type: ignore[no-untyped-def]
    """NaN depth and sigma (and ``value`` as reason where ``has_reason``) for every point none of whose 8
    neighbours has a point; counted per row. Dropping one such point leaves no other alone (it had no
    neighbour), so one pass is final."""
    h, w = depth.shape
    for r in range(h):
        n = 0
        for c in range(w):
            if not np.isfinite(depth[r, c]):
                continue
            alone = True
            for y in range(max(r - 1, 0), min(r + 2, h)):
                for x in range(max(c - 1, 0), min(c + 2, w)):
                    if (y != r or x != c) and np.isfinite(depth[y, x]):
                        alone = False
            if alone:
                depth[r, c] = np.nan
                sigma[r, c] = np.nan
                if has_reason:
                    reason[r, c] = value
                n += 1
        per_row[r] = n
