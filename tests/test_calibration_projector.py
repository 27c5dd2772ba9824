"""Projector calibration on the real procam captures, the local corner fit, and the calibrate commands."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import pytest

from appliance.calibration.boards import BoardSpec, Detection
from appliance.calibration.cli import board_from_args, calibrate_camera_cli, calibrate_projector_cli
from appliance.calibration.projector import (
    ProcamView,
    calibrate_procam,
    corner_projector_coords,
    procam_view,
    projector_detection,
)
from appliance.calibration.report import StereoEntry, report_paths, write_report
from appliance.geometry.calibration_file import read_calibration
from appliance.patterns import (
    BlackFrame,
    Sequence,
    WhiteFrame,
    gray_code_frames,
    read_manifest,
    write_manifest,
)

PROCAM = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam_graycode_calib"
SPEC = BoardSpec(type="chessboard", cols=9, rows=7, square_mm=75)


def procam_manifests(folder: Path) -> list[Path]:
    """One manifest per procam pose, pointing at the shared images (frame order of the README)."""
    seq = Sequence(1024, 768, gray_code_frames(1024, "x", bits=10) + gray_code_frames(768, "y", bits=10)
                   + (WhiteFrame(), BlackFrame()))  # fmt: skip
    out = []
    for pose in range(5):
        imgs = [
            os.path.relpath(PROCAM / f"capture_{pose}" / f"graycode_{i:02d}.png", folder) for i in range(42)
        ]
        out.append(write_manifest(folder / f"pose{pose}.yaml", seq, ["cam0"], images={"cam0": imgs}))
    return out


@pytest.fixture(scope="module")
def procam_views(tmp_path_factory: pytest.TempPathFactory) -> list[ProcamView]:
    if not PROCAM.is_dir():
        pytest.skip(f"test data {PROCAM} is absent")
    views = []
    for path in procam_manifests(tmp_path_factory.mktemp("procam")):
        man = read_manifest(path)
        views.append(procam_view(man.load_stack("cam0"), man.sequence, SPEC))
    return views


def test_procam_corner_projector_coordinates(procam_views: list[ProcamView]) -> None:
    for v in procam_views:
        assert v.camera is not None and v.projector is not None and v.fit is not None
        assert len(v.projector) >= 40
        # Gray-only decoding is quantised to whole projector pixels; the local fit averages it out
        assert np.nanmedian(v.fit.residual_rms) < 0.6
        assert np.all((v.projector.image_points >= 0) & (v.projector.image_points < [1024, 768]))


def test_procam_calibration_accuracy(procam_views: list[ProcamView], tmp_path: Path) -> None:
    res = calibrate_procam(procam_views, (1280, 1024), (1024, 768))
    K = res.camera.camera.K
    assert K[0, 0] == pytest.approx(3452.39, rel=0.005)
    assert K[1, 1] == pytest.approx(3449.92, rel=0.005)
    assert abs(K[0, 2] - 587.17) < 5 and abs(K[1, 2] - 521.45) < 5
    assert res.projector.rms <= 0.35
    assert res.stereo.rms <= 0.4
    P = res.projector.camera.K
    # physically plausible for a 1024x768 projector: throw ratio 1..3, square pixels, principal point
    # within the image horizontally, vertically at most a lens-shift away (projectors project upwards)
    assert 1024 < P[0, 0] < 3072 and P[1, 1] == pytest.approx(P[0, 0], rel=0.01)
    assert 0.25 * 1024 < P[0, 2] < 0.75 * 1024
    assert 0 < P[1, 2] < 1.5 * 768
    # the projector sits a few hundred mm from the camera, in front of the board (board at ~3 m)
    assert 200 < res.stereo.baseline_mm < 2000
    devices = res.devices()
    assert set(devices) == {"cam0", "projector"}
    np.testing.assert_allclose(devices["projector"].T, res.stereo.T)
    page = write_report(
        tmp_path / "calib.yaml", [res.camera, res.projector], [StereoEntry("cam0", "projector", res.stereo)]
    )
    html, folder = report_paths(tmp_path / "calib.yaml")
    assert page == html and "projector" in html.read_text() and "data:image/png;base64" in html.read_text()
    assert {p.name for p in folder.iterdir()} >= {
        "cam0_residuals.png",
        "projector_coverage.png",
        "stereo_cam0_projector_per_view.png",
    }


def test_corner_fit_recovers_a_homography_with_outliers() -> None:
    rng = np.random.default_rng(0)
    H = np.array([[0.8, 0.05, 100.0], [-0.03, 0.75, 60.0], [2e-5, -1e-5, 1.0]])
    ys, xs = np.mgrid[0:300, 0:400].astype(np.float64)
    den = H[2, 0] * xs + H[2, 1] * ys + 1
    u = ((H[0, 0] * xs + H[0, 1] * ys + H[0, 2]) / den).astype(np.float32)
    v = ((H[1, 0] * xs + H[1, 1] * ys + H[1, 2]) / den).astype(np.float32)
    u_q, v_q = np.round(u), np.round(v)  # Gray-only quantisation
    bad = rng.random(u.shape) < 0.15  # wrong Gray bits: far-off codes
    u_q[bad] += rng.choice([-256.0, 128.0, 64.0], bad.sum())
    u_q[rng.random(u.shape) < 0.1] = np.nan
    corners = np.array([[100.3, 80.7], [250.5, 150.2], [330.1, 240.9], [-4.0, 50.0]])
    fit = corner_projector_coords(u_q, v_q, corners, radius_px=20)
    c = corners[:3]
    d = H[2, 0] * c[:, 0] + H[2, 1] * c[:, 1] + 1
    truth = np.stack([(H[0, 0] * c[:, 0] + H[0, 1] * c[:, 1] + H[0, 2]) / d,
                      (H[1, 0] * c[:, 0] + H[1, 1] * c[:, 1] + H[1, 2]) / d], axis=1)  # fmt: skip
    np.testing.assert_allclose(fit.points[:3], truth, atol=0.05)
    assert not fit.valid[3]  # beyond the image edge: only the right half of the window exists
    det = Detection(np.arange(4, dtype=np.int32), corners, np.zeros((4, 3)), (400, 300))
    pdet = projector_detection(det, fit, (1024, 768))
    assert pdet is None  # 3 valid corners are not a view


@pytest.fixture()
def board() -> object:
    ns = argparse.Namespace(board="chessboard", cols=9, rows=7, square_mm=75.0, marker_mm=None,
                            dictionary="DICT_6X6_250")  # fmt: skip
    return board_from_args(ns)


def test_calibrate_camera_command(board: object, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not PROCAM.is_dir():
        pytest.skip(f"test data {PROCAM} is absent")
    out = tmp_path / "cam.yaml"
    images = [PROCAM / f"capture_{i}" / "graycode_40.png" for i in range(5)]
    assert calibrate_camera_cli(images, board, out, "standard") == 0  # type: ignore[arg-type]
    text = capsys.readouterr().out
    assert "RMS" in text and "per-view RMS" in text and "#4:" in text
    calib = read_calibration(out)
    assert list(calib.devices) == ["cam0"]
    cam = calib.devices["cam0"]
    assert cam.K[0, 0] == pytest.approx(3452.39, rel=0.005)
    assert 0 < cam.rms < 0.4
    assert report_paths(out)[0].is_file()


def test_calibrate_projector_command(
    board: object, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if not PROCAM.is_dir():
        pytest.skip(f"test data {PROCAM} is absent")
    out = tmp_path / "procam.yaml"
    manifests = procam_manifests(tmp_path)[:3]  # the accuracy test above uses all 5 poses; I/O here
    assert calibrate_projector_cli(manifests, board, out) == 0  # type: ignore[arg-type]
    text = capsys.readouterr().out
    assert "stereo cam0 -> projector: RMS" in text
    calib = read_calibration(out)
    assert set(calib.devices) == {"cam0", "projector"}
    proj = calib.devices["projector"]
    assert (proj.width, proj.height) == (1024, 768)
    assert proj.rms <= 0.35
    np.testing.assert_allclose(calib.devices["cam0"].T, 0.0)
    assert 200 < np.linalg.norm(proj.T) < 2000
    html, folder = report_paths(out)
    assert html.is_file() and (folder / "projector_residuals.png").is_file()
