"""The camera-camera neighbour filter judges agreement by sigma; a missing neighbour counts neither way.

On an organised plane 1 m away with sigma 0.2 mm: a one-pixel hole and a row of holes keep every point around
them (with the old rule, 8 valid near neighbours, each hole grew by a pixel all round); a point 30 mm off the
plane (a mixed pixel on a depth edge) goes, and so does a lone point with no neighbour.
"""

from __future__ import annotations

import math

import numpy as np

from appliance.reconstruct import _stereo_kernels as C


def _plane(h: int = 40, w: int = 50) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    xyz = np.stack([xs * 0.4, ys * 0.4, 1000.0 + 0.05 * xs], axis=2).astype(np.float32)
    return np.ascontiguousarray(xyz), np.full((h, w), 0.2, np.float32)


def _keep(xyz: np.ndarray, sigma: np.ndarray, min_neighbours: int = 8) -> np.ndarray:
    keep = np.empty(xyz.shape[:2], np.bool_)
    # the pipeline's defaults: 6 sigmas + 6 pixel footprints (z / f with f = 2500 px)
    C.agree_keep_sigma(xyz, sigma, 8 - min_neighbours, min(min_neighbours, 2), 0.0, 6.0, 6.0, 1 / 2500.0,
                       math.inf, keep)  # fmt: skip
    return keep


def test_holes_do_not_grow() -> None:
    xyz, sigma = _plane()
    xyz[10, 10] = np.nan  # a one-pixel hole
    xyz[20, 5:45] = np.nan  # a row of holes (a moire line)
    keep = _keep(xyz, sigma)
    valid = np.isfinite(xyz[..., 2])
    np.testing.assert_array_equal(keep, valid)


def test_a_point_off_the_surface_and_a_lone_point_go() -> None:
    xyz, sigma = _plane()
    xyz[30, 30, 2] += 30.0  # a mixed pixel: 30 mm off, every neighbour disagrees
    xyz[2:7, 40:47] = np.nan
    xyz[4, 43] = (17.2, 1.6, 1002.0)  # alone in a hole
    keep = _keep(xyz, sigma)
    assert not keep[30, 30] and not keep[4, 43]
    assert keep[29:32, 29:32].sum() == 0  # the neighbours of the outlier see it beyond their limit too
    with np.errstate(invalid="ignore"):
        rest = np.isfinite(xyz[..., 2])
    rest[29:32, 29:32] = False
    rest[4, 43] = False
    np.testing.assert_array_equal(keep[rest], True)


def test_a_noisy_neighbour_is_judged_by_both_sigmas() -> None:
    xyz, sigma = _plane()
    xyz[15, 15, 2] += 8.0  # 8 mm off: beyond 6 x 0.2 mm + footprints, within 6 x hypot(0.2, 2) mm
    assert not _keep(xyz, sigma)[15, 15]
    sigma[15, 15] = 2.0
    assert _keep(xyz, sigma)[15, 15]


def test_min_neighbours_zero_keeps_every_point() -> None:
    xyz, sigma = _plane()
    xyz[5, 5, 2] += 50.0
    assert _keep(xyz, sigma, 0).all()
