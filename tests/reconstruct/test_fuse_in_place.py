"""fuse_points_into (mode ``both``'s in-place fusion) against fuse_depths, the reference, on random maps."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.geometry.camera import look_at
from appliance.reconstruct.fuse import fuse_depths, fuse_points_into
from appliance.reconstruct.types import Reason


@pytest.mark.parametrize("keep", [False, True])
def test_in_place_fusion_equals_fuse_depths(keep: bool) -> None:
    rng = np.random.default_rng(3)
    h, w = 40, 50
    r, t = look_at(np.array([-30.0, 10.0, 5.0]), np.array([0.0, 0.0, 600.0]))
    z1 = rng.uniform(550, 650, (h, w)).astype(np.float32)
    s1 = rng.uniform(0.02, 0.2, (h, w)).astype(np.float32)
    z2 = (z1 + rng.normal(0, 0.3, (h, w))).astype(np.float32)
    s2 = rng.uniform(0.02, 0.2, (h, w)).astype(np.float32)
    z1[rng.random((h, w)) < 0.2] = np.nan  # only the second, only the first, neither
    z2[rng.random((h, w)) < 0.2] = np.nan
    s2[rng.random((h, w)) < 0.05] = 0.0  # no estimate
    # the second estimate as world points on the camera's rays (pixel rays need not be real: any direction)
    d = np.stack([rng.uniform(-0.3, 0.3, (h, w)), rng.uniform(-0.3, 0.3, (h, w)), np.ones((h, w))], -1)
    p_cam = d * z2.astype(np.float64)[..., None]
    xyz = np.ascontiguousarray(((p_cam - t) @ r), np.float32)  # x_cam = R x_world + T

    ref = fuse_depths(z1, s1, (xyz.astype(np.float64) @ r[2] + t[2]).astype(np.float32), s2,
                      keep_disagreeing=keep)  # fmt: skip
    depth, sigma = z1.copy(), s1.copy()
    counts = np.full(h + 1, -1, np.int64)
    reason = np.where(np.isfinite(z1), Reason.DECODED, Reason.SHADOW).astype(np.uint8)
    got = fuse_points_into(depth, sigma, xyz, s2, r[2], float(t[2]), counts, reason,
                           (Reason.DECODED, Reason.FILTERED), keep_disagreeing=keep)  # fmt: skip

    assert got == ref.counts() and got["fused"] > 0 and got["disagree"] > 0 and got["second"] > 0
    np.testing.assert_allclose(depth, ref.depth, rtol=0, atol=1e-3, equal_nan=True)  # mm
    np.testing.assert_allclose(sigma, ref.sigma, rtol=1e-5, atol=1e-6, equal_nan=True)
    has = np.isfinite(depth)
    assert counts[0] == 0 and np.array_equal(counts[1:], has.sum(axis=1))
    assert (reason[has] == Reason.DECODED).all()
    lost = np.isfinite(z1) & ~has  # decoded, dropped for disagreeing
    assert lost.any() != keep and (reason[lost] == Reason.FILTERED).all()
    assert (reason[~np.isfinite(z1) & ~has] == Reason.SHADOW).all()


def test_in_place_fusion_refuses_a_wrong_buffer() -> None:
    z = np.zeros((4, 5), np.float32)
    with pytest.raises(ValueError, match="xyz is"):
        fuse_points_into(z, z.copy(), np.zeros((4, 5, 2), np.float32), z.copy(), np.array([0, 0, 1.0]), 0.0,
                         np.zeros(5, np.int64))  # fmt: skip
