"""One set of defaults from 0.3 m to 4 m (issue 8 item 2): the neighbour filter's jump limit per point.

The same rig (190 mm baseline) scans a plane and a sphere at 0.3 m and at 4 m, where the depth noise differs
by (4 / 0.3)^2 ~ 180x. With the default per-point limits (``neighbour_jump_sigmas`` times the point's
sigma plus ``neighbour_jump_footprints`` pixel footprints) both keep >= 98 % of the lit pixels and their
sigma stays calibrated; a fixed 2 mm limit loses most of the far scan and says so.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from appliance.config.schema import (
    DeviceOptics,
    ImagingConfig,
    PlaneObject,
    ReconstructionConfig,
    SphereObject,
    VirtualRigConfig,
)
from appliance.patterns.sequence import Sequence, gray_phase_sequence
from appliance.reconstruct.decode import DecodeParams, decode
from appliance.reconstruct.pipeline import Reconstruction, Reconstructor
from appliance.reconstruct.types import DecodedMaps, PointCloud
from appliance.scan import virtual_calibration
from appliance.sim.accuracy import AccuracyReport, compare_to_ground_truth
from appliance.sim.rig import VirtualRig


@cache
def _scan(z0: float) -> tuple[VirtualRig, Sequence, DecodedMaps, np.ndarray]:  # type: ignore[type-arg]
    s = z0 / 600.0
    cam = DeviceOptics(width=1280, height=1024, focal_px=2400.0, dist=(-0.08, 0.12, 5e-4, -3e-4, 0.0),
                       look_at_mm=(0.0, 0.0, z0))  # fmt: skip
    proj = DeviceOptics(width=1280, height=800, focal_px=1750.0, dist=(0.02, -0.01, 0.0, 0.0, 0.0),
                        position_mm=(190.0, 0.0, 0.0), look_at_mm=(0.0, 0.0, z0))  # fmt: skip
    scene = (
        PlaneObject(point_mm=(0.0, 0.0, 1.05 * z0), normal=(0.0, 0.1, -1.0), texture=0.3),
        SphereObject(center_mm=(-20.0 * s, 10.0 * s, 0.93 * z0), radius_mm=40.0 * s, texture=0.2),
    )
    rig = VirtualRig(VirtualRigConfig(cameras={"cam0": cam}, projector=proj, scene=scene,
                                      imaging=ImagingConfig(seed=5)))  # fmt: skip
    seq = gray_phase_sequence(1280, 800, "x", period=16, steps=4)
    frames = rig.render(seq, "cam0")
    return rig, seq, decode(frames, seq, DecodeParams()), frames[0]


def _reconstruct(z0: float, jump_mm: float | None) -> tuple[PointCloud, AccuracyReport, Reconstruction]:
    rig, seq, maps, white = _scan(z0)
    cfg = ReconstructionConfig(min_depth_mm=0.5 * z0, max_depth_mm=2.0 * z0, max_neighbour_jump_mm=jump_mm)
    rec = Reconstructor(virtual_calibration(rig), "x", cfg, sequence=seq).run({"cam0": maps}, {"cam0": white})
    cloud = rec.cloud
    return cloud, compare_to_ground_truth(cloud, rig, ["cam0"]), rec


@pytest.mark.parametrize("z0", [300.0, 4000.0])
def test_default_jump_limits_hold_near_and_far(z0: float) -> None:
    cloud, rep, rec = _reconstruct(z0, None)
    print(f"{z0:.0f} mm: {rep.line()}")
    assert rep.completeness >= 0.98
    assert not rec.warnings
    rig = _scan(z0)[0]
    err = np.linalg.norm(cloud.xyz - rig.ground_truth("cam0").xyz[cloud.row, cloud.col], axis=1)
    assert cloud.sigma_mm is not None
    ratio = float(np.sqrt(np.mean((err / cloud.sigma_mm) ** 2)))
    assert 0.8 <= ratio <= 1.25
    assert float(np.mean(err > 5 * cloud.sigma_mm)) < 1e-3
    # the error scales with z^2 / (f b): ~180x from 0.3 m to 4 m; sigma follows
    assert np.median(cloud.sigma_mm) == pytest.approx(np.median(err) / 0.6745, rel=0.3)


def test_a_fixed_jump_limit_fails_far_away_and_says_so() -> None:
    _, rep, rec = _reconstruct(4000.0, 2.0)
    assert rep.completeness < 0.5
    assert any("fixed max_neighbour_jump_mm = 2 mm" in w and "unset it" in w for w in rec.warnings)
    assert rec.stages[0].rejected()["neighbours"] > 0.5 * rec.stages[0].in_range
