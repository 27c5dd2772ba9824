"""Fusion of two depth estimates of the same pixels, weighted by their expected errors.

In mode ``both`` a reference camera has a camera-projector depth map and a camera-camera one on the same
pixel grid, each with its 1-sigma error. Where both exist the fused depth is the inverse-variance
weighted mean, ``z = (z1 / s1^2 + z2 / s2^2) / (1 / s1^2 + 1 / s2^2)``, with sigma
``1 / sqrt(1 / s1^2 + 1 / s2^2)``; a pixel where the two disagree by more than ``max_sigmas`` times the
sigma of their difference, ``sqrt(s1^2 + s2^2)``, is flagged (and, by default, left out: one of the two is
wrong, and averaging would hide it). Where only one exists it is taken as it is. Depths and sigmas are
along the same camera ray, so fusing depths fuses points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)

F32 = npt.NDArray[np.float32]

DISAGREE_SIGMAS = 3.0
"""Two estimates further apart than this many sigmas of their difference disagree."""


@dataclass(frozen=True)
class FusedDepth:
    """Result of :func:`fuse_depths` (all arrays (H, W), NaN where there is no depth).

    Attributes
    ----------
    depth : ndarray, float32
        Fused depth (mm).
    sigma : ndarray, float32
        Its 1-sigma error (mm).
    disagree : ndarray, bool
        Both estimates exist and differ by more than ``max_sigmas`` sigmas of their difference.
    source : ndarray, uint8
        0 none, 1 only the first, 2 only the second, 3 both fused, 4 disagreeing.
    """

    depth: F32
    sigma: F32
    disagree: npt.NDArray[np.bool_]
    source: npt.NDArray[np.uint8]

    def counts(self) -> dict[str, int]:
        """How many pixels came from each source (``first``, ``second``, ``fused``, ``disagree``)."""
        c = np.bincount(self.source.ravel(), minlength=5)
        return {"first": int(c[1]), "second": int(c[2]), "fused": int(c[3]), "disagree": int(c[4])}


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def _fuse(z1, s1, z2, s2, k, keep_disagree, depth, sigma, source):  # type: ignore[no-untyped-def]
    h, w = z1.shape[0], z1.shape[1]
    for r in prange(h):
        for c in range(w):
            a = np.float64(z1[r, c])
            b = np.float64(z2[r, c])
            sa = np.float64(s1[r, c])
            sb = np.float64(s2[r, c])
            ha = a == a and sa > 0.0  # a sigma that is NaN, 0 or negative is no estimate
            hb = b == b and sb > 0.0
            if ha and hb:
                va = sa * sa
                vb = sb * sb
                if abs(a - b) > k * np.sqrt(va + vb):
                    source[r, c] = 4
                    if keep_disagree:  # the more certain one
                        depth[r, c] = a if va <= vb else b
                        sigma[r, c] = sa if va <= vb else sb
                    else:
                        depth[r, c] = np.nan
                        sigma[r, c] = np.nan
                    continue
                wa = 1.0 / va
                wb = 1.0 / vb
                depth[r, c] = (a * wa + b * wb) / (wa + wb)
                sigma[r, c] = 1.0 / np.sqrt(wa + wb)
                source[r, c] = 3
            elif ha:
                depth[r, c] = a
                sigma[r, c] = sa
                source[r, c] = 1
            elif hb:
                depth[r, c] = b
                sigma[r, c] = sb
                source[r, c] = 2
            else:
                depth[r, c] = np.nan
                sigma[r, c] = np.nan
                source[r, c] = 0


def fuse_depths(
    depth1: F32,
    sigma1: F32,
    depth2: F32,
    sigma2: F32,
    max_sigmas: float = DISAGREE_SIGMAS,
    keep_disagreeing: bool = False,
) -> FusedDepth:
    """Fuse two organised depth maps of one camera by inverse-variance weighting; flag disagreements.

    Parameters
    ----------
    depth1, sigma1 : ndarray, shape (H, W)
        First estimate (e.g. camera-projector): depth along the camera's z (mm) and its 1-sigma error
        (mm, along the ray: the ratio to the depth error is the same for both maps); NaN where none.
    depth2, sigma2 : ndarray, shape (H, W)
        Second estimate (e.g. camera-camera) on the same pixel grid.
    max_sigmas : float
        Disagreement threshold in sigmas of the difference (> 0).
    keep_disagreeing : bool
        Keep the more certain estimate where they disagree (default: no depth there).

    Returns
    -------
    FusedDepth
        Depth, sigma, disagreement flags and the source of every pixel.

    Raises
    ------
    ValueError
        When the shapes differ or ``max_sigmas`` is not positive.
    """
    arrs = [np.ascontiguousarray(a, np.float32) for a in (depth1, sigma1, depth2, sigma2)]
    shape = arrs[0].shape
    if len(shape) != 2 or any(a.shape != shape for a in arrs):
        raise ValueError(
            f"fuse_depths: depth1 {arrs[0].shape}, sigma1 {arrs[1].shape}, depth2 {arrs[2].shape}, "
            f"sigma2 {arrs[3].shape}: must all be the same (H, W)"
        )
    if not max_sigmas > 0:
        raise ValueError(f"fuse_depths: max_sigmas = {max_sigmas}: must be > 0")
    depth = np.empty(shape, np.float32)
    sigma = np.empty(shape, np.float32)
    source = np.empty(shape, np.uint8)
    _fuse(arrs[0], arrs[1], arrs[2], arrs[3], float(max_sigmas), bool(keep_disagreeing), depth, sigma, source)
    return FusedDepth(depth, sigma, source == 4, source)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def _fuse_into(z1, s1, xyz, s2, rz, tz, k, keep_disagree, reason, has_r, decoded, filtered, counts, tally):  # type: ignore[no-untyped-def]
    h, w = z1.shape[0], z1.shape[1]
    for r in prange(h):
        kept = 0
        for c in range(w):
            a = np.float64(z1[r, c])
            sa = np.float64(s1[r, c])
            # the camera-camera point's depth along the camera's optical axis (its z in the camera frame)
            b = rz[0] * xyz[r, c, 0] + rz[1] * xyz[r, c, 1] + rz[2] * xyz[r, c, 2] + tz
            sb = np.float64(s2[r, c])
            ha = a == a and sa > 0.0  # a sigma that is NaN, 0 or negative is no estimate
            hb = b == b and sb > 0.0
            src = 0
            if ha and hb:
                va = sa * sa
                vb = sb * sb
                if abs(a - b) > k * np.sqrt(va + vb):
                    src = 4
                    if keep_disagree:  # the more certain one
                        z1[r, c] = a if va <= vb else b
                        s1[r, c] = sa if va <= vb else sb
                    else:
                        z1[r, c] = np.nan
                        s1[r, c] = np.nan
                else:
                    wa = 1.0 / va
                    wb = 1.0 / vb
                    z1[r, c] = (a * wa + b * wb) / (wa + wb)
                    s1[r, c] = 1.0 / np.sqrt(wa + wb)
                    src = 3
            elif ha:
                src = 1
            elif hb:
                z1[r, c] = b
                s1[r, c] = sb
                src = 2
            else:
                z1[r, c] = np.nan
                s1[r, c] = np.nan
            tally[r, src] += 1
            has = z1[r, c] == z1[r, c]
            kept += has
            if has_r:
                if has:
                    reason[r, c] = decoded
                elif reason[r, c] == decoded:
                    reason[r, c] = filtered
        counts[r + 1] = kept
    counts[0] = 0


def fuse_points_into(
    depth: F32,
    sigma: F32,
    xyz: F32,
    sigma_xyz: F32,
    axis_z: npt.NDArray[np.float64],
    offset_z: float,
    counts: npt.NDArray[np.int64],
    reason: npt.NDArray[np.uint8] | None = None,
    reason_codes: tuple[int, int] = (0, 0),
    max_sigmas: float = DISAGREE_SIGMAS,
    keep_disagreeing: bool = False,
) -> dict[str, int]:
    """:func:`fuse_depths` of a depth map and an organised cloud of the same camera, in place, in one pass.

    What the fused reconstruction needs without a full-image temporary: the cloud's depth along the camera's
    optical axis is taken per pixel, and the fused depth and sigma overwrite the first estimate.

    Parameters
    ----------
    depth, sigma : ndarray, shape (H, W), float32, C-contiguous
        First estimate (camera-projector): depth (mm) and its 1-sigma error (mm), NaN where none;
        overwritten by the fused depth and sigma.
    xyz : ndarray, shape (H, W, 3), float32
        Second estimate (camera-camera) as world points (mm) organised on the same pixels, NaN where none.
    sigma_xyz : ndarray, shape (H, W), float32
        Its 1-sigma error along the ray (mm).
    axis_z : ndarray, shape (3,), float64
        The camera's optical axis in the world frame (third row of its R): depth = ``axis_z . p + offset_z``.
    offset_z : float
        The camera's T[2] (mm).
    counts : ndarray, shape (H + 1,), int64
        Receives ``counts[r + 1]`` = pixels with a fused depth in row r, ``counts[0]`` = 0.
    reason : ndarray, shape (H, W), uint8, optional
        Reason map, updated: a pixel with a fused depth becomes ``reason_codes[0]`` (decoded), a decoded one
        that lost its depth (disagreement) ``reason_codes[1]`` (filtered).
    reason_codes : tuple of int
        (decoded, filtered) reason values.
    max_sigmas, keep_disagreeing
        As in :func:`fuse_depths`.

    Returns
    -------
    dict of str to int
        Pixels by source (``first``, ``second``, ``fused``, ``disagree``), as :meth:`FusedDepth.counts`.
    """
    h, w = depth.shape
    for name, a, shape in (("depth", depth, (h, w)), ("sigma", sigma, (h, w)), ("xyz", xyz, (h, w, 3)),
                           ("sigma_xyz", sigma_xyz, (h, w))):  # fmt: skip
        if a.shape != shape or a.dtype != np.float32 or not a.flags.c_contiguous:
            raise ValueError(f"fuse_points_into: {name} is {a.shape} {a.dtype}: must be C-contiguous float32 {shape}")
    if counts.shape != (h + 1,) or counts.dtype != np.int64:
        raise ValueError(f"fuse_points_into: counts is {counts.shape} {counts.dtype}: must be int64 {(h + 1,)}")
    if not max_sigmas > 0:
        raise ValueError(f"fuse_points_into: max_sigmas = {max_sigmas}: must be > 0")
    has_r = reason is not None
    rmap = reason if reason is not None else np.zeros((1, 1), np.uint8)
    if has_r and rmap.shape != (h, w):
        raise ValueError(f"fuse_points_into: reason is {rmap.shape}: must be {(h, w)}")
    tally = np.zeros((h, 5), np.int64)
    _fuse_into(depth, sigma, xyz, sigma_xyz, np.ascontiguousarray(axis_z, np.float64), float(offset_z),
               float(max_sigmas), bool(keep_disagreeing), rmap, has_r, np.uint8(reason_codes[0]),
               np.uint8(reason_codes[1]), counts, tally)  # fmt: skip
    c = tally.sum(axis=0)
    return {"first": int(c[1]), "second": int(c[2]), "fused": int(c[3]), "disagree": int(c[4])}
