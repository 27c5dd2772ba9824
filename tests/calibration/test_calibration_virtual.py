"""Calibration on the virtual rig against its ground truth: live capture, joint refinement, verification.

The rig is the default configuration (camera 1280x1024 with distortion, projector 1280x800 with
distortion, 190 mm baseline); the board is moved through preset poses by the live command, which also keeps
each pose's white frame; ``scan3d calibrate camera`` then runs on those 15 frames.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.calibration.boards import BoardSpec
from appliance.calibration.bundle import Observation, bundle_adjust
from appliance.calibration.report import report_paths
from appliance.calibration.verify import evaluate_artefact
from appliance.calibration.virtual import preset_board_poses
from appliance.cli import main
from appliance.config.schema import AppConfig, ArtefactConfig, ArtefactPosition, VerifyTolerances
from appliance.geometry.calibration_file import read_calibration
from appliance.geometry.camera import CameraModel, look_at
from appliance.procedures.live_calibration import calibrate_live
from appliance.procedures.verify import verify_rig
from appliance.sim.rig import device_model

TRUTH = AppConfig().virtual_rig
CAM = device_model("cam0", TRUTH.cameras["cam0"])
PROJ = device_model("projector", TRUTH.projector)


@pytest.fixture(scope="module")
def calibration_15(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    folder = tmp_path_factory.mktemp("live15")
    out = folder / "calibration.yaml"
    config = folder / "appliance.yaml"
    config.write_text("serial: SIM-CAL\n")  # the virtual-rig defaults
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["calibrate", "--live", "--poses", "15", "--config", str(config), "--out", str(out),
                   "--save-frames", str(folder / "frames")])  # fmt: skip
    assert rc == 0, buf.getvalue()
    return out, buf.getvalue()


@pytest.mark.slow
def test_fifteen_pose_calibration_matches_ground_truth(calibration_15: tuple[Path, str]) -> None:
    out, text = calibration_15
    calib = read_calibration(out)
    assert list(calib.devices) == ["cam0", "projector"]
    for got, truth in ((calib.devices["cam0"], CAM), (calib.devices["projector"], PROJ)):
        np.testing.assert_allclose(got.K[0, 0], truth.K[0, 0], rtol=0.002)
        np.testing.assert_allclose(got.K[1, 1], truth.K[1, 1], rtol=0.002)
        assert abs(got.K[0, 2] - truth.K[0, 2]) < 1.0, (got.name, got.K[0, 2], truth.K[0, 2])
        assert abs(got.K[1, 2] - truth.K[1, 2]) < 1.0, (got.name, got.K[1, 2], truth.K[1, 2])
        assert got.rms < 0.2
    # baseline: distance between the optical centres (world = cam0)
    baseline = np.linalg.norm(calib.devices["projector"].center - calib.devices["cam0"].center)
    assert abs(baseline - np.linalg.norm(PROJ.center - CAM.center)) < 0.1
    np.testing.assert_allclose(calib.devices["cam0"].T, 0.0, atol=1e-12)
    assert "pose 15: cam0" in text and "coverage: cam0" in text and "joint refinement" in text
    assert "cam0: distortion model" in text and "projector: distortion model" in text and "held-out" in text
    html, folder = report_paths(out)
    assert html.is_file() and (folder / "projector_residuals.png").is_file()


@pytest.mark.slow
def test_camera_command_on_fifteen_virtual_board_frames(calibration_15: tuple[Path, str]) -> None:
    """``scan3d calibrate camera`` on the 15 white frames the live calibration kept, against the truth."""
    frames = sorted((calibration_15[0].parent / "frames").glob("pose_*_cam0.png"))
    assert len(frames) == 15
    out = calibration_15[0].parent / "camera.yaml"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["calibrate", "camera", *map(str, frames), "--board", "chessboard", "--cols", "15",
                   "--rows", "11", "--square-mm", "15", "--out", str(out)])  # fmt: skip
    assert rc == 0, buf.getvalue()
    got = read_calibration(out).devices["cam0"]
    assert abs(got.K[0, 0] / CAM.K[0, 0] - 1) <= 0.001 and abs(got.K[1, 1] / CAM.K[1, 1] - 1) <= 0.001
    assert abs(got.K[0, 2] - CAM.K[0, 2]) <= 0.5 and abs(got.K[1, 2] - CAM.K[1, 2]) <= 0.5
    assert re.search(r"cam0: distortion model \w+ \(selected\)", buf.getvalue())


@pytest.mark.slow
def test_scan_with_recovered_calibration_measures_sphere_and_plane(
    calibration_15: tuple[Path, str],
) -> None:
    cfg = AppConfig(calibration_file=calibration_15[0])
    art = cfg.calibration.artefact.model_copy(update={"positions": (ArtefactPosition(),)})
    cfg = cfg.model_copy(update={"calibration": cfg.calibration.model_copy(update={"artefact": art})})
    report = asyncio.run(verify_rig(cfg)).reports[0]
    assert len(report.spheres) == 2 and report.plane is not None
    for s in report.spheres:
        assert abs(s["error_mm"]) <= 0.05, report.lines()
    assert report.plane["flatness_mm"] <= 0.1, report.lines()
    assert report.ball_bar is not None and abs(report.ball_bar["error_mm"]) <= 0.1
    assert report.passed


def test_live_calibration_interactive_on_virtual_rig(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "live.yaml"
    # three Enter presses capture three poses, 'c' calibrates
    assert asyncio.run(calibrate_live(None, out=out, stdin=io.StringIO("\n\n\nc\n"))) == 0
    text = capsys.readouterr().out
    assert text.count("board points") == 3 and "pose 3: cam0" in text
    # after each pose it says where the board is still missing, and the result says what to add
    assert "next pose: put the board into the" in text
    assert "the calibration is weak:" in text and "only 3 views (want >= 10)" in text
    calib = read_calibration(out)
    assert set(calib.devices) == {"cam0", "projector"}
    # three poses constrain the focal length to well under 1 %
    np.testing.assert_allclose(calib.devices["cam0"].K[0, 0], CAM.K[0, 0], rtol=0.01)
    assert report_paths(out)[0].is_file()


def test_live_calibration_quit_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "none.yaml"
    assert asyncio.run(calibrate_live(None, out=out, stdin=io.StringIO("q\n"))) == 1
    assert not out.exists()


def test_evaluate_artefact_on_exact_points() -> None:
    art = ArtefactConfig()
    rng = np.random.default_rng(3)
    pts = []
    for s in art.spheres:
        d = rng.normal(size=(4000, 3))
        d[:, 2] = -np.abs(d[:, 2])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts.append(np.asarray(s.center_mm) + (s.diameter_mm / 2 + 0.02) * d)  # 0.04 mm too large
    assert art.plane is not None
    n = np.asarray(art.plane.normal) / np.linalg.norm(art.plane.normal)
    a = np.cross(n, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    uv = rng.uniform(-90, 90, (20000, 2))
    bump = 0.08 * np.exp(-((uv[:, 0] - 40) ** 2 + uv[:, 1] ** 2) / (2 * 15.0**2))  # 0.08 mm dent
    pts.append(np.asarray(art.plane.point_mm) + uv[:, :1] * a + uv[:, 1:] * b + bump[:, None] * n)
    pts.append(np.array([[0.0, 0.0, 400.0]]))  # a stray point far from everything
    rep = evaluate_artefact(np.concatenate(pts), art, VerifyTolerances())
    for s in rep.spheres:
        assert s["error_mm"] == pytest.approx(0.04, abs=1e-6)
        assert s["form_mm"] == pytest.approx(0.0, abs=1e-6)  # exact sphere: no form error
    assert rep.ball_bar is not None and rep.ball_bar["error_mm"] == pytest.approx(0.0, abs=1e-6)
    assert rep.plane is not None and rep.plane["flatness_mm"] == pytest.approx(0.08, abs=0.01)
    assert rep.passed
    strict = evaluate_artefact(np.concatenate(pts), art, VerifyTolerances(sphere_diameter_mm=0.03))
    assert not strict.passed


def test_bundle_adjustment_recovers_rig_from_synthetic_views() -> None:
    """Joint refinement from perturbed starting values, two cameras and a projector, exact data."""
    board = BoardSpec(type="chessboard", cols=15, rows=11, square_mm=15)
    R1, T1 = look_at(np.array([-120.0, 10.0, 0.0]), np.array([0.0, 0.0, 600.0]))
    cam1 = CameraModel("cam1", CAM.K.copy(), CAM.dist.copy(), CAM.width, CAM.height, R1, T1)
    devices = {"cam0": CAM, "cam1": cam1, "projector": PROJ}
    poses = preset_board_poses(board, 12, CAM, np.array([0.0, 0.0, 600.0]), list(devices.values()))
    obs = []
    init_poses = {}
    rng = np.random.default_rng(5)
    for v, pose in enumerate(poses):
        world = pose.world_points(board)
        for name, dev in devices.items():
            obs.append(Observation(name, v, board.object_points(), dev.project(world)[0]))
        r, _ = cv2.Rodrigues(pose.R)
        init_poses[v] = (r.ravel() + rng.normal(0, 0.01, 3), pose.t + rng.normal(0, 2.0, 3))
    start = {}
    for name, dev in devices.items():
        K = dev.K.copy()
        K[0, 0] *= 1.01
        K[1, 1] *= 0.99
        K[0, 2] += 5
        T = dev.T + (rng.normal(0, 3.0, 3) if name != "cam0" else 0.0)
        start[name] = CameraModel(name, K, np.zeros(5), dev.width, dev.height, dev.R, T)
    res = bundle_adjust(start, {"cam0": "k3p", "cam1": "k3p", "projector": "k2p"}, obs, init_poses)
    assert res.rms < 1e-6
    for name, dev in devices.items():
        np.testing.assert_allclose(res.devices[name].K, dev.K, atol=1e-5)
        np.testing.assert_allclose(res.devices[name].T, dev.T, atol=1e-6)
        np.testing.assert_allclose(res.devices[name].R, dev.R, atol=1e-9)
        np.testing.assert_allclose(res.devices[name].dist[:5], dev.dist_padded(5), atol=1e-8)
    assert set(res.std_devs["cam1"]) >= {"fx", "cx", "k1", "p1", "tx", "rz"}
