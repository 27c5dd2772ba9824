"""Calibration file I/O and per-pixel ray tables."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import Calibration, read_calibration, write_calibration
from appliance.geometry.camera import CameraModel, look_at
from appliance.geometry.rays import RayTable


def _calibration() -> Calibration:
    cam0 = CameraModel(
        "cam0",
        [[1800.5, 0.25, 640.3], [0, 1799.7, 511.9], [0, 0, 1]],
        [-0.12, 0.09, 4e-4, -3e-4, -0.02],
        1280,
        1024,
        rms=0.083,
    )
    r1, t1 = look_at(np.array([200.0, 5.0, 3.0]), np.array([30.0, 0.0, 575.0]))
    cam1 = CameraModel(
        "cam1",
        [[1750, 0, 630], [0, 1752, 515], [0, 0, 1]],
        [-0.1, 0.07, -2e-4, 3e-4, -0.01, 0.001, 0.002, 0.003],
        1280,
        1024,
        r1,
        t1,
        rms=0.1 / 3,
    )
    rp, tp = look_at(np.array([100.0, -30.0, 0.0]), np.array([0.0, 0.0, 575.0]))
    proj = CameraModel(
        "projector",
        [[1600, 0, 640.4], [0, 1600, 780.2], [0, 0, 1]],
        [0.08, -0.05, -6e-4, 5e-4],
        1280,
        800,
        rp,
        tp,
    )  # rms unknown: NaN
    return Calibration({"cam0": cam0, "projector": proj, "cam1": cam1})


def _same(a: CameraModel, b: CameraModel) -> None:
    assert a.name == b.name and a.size == b.size
    for x, y in ((a.K, b.K), (a.dist, b.dist), (a.R, b.R), (a.T, b.T)):
        np.testing.assert_array_equal(x, y)  # %.17g round trip is exact
    assert (np.isnan(a.rms) and np.isnan(b.rms)) or a.rms == b.rms


def test_calibration_round_trip(tmp_path: Path) -> None:
    calib = _calibration()
    path = tmp_path / "calibration.yaml"
    write_calibration(path, calib)
    assert path.read_text().splitlines()[0] == "%YAML:1.0"
    back = read_calibration(path)
    assert list(back.devices) == ["cam0", "projector", "cam1"]
    for name in calib.devices:
        _same(calib.devices[name], back.devices[name])
    assert back.camera_names == ["cam0", "cam1"]
    assert back.projector is not None and back.projector.name == "projector"
    assert back.hash() == calib.hash() and len(calib.hash()) == 16
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yaml"]  # no temporary left
    write_calibration(path, back)  # overwrite in place
    assert read_calibration(path).hash() == calib.hash()


def test_calibration_loads_with_cv2_filestorage(tmp_path: Path) -> None:
    calib = _calibration()
    path = tmp_path / "calib.yaml"
    write_calibration(path, calib)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    for name, dev in calib.devices.items():
        node = fs.getNode(name)
        assert node.isMap()
        np.testing.assert_array_equal(node.getNode("K").mat(), dev.K)
        dist = node.getNode("dist").mat()
        assert dist.shape == (1, dev.dist.size)
        np.testing.assert_array_equal(dist.ravel(), dev.dist)
        size = node.getNode("size")
        assert size.isSeq() and [size.at(0).real(), size.at(1).real()] == [dev.width, dev.height]
        np.testing.assert_array_equal(node.getNode("R").mat(), dev.R)
        t = node.getNode("T").mat()
        assert t.shape == (3, 1)
        np.testing.assert_array_equal(t.ravel(), dev.T)
        rms = node.getNode("rms").real()
        assert (np.isnan(rms) and np.isnan(dev.rms)) or rms == dev.rms
    fs.release()


def test_calibration_hash_follows_content() -> None:
    a = _calibration()
    cam0 = a.devices["cam0"]
    b = Calibration(dict(a.devices))
    b.devices["cam0"] = CameraModel(
        "cam0", cam0.K + np.diag([1e-9, 0, 0]), cam0.dist, 1280, 1024, rms=cam0.rms
    )
    assert a.hash() != b.hash()
    c = Calibration({k: a.devices[k] for k in ("cam1", "cam0", "projector")})
    assert c.hash() != a.hash()  # order (which camera is the world) is content


MAT33 = "!!opencv-matrix\n      rows: 3\n      cols: 3\n      dt: d\n      data: "
MAT31 = MAT33.replace("cols: 3", "cols: 1")
MAT15 = MAT33.replace("rows: 3", "rows: 1").replace("cols: 3", "cols: 5")


def _write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _device_text(**override: str) -> str:
    fields = {
        "K": MAT33 + "[ 1000., 0., 320., 0., 1000., 240., 0., 0., 1. ]",
        "dist": MAT15 + "[ 0., 0., 0., 0., 0. ]",
        "size": "[ 640, 480 ]",
        "R": MAT33 + "[ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]",
        "T": MAT31 + "[ 0., 0., 0. ]",
        "rms": "0.1",
    }
    fields.update(override)
    body = "".join(f"   {k}: {v}\n" for k, v in fields.items() if v != "")
    return f"%YAML:1.0\n---\ncam0:\n{body}"


@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ({"K": ""}, "cam0.K: missing"),
        ({"T": "[ 1., 2. ]"}, "cam0.T: has 2 values"),
        ({"dist": "[ 0.1, 0.2, 0.3 ]"}, "cam0.dist: has 3 values"),
        ({"size": "[ 640 ]"}, "cam0.size"),
        (
            {"R": MAT33 + "[ 2., 0., 0., 0., 1., 0., 0., 0., 1. ]"},
            "cam0.R: not a rotation",
        ),
        ({"K": "[ 1., 0., 0., 0., 1., 0., 0., 0., 0. ]"}, "cam0.K"),
        ({"T": "[ .Nan, 0., 0. ]"}, "cam0.T: holds non-finite"),
    ],
)
def test_bad_calibration_names_file_device_and_key(
    tmp_path: Path, override: dict[str, str], needle: str
) -> None:
    path = _write_text(tmp_path / "bad.yaml", _device_text(**override))
    with pytest.raises(CalibrationError) as e:
        read_calibration(path)
    assert str(path) in str(e.value) and needle in str(e.value)


def test_good_hand_written_calibration_reads(tmp_path: Path) -> None:
    calib = read_calibration(_write_text(tmp_path / "ok.yaml", _device_text()))
    assert calib.camera_names == ["cam0"] and calib.projector is None
    assert calib.devices["cam0"].size == (640, 480) and calib.devices["cam0"].rms == 0.1


def test_unreadable_or_missing_calibration(tmp_path: Path) -> None:
    path = _write_text(tmp_path / "broken.yaml", "%YAML:1.0\ncam0: [1, 2\n")
    with pytest.raises(CalibrationError, match=r"broken\.yaml"):
        read_calibration(path)
    with pytest.raises(CalibrationError, match="not found"):
        read_calibration(tmp_path / "absent.yaml")
    with pytest.raises(CalibrationError, match="no device"):
        read_calibration(_write_text(tmp_path / "empty.yaml", "%YAML:1.0\n---\nnote: 3\n"))


@pytest.mark.parametrize("posed", [False, True])
def test_ray_table_reprojects_to_its_pixels(posed: bool) -> None:
    r, t = (
        look_at(np.array([120.0, -40.0, 10.0]), np.array([0.0, 0.0, 600.0]))
        if posed
        else (np.eye(3), np.zeros(3))
    )
    cam = CameraModel(
        "cam0",
        [[900, 0, 161.3], [0, 905, 118.2], [0, 0, 1]],
        [-0.25, 0.12, 1e-3, -5e-4, -0.03],
        320,
        240,
        r,
        t,
    )
    rays = RayTable(cam)
    assert rays.dirs.shape == (240, 320, 3) and rays.dirs.dtype == np.float32
    assert rays.normalized.shape == (240, 320, 2) and rays.normalized.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(rays.dirs, axis=2), 1.0, atol=1e-6)
    np.testing.assert_allclose(rays.origin, cam.center, atol=1e-9)
    pts = rays.origin + 500.0 * rays.dirs.reshape(-1, 3).astype(np.float64)
    px, z = cam.project(pts)
    ys, xs = np.mgrid[0:240, 0:320]
    np.testing.assert_allclose(px[:, 0], xs.ravel(), atol=2e-3)  # float32 directions: ~1e-4 px
    np.testing.assert_allclose(px[:, 1], ys.ravel(), atol=2e-3)
    assert np.all(z > 0)
