"""Regions of points walled in by reflections (``appliance.reconstruct.walled``) on made-up reason maps.

The mirror groove, rendered, is in ``tests/accuracy/test_hard_scenes.py``.
"""

from __future__ import annotations

import numpy as np

from appliance.reconstruct.types import Reason
from appliance.reconstruct.walled import drop_isolated, drop_walled

H, W = 120, 200


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # type: ignore[type-arg]
    reason = np.zeros((H, W), np.uint8)
    depth = np.full((H, W), 500.0, np.float32)
    sigma = np.full((H, W), 0.1, np.float32)
    return reason, depth, sigma


def _run(reason: np.ndarray, depth: np.ndarray, sigma: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:  # type: ignore[type-arg]
    depth[reason != 0] = np.nan
    sigma[reason != 0] = np.nan
    counts = np.concatenate([[0], (reason == 0).sum(axis=1)]).astype(np.int64)
    stats = np.zeros((H, 6), np.int64)
    stats[:, 5] = counts[1:]
    n = drop_walled(depth, sigma, reason, counts, stats)
    assert np.array_equal(counts[1:], (reason == 0).sum(axis=1)) and np.array_equal(stats[:, 5], counts[1:])
    return n, counts, stats


def test_a_band_between_two_reflections_loses_its_points_and_says_why() -> None:
    reason, depth, sigma = _scene()
    reason[10:110, 60:90] = Reason.HIDDEN  # ghosts seen in the mirror
    reason[10:110, 101:140] = Reason.INTERREFLECTION  # two copies, parted
    reason[10:110, 100] = Reason.FILTERED  # the neighbour filter's border next to them
    reason[:10, :] = reason[110:, :] = Reason.SHADOW  # the band's ends: no wall
    band = (slice(10, 110), slice(90, 100))
    n, _, _ = _run(reason, depth, sigma)
    assert n == 100 * 10
    assert np.all(reason[band] == Reason.INTERREFLECTION) and np.all(np.isnan(depth[band]))
    assert np.all(np.isnan(sigma[band]))
    assert np.all(reason[10:110, :60] == Reason.DECODED)  # the region beside the reflection keeps its points
    assert np.all(reason[10:110, 140:] == Reason.DECODED)


def test_a_wide_region_beside_a_mirror_and_stray_marks_keep_their_points() -> None:
    reason, depth, sigma = _scene()
    reason[:, :40] = Reason.HIDDEN  # a mirror all along the left
    reason[:, 160:] = Reason.INTERREFLECTION  # and two copies along the right: walled, but 120 px wide
    rng = np.random.default_rng(1)
    marks = rng.integers(0, [H, W], (300, 2))
    reason[marks[:, 0], marks[:, 1]] = Reason.INTERREFLECTION  # stray marks: holes, no wall
    before = reason.copy()
    n, _, _ = _run(reason, depth, sigma)
    assert n == 0 and np.array_equal(reason, before)


def test_a_narrow_region_walled_by_stray_marks_only_keeps_its_points() -> None:
    reason, depth, sigma = _scene()
    reason[:, :95] = Reason.SHADOW
    reason[:, 105:] = Reason.SHADOW
    reason[::7, 94] = Reason.INTERREFLECTION  # single marks along the band's sides: each below the wall area
    reason[::7, 105] = Reason.INTERREFLECTION
    n, _, _ = _run(reason, depth, sigma)
    assert n == 0 and np.all(reason[:, 95:105] == Reason.DECODED)


def test_a_point_left_without_neighbours_is_dropped_as_filtered() -> None:
    # what the one-pass neighbour filter can leave: a point whose neighbours it dropped after they counted for it
    reason, depth, sigma = _scene()
    reason[40:60, 40:60] = Reason.FILTERED
    reason[50, 50] = 0  # alone in the filtered patch
    reason[40:60, 100:120] = Reason.FILTERED
    reason[50, 110] = reason[51, 111] = 0  # two diagonal neighbours: a surface, kept
    reason[0, 0] = 0
    reason[0, 1] = reason[1, 0] = reason[1, 1] = Reason.SHADOW  # alone in the image's corner
    depth[reason != 0] = np.nan
    sigma[reason != 0] = np.nan
    counts = np.concatenate([[0], (reason == 0).sum(axis=1)]).astype(np.int64)
    stats = np.zeros((H, 6), np.int64)
    stats[:, 4] = stats[:, 5] = counts[1:]
    kept = int(counts.sum())
    assert drop_isolated(depth, sigma, reason, counts, stats) == 2
    assert reason[50, 50] == Reason.FILTERED and reason[0, 0] == Reason.FILTERED
    assert np.isnan(depth[50, 50]) and np.isnan(sigma[0, 0])
    assert reason[50, 110] == 0 and reason[51, 111] == 0 and np.isfinite(depth[50, 110])
    assert int(counts.sum()) == kept - 2 and np.array_equal(counts[1:], (reason == 0).sum(axis=1))
    assert np.array_equal(stats[:, 4], counts[1:]) and np.array_equal(stats[:, 5], counts[1:])
    assert drop_isolated(depth, sigma, None, counts, stats) == 0  # one pass is final; no reason map is fine
