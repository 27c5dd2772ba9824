"""Per-point uncertainty (issue 8 item 6): sigma_mm against ground truth, the sigma filter, PLY read-back.

Virtual-rig renders (read noise 1-4 DN plus shot noise) are decoded and reconstructed with the product;
each point's error against the true surface, divided by its predicted sigma, must be a unit-variance
quantity: RMS in 0.8-1.25 and fewer than 0.1 % of points beyond 5 sigma.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from plyfile import PlyData

from appliance.config.schema import ImagingConfig, ReconstructionConfig, VirtualRigConfig
from appliance.errors import CalibrationError
from appliance.output.ply import write_ply
from appliance.patterns.sequence import Sequence, gray_code_sequence, gray_phase_sequence
from appliance.reconstruct.decode import DecodeParams, decode
from appliance.reconstruct.fuse import fuse_depths
from appliance.reconstruct.geometry_defaults import depth_range_from_geometry
from appliance.reconstruct.pipeline import Reconstruction, Reconstructor, stage_warnings
from appliance.reconstruct.types import DecodedMaps, PointCloud, StageCounts
from appliance.reconstruct.uncertainty import CodeNoise, code_noise_for_sequence
from appliance.scan import virtual_calibration
from appliance.sim.rig import VirtualRig

F64 = npt.NDArray[np.float64]


@cache
def _render(
    read_noise_dn: float, kind: str = "phase"
) -> tuple[VirtualRig, Sequence, DecodedMaps, npt.NDArray[np.uint8]]:
    rig = VirtualRig(VirtualRigConfig(imaging=ImagingConfig(read_noise_dn=read_noise_dn, seed=11)))
    w, h = rig.projector.width, rig.projector.height
    seq = gray_phase_sequence(w, h, "x", period=16, steps=4) if kind == "phase" else gray_code_sequence(w, h, "x")
    frames = rig.render(seq, "cam0")
    maps = decode(frames, seq, DecodeParams())
    return rig, seq, maps, frames[0]  # frame 0 is the white frame


def _reconstruct(read_noise_dn: float, kind: str = "phase", **cfg: object) -> tuple[PointCloud, F64, Reconstruction]:
    rig, seq, maps, white = _render(read_noise_dn, kind)
    rc = ReconstructionConfig(min_depth_mm=300, max_depth_mm=900, camera_read_noise_dn=read_noise_dn, **cfg)  # type: ignore[arg-type]
    rec = Reconstructor(virtual_calibration(rig), "x", rc, sequence=seq).run({"cam0": maps}, {"cam0": white})
    cloud = rec.cloud
    truth = rig.ground_truth("cam0").xyz[cloud.row, cloud.col]
    assert np.isfinite(truth).all()  # no point off the objects
    err = np.linalg.norm(cloud.xyz.astype(np.float64) - truth, axis=1)
    return cloud, err, rec


@pytest.mark.parametrize("read_noise_dn", [1.0, 2.0, 3.0, 4.0])
def test_sigma_is_calibrated_against_ground_truth(read_noise_dn: float) -> None:
    cloud, err, rec = _reconstruct(read_noise_dn)
    assert cloud.sigma_mm is not None and cloud.sigma_mm.dtype == np.float32
    sigma = cloud.sigma_mm.astype(np.float64)
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    z = err / sigma
    rms = float(np.sqrt(np.mean(z**2)))
    beyond5 = float(np.mean(z > 5.0))
    print(f"read noise {read_noise_dn} DN: {len(z)} points, error RMS {np.sqrt(np.mean(err**2)):.4f} mm, "
          f"median sigma {np.median(sigma):.4f} mm, RMS(error/sigma) {rms:.3f}, beyond 5 sigma {beyond5:.5%}")
    assert len(z) > 1_000_000
    assert 0.8 <= rms <= 1.25
    assert beyond5 < 1e-3
    # sigma follows the noise: it grows with the read noise (shot noise keeps it from being proportional)
    st = rec.stages[0]
    assert st.kept == len(cloud) and st.decoded > st.kept and sum(st.rejected().values()) == st.pixels - st.kept


def test_sigma_grows_with_read_noise() -> None:
    lo, _, _ = _reconstruct(1.0)
    hi, _, _ = _reconstruct(4.0)
    assert lo.sigma_mm is not None and hi.sigma_mm is not None
    ratio = float(np.median(hi.sigma_mm) / np.median(lo.sigma_mm))
    # sigma_I: sqrt(1 + shot + 1/12) -> sqrt(16 + shot + 1/12) with shot ~ 4 DN^2 at this brightness
    assert 1.6 < ratio < 2.6


def test_max_sigma_filter_drops_the_uncertain_points() -> None:
    cloud, err, _ = _reconstruct(4.0)
    assert cloud.sigma_mm is not None
    limit = float(np.percentile(cloud.sigma_mm, 70))
    kept, kerr, rec = _reconstruct(4.0, max_sigma_mm=limit)
    assert kept.sigma_mm is not None and np.all(kept.sigma_mm <= limit)
    assert 0.5 * len(cloud) < len(kept) < 0.8 * len(cloud)
    assert np.sqrt(np.mean(kerr**2)) < np.sqrt(np.mean(err**2))
    st = rec.stages[0]
    assert st.rejected()["sigma"] > 0.2 * len(cloud)
    # a tight limit rejects most points and says so in words, naming the setting
    _, _, tight = _reconstruct(4.0, max_sigma_mm=float(np.percentile(cloud.sigma_mm, 10)))
    assert any("max_sigma_mm" in w and "expected error" in w for w in tight.warnings)


def test_gray_only_sigma_is_the_stripe_quantisation() -> None:
    cloud, err, _ = _reconstruct(2.0, kind="gray")
    assert cloud.sigma_mm is not None
    z = err / cloud.sigma_mm
    # stripe centres: the error is uniform over a stripe (plus edge pixels one stripe off)
    assert 0.7 < float(np.sqrt(np.mean(z**2))) < 1.5


def test_sigma_mm_read_back_with_plyfile(tmp_path: Path) -> None:
    cloud, _, _ = _reconstruct(2.0)
    path = write_ply(tmp_path / "s.ply", cloud)
    v = PlyData.read(str(path))["vertex"]
    assert "sigma_mm" in [p.name for p in v.properties]
    np.testing.assert_array_equal(np.asarray(v["sigma_mm"]), cloud.sigma_mm)
    assert np.asarray(v["sigma_mm"]).dtype == np.float32
    # a cloud without sigma still writes the property on every point, as NaN
    bare = PointCloud(cloud.xyz[:5], cloud.row[:5], cloud.col[:5], cloud.camera[:5], cloud.intensity[:5],
                      cloud.quality[:5])  # fmt: skip
    v = PlyData.read(str(write_ply(tmp_path / "b.ply", bare)))["vertex"]
    assert np.isnan(np.asarray(v["sigma_mm"])).all() and len(v["sigma_mm"]) == 5


# open3d loads its own (older) TBB; numba then says it keeps its other threading layer
@pytest.mark.filterwarnings("ignore:The TBB threading layer requires TBB")
def test_sigma_mm_read_back_with_open3d(tmp_path: Path) -> None:
    import open3d as o3d  # a second reader, independent of plyfile

    cloud, _, _ = _reconstruct(2.0)
    assert cloud.sigma_mm is not None
    pcd = o3d.t.io.read_point_cloud(str(write_ply(tmp_path / "o.ply", cloud)))
    np.testing.assert_array_equal(pcd.point["positions"].numpy(), cloud.xyz)
    sigma = pcd.point["sigma_mm"].numpy().ravel()
    assert sigma.dtype == np.float32
    np.testing.assert_array_equal(sigma, cloud.sigma_mm)


def test_code_noise_model() -> None:
    seq = gray_phase_sequence(1280, 800, "x", period=16, steps=4)
    noise = code_noise_for_sequence(seq, "x", read_noise_dn=2.0, electrons_per_dn=25.0)
    assert noise.phase_px == pytest.approx(16 * np.sqrt(0.5) / np.pi)
    # sigma_u = P sqrt(2/N) sigma_I / (pi q), sigma_I^2 = 4 + A/25 + 1/12
    q = np.array([100.0])
    expected = 16 * np.sqrt(2 / 4) * np.sqrt(4 + 50 / 25 + 1 / 12) / (np.pi * 100)
    assert noise.sigma_px(q)[0] == pytest.approx(expected)
    gray = code_noise_for_sequence(gray_code_sequence(1280, 800, "x", stripe=4), "x")
    assert gray.phase_px == 0 and gray.sigma_px(q)[0] == pytest.approx(4 / np.sqrt(12))
    with pytest.raises(ValueError, match="codes nothing on axis 'y'"):
        code_noise_for_sequence(seq, "y")
    with pytest.raises(ValueError, match="one must be > 0"):
        CodeNoise(0.0, 0.0)


def test_stage_warnings_in_plain_words() -> None:
    cfg = ReconstructionConfig(min_depth_mm=300, max_depth_mm=900)
    ok = StageCounts("cam0", 1000, 900, 890, 880, 870, 870)
    assert stage_warnings([ok], cfg) == []
    bad = StageCounts("cam0", 1000, 900, 890, 100, 95, 95)
    (msg,) = stage_warnings([bad], cfg)
    assert msg.startswith("89 % of camera cam0's points lie outside reconstruction.min_depth_mm .. max_depth_mm")
    assert "300 .. 900 mm" in msg
    assert bad.rejected() == {"decode": 100, "geometry": 10, "epipolar": 0, "depth_range": 790, "neighbours": 5,
                              "sigma": 0}  # fmt: skip
    # an object on a dark background: 70 % of the image decodes nothing, which is no fault; 95 % is
    dark = StageCounts("cam0", 1000, 300, 295, 290, 285, 285)
    assert stage_warnings([dark], cfg) == []
    (msg,) = stage_warnings([StageCounts("cam0", 1000, 50, 49, 48, 47, 47)], cfg)
    assert msg.startswith("95 % of camera cam0's pixels decoded no code") and "exposure" in msg


def test_fusion_weights_by_sigma_and_flags_disagreement() -> None:
    rng = np.random.default_rng(5)
    h, w = 200, 300
    truth = 600.0 + np.linspace(0.0, 50.0, w)[None, :] + np.zeros((h, 1))
    s1 = np.full((h, w), 0.1, np.float32)
    s2 = np.where(np.arange(w)[None, :] < w // 2, 0.1, 0.3).astype(np.float32) + np.zeros((h, 1), np.float32)
    z1 = (truth + rng.normal(0.0, 1.0, (h, w)) * s1).astype(np.float32)
    z2 = (truth + rng.normal(0.0, 1.0, (h, w)) * s2).astype(np.float32)
    z1[:10] = np.nan  # only the second there
    z2[-10:] = np.nan  # only the first there
    z2[50:60, 100:110] += 5.0  # a wrong match in the second estimate
    f = fuse_depths(z1, s1, z2, s2)
    both = f.source == 3
    err = (f.depth - truth)[both] / f.sigma[both]
    assert 0.95 < float(np.sqrt(np.mean(err**2))) < 1.05  # the fused sigma is the fused error
    np.testing.assert_allclose(f.sigma[both & (s2 == np.float32(0.1))], 0.1 / np.sqrt(2), rtol=1e-5)
    assert f.disagree[50:60, 100:110].all() and np.isnan(f.depth[50:60, 100:110]).all()
    assert f.counts()["disagree"] < 100 + 0.01 * h * w  # 3 sigma: ~0.3 % of honest pixels are flagged too
    assert (f.source[:10] == 2).all() and (f.source[-10:] == 1).all()
    kept = fuse_depths(z1, s1, z2, s2, keep_disagreeing=True)
    np.testing.assert_array_equal(kept.depth[50:60, 100:110], z1[50:60, 100:110])
    with pytest.raises(ValueError, match="must all be the same"):
        fuse_depths(z1, s1, z2[:5], s2)


def test_depth_range_from_geometry_covers_the_virtual_scene() -> None:
    rig, _, _, _ = _render(2.0)
    calib = virtual_calibration(rig)
    zmin, zmax = depth_range_from_geometry(calib)
    depth = rig.ground_truth("cam0").depth
    seen = depth[rig.ground_truth("cam0").lit]
    assert zmin < float(seen.min()) and float(seen.max()) < zmax
    assert 0.0 < zmin < 600.0 < zmax < 20_000.0
    with pytest.raises(CalibrationError, match="needs two cameras"):
        depth_range_from_geometry(calib, "stereo")
