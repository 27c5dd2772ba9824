"""Camera intrinsics: procam photos against the published values; synthetic views with ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from procam_helpers import PROCAM, procam_white_detections

from appliance.calibration.boards import BoardSpec, Detection
from appliance.calibration.intrinsics import calibrate_camera, coverage_map, model_flags
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

SPEC = BoardSpec(type="chessboard", cols=9, rows=7, square_mm=75)


def test_procam_camera_matches_published_intrinsics() -> None:
    if not PROCAM.is_dir():
        pytest.skip(f"test data {PROCAM} is absent")
    res = calibrate_camera(procam_white_detections(), (1280, 1024), "k3p")
    K = res.camera.K
    assert K[0, 0] == pytest.approx(3452.39, rel=0.005)
    assert K[1, 1] == pytest.approx(3449.92, rel=0.005)
    assert abs(K[0, 2] - 587.17) < 5.0
    assert abs(K[1, 2] - 521.45) < 5.0
    assert res.rms < 0.4
    assert len(res.views) == 5 and res.per_view_errors.shape == (5,)
    # per-view errors combine into the overall RMS (63 points per view)
    assert np.sqrt(np.mean(res.per_view_errors**2)) == pytest.approx(res.rms, rel=1e-6)
    assert set(res.std_devs) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert 0 < res.std_devs["fx"] < 50
    assert any("only 5 views" in w for w in res.warnings)
    assert any("cover only" in w for w in res.warnings)


def _synthetic_views(
    cam: CameraModel, spec: BoardSpec, n: int, rng: np.random.Generator, spread: float = 1.0
) -> list[Detection | None]:
    obj = spec.object_points()
    centre = obj.mean(axis=0)
    out: list[Detection | None] = []
    for _ in range(n):
        rvec = rng.normal(0, 0.35, 3)
        target = np.array([rng.uniform(-150, 150) * spread, rng.uniform(-110, 110) * spread, 0.0])
        R, _ = cv2.Rodrigues(rvec)
        tvec = np.array([0.0, 0.0, 700.0]) + target - R @ centre
        px, _ = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist)
        px = px.reshape(-1, 2) + rng.normal(0, 0.05, (len(obj), 2))
        inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        ids = np.flatnonzero(inside).astype(np.int32)
        out.append(Detection(ids, px[ids], obj[ids], cam.size))
    return out


TRUE_CAM = CameraModel("cam0", [[1500.0, 0, 650.0], [0, 1502.0, 500.0], [0, 0, 1]],
                       [-0.12, 0.09, 0.0006, -0.0004, 0.0], 1280, 1024)  # fmt: skip
GRID = BoardSpec(type="chessboard", cols=11, rows=8, square_mm=20)


def test_synthetic_ground_truth_and_outlier_view_rejected() -> None:
    rng = np.random.default_rng(3)
    dets = _synthetic_views(TRUE_CAM, GRID, 14, rng)
    bad = dets[5]
    assert bad is not None
    # a mis-ordered detection (unreliable) must be rejected, not averaged in
    shuffled = bad.image_points.copy()
    shuffled[:10] = shuffled[:10][::-1]
    dets[5] = Detection(bad.ids, shuffled, bad.object_points, bad.image_size)
    dets.append(None)
    res = calibrate_camera(dets, TRUE_CAM.size, "k3p")
    assert 5 in res.rejected and len(dets) - 1 in res.rejected
    assert "not found" in res.rejected[len(dets) - 1]
    np.testing.assert_allclose(res.camera.K, TRUE_CAM.K, atol=1.5)
    assert res.rms == pytest.approx(0.05 * np.sqrt(2), rel=0.25)
    assert res.camera.dist.shape == (5,)
    assert not any("views used" in w for w in res.warnings)
    # residuals are observation minus reprojection of the recovered model
    assert np.sqrt(np.mean(np.concatenate(res.residuals) ** 2) * 2) == pytest.approx(res.rms, rel=1e-3)


def test_models_and_coverage_warning() -> None:
    rng = np.random.default_rng(5)
    dets = _synthetic_views(TRUE_CAM, GRID, 12, rng, spread=0.0)  # all views in the image centre
    res = calibrate_camera(dets, TRUE_CAM.size, "k2")
    assert res.camera.dist[2:].tolist() == [0.0, 0.0, 0.0]
    assert set(res.std_devs) == {"fx", "fy", "cx", "cy", "k1", "k2"}
    assert res.coverage_fraction < 0.6
    assert any("cover only" in w for w in res.warnings)
    rational = calibrate_camera(dets, TRUE_CAM.size, "rational")
    assert rational.camera.dist.shape == (8,)
    with pytest.raises(CalibrationError, match="distortion model"):
        model_flags("k4")


def test_too_few_views_is_an_error() -> None:
    rng = np.random.default_rng(1)
    dets = _synthetic_views(TRUE_CAM, GRID, 2, rng)
    with pytest.raises(CalibrationError, match="usable views"):
        calibrate_camera([*dets, None], TRUE_CAM.size)


def test_coverage_map_counts_views() -> None:
    square = np.array([[0.0, 0.0], [639.0, 0.0], [639.0, 479.0], [0.0, 479.0]])
    cov = coverage_map([square, square[:, :] * 0.5], (1280, 960))
    assert cov.shape == (60, 80)
    assert cov[5, 5] == 2 and cov[20, 30] == 1 and cov[50, 70] == 0
