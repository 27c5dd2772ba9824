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
