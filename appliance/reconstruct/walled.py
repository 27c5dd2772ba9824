"""Regions walled in by reflections: a band of points where two copies of the pattern coincide.

Where a mirror-like face meets the surface it lights (a concave corner of a glossy part), the mirrored copy of the
pattern falls nearly onto the direct one: next to the corner line the two codes differ by less than the decoder
can tell apart, so every code reads their light-weighted centroid, a point 1-2 mm off (and, on the mirror's side
of the line, ghosts behind it), and no pixel-local check sees it. Farther from the line the copies part, and the
decoder drops those pixels ("two copies of the pattern"); on the mirror the visibility check drops the ghosts
("hidden from the projector"). What is left is a narrow region of points walled in on its long sides by pixels
whose light came another way.

This check looks at each connected region of points (4-connected) of a camera: the share of its boundary (pixel
edges between a point and a pixel without one, the image border included) that touches a region of pixels
dropped as reflections (two copies, hidden, off the epipolar line; regions of at least :data:`MIN_WALL_AREA` of
the image, and two pixels around them, where the neighbour filter took the border: one pixel in a scan of one
exposure, two where an HDR fusion takes neighbours from different passes), and its mean width (twice its
area over its boundary). A region whose boundary is at least :data:`WALL_SHARE` walled and whose mean width is at
most :data:`MAX_WIDTH` of the image's larger side loses its points, with reason ``INTERREFLECTION``: the pattern
reaches it by two ways, as it does all around it. Stray marks (a few pixels of noise, or the holes of diffuse
interreflection) are no wall, and a wide region beside a mirror keeps its points.

On the mirror groove (480 x 384): one band of 3.2 k points (2.3 k of them > 1 mm off) goes; the points > 1 mm off
fall from 2.0 % to 0.16 %, those > 5 mm from 0.17 % to 0, beyond 5 sigma from 0.31 % to 0. Scanned at 20 ms (the
matte face clips) 0.05 % are > 1 mm off, and with two exposures (10 and 40 ms) 0.002 %; a wall border of one
pixel instead of two left 1.75 % and 1.7 % there. No other hard scene loses a point.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from appliance.reconstruct import _walled_kernels as _k
from appliance.reconstruct.types import Reason

WALL_SHARE = 0.6
"""A region of points loses them when at least this share of its boundary touches reflections (the mirror
groove's band: 0.94; the regions beside it 0.16 and 0.30)."""
MAX_WIDTH = 0.05
"""... and its mean width is at most this share of the image's larger side (the band: 11 px of 480)."""
MIN_WALL_AREA = 5e-4
"""A region of reflection pixels counts as a wall from this share of the image's pixels (92 px of 480 x 384):
a reflection covers a region, a stray mark does not."""
WALL_REASONS = (Reason.INTERREFLECTION, Reason.HIDDEN, Reason.EPIPOLAR)
"""The reasons of pixels whose light came another way."""
_WALL_LUT = np.zeros(256, np.uint8)
_WALL_LUT[[int(r) for r in WALL_REASONS]] = 1


def drop_walled(
    depth: npt.NDArray[np.float32],
    sigma: npt.NDArray[np.float32],
    reason: npt.NDArray[np.uint8],
    counts: npt.NDArray[np.int64],
    stats: npt.NDArray[np.int64],
    separated: npt.NDArray[np.float32] | None = None,
) -> int:
    """Drop the points of regions walled in by reflections (see the module docstring); their reason becomes
    ``INTERREFLECTION``.

    Parameters
    ----------
    depth, sigma : ndarray, shape (H, W), float32
        Depth (mm) and 1-sigma error (mm) of every kept point, NaN elsewhere; dropped points become NaN.
    reason : ndarray, shape (H, W), uint8
        The camera's reason map after the depth pass and the visibility check (0 where a point is kept).
    counts : ndarray, shape (H + 1,), int64
        Kept points per row (``counts[r + 1]``), lowered by the points dropped.
    stats : ndarray, shape (H, 6), int64
        The depth pass's per-row counts; its kept column (5) is lowered likewise.
    separated : ndarray, shape (N, 3), float32, optional
        The pixels whose direct code was taken apart from a second copy (``DecodedMaps.separated``: row,
        column, ...): lit by two copies, they wall in as the dropped ones do, and are no region of their own.

    Returns
    -------
    int
        Points dropped.
    """
    import cv2

    h, w = reason.shape
    walls = cv2.LUT(reason, _WALL_LUT)
    sep = None
    if separated is not None and len(separated):
        sep = np.zeros((h, w), np.bool_)
        sep[separated[:, 0].astype(np.int64), separated[:, 1].astype(np.int64)] = True
        walls[sep] = 1
    if not walls.any():
        return 0
    _n, wall_lab, wall_stats, _ = cv2.connectedComponentsWithStats(walls, connectivity=8)
    big = (wall_stats[:, cv2.CC_STAT_AREA] >= max(16.0, MIN_WALL_AREA * h * w)).astype(np.uint8)
    big[0] = 0
    if not big.any():
        return 0
    points = (reason == int(Reason.DECODED)) & np.isfinite(depth)
    if sep is not None:
        points &= ~sep
    n_p, lab = cv2.connectedComponents(points.view(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    edges = np.zeros(n_p, np.int64)
    walled = np.zeros(n_p, np.int64)
    area = np.zeros(n_p, np.int64)
    _k.region_edges(lab, np.asarray(wall_lab, np.int32), big, edges, walled, area)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = walled / edges
        width = 2.0 * area / edges
    drop = (share >= WALL_SHARE) & (width <= MAX_WIDTH * max(h, w))
    drop[0] = False
    if not drop.any():
        return 0
    per_row = np.zeros(h, np.int64)
    _k.drop_regions(lab, drop.astype(np.uint8), depth, sigma, reason, np.uint8(Reason.INTERREFLECTION), per_row)
    counts[1:] -= per_row
    stats[:, 5] -= per_row
    return int(per_row.sum())


def drop_isolated(
    depth: npt.NDArray[np.float32],
    sigma: npt.NDArray[np.float32],
    reason: npt.NDArray[np.uint8] | None,
    counts: npt.NDArray[np.int64],
    stats: npt.NDArray[np.int64],
) -> int:
    """Drop the points left without any of their 8 neighbours (reason ``FILTERED``).

    The neighbour filter judges each point by the neighbours it has before any is dropped, in one pass; where it
    drops a patch of ghost points around one that counted them, and the checks after it drop the rest of what
    was around, that point is left alone: on the mirror groove with periods [16, 8], one point 583 mm behind the
    back wall with a sigma of 1.1 mm. A point with no neighbour at all is never a surface this scanner resolves.

    Parameters
    ----------
    depth, sigma : ndarray, shape (H, W), float32
        Depth (mm) and 1-sigma error (mm) of every kept point, NaN elsewhere; dropped points become NaN.
    reason : ndarray, shape (H, W), uint8, optional
        The camera's reason map (0 where a point is kept); the dropped points get ``FILTERED``.
    counts : ndarray, shape (H + 1,), int64
        Kept points per row (``counts[r + 1]``), lowered by the points dropped.
    stats : ndarray, shape (H, 6), int64
        The depth pass's per-row counts; its with-neighbours (4) and kept (5) columns are lowered likewise.

    Returns
    -------
    int
        Points dropped.
    """
    h = depth.shape[0]
    per_row = np.zeros(h, np.int64)
    r_arg = reason if reason is not None else np.zeros((1, 1), np.uint8)
    _k.drop_isolated(depth, sigma, r_arg, reason is not None, np.uint8(Reason.FILTERED), per_row)
    counts[1:] -= per_row
    stats[:, 4] -= per_row
    stats[:, 5] -= per_row
    return int(per_row.sum())
