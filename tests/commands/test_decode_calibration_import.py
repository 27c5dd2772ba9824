"""Calibration files from other projects: SLMaster's ``caliInfo.yml`` (monocular and binocular layouts).

Files are written here with ``cv2.FileStorage`` in SLMaster's flat layout from known poses, read back through
:func:`read_calibration`, and checked against those poses; the real files in ``../shared/data`` against the
device centres their READMEs give.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import PROJECTOR_NAME, read_calibration
from appliance.reconstruct.defaults import default_depth_range_mm

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def _rot_y(deg: float) -> npt.NDArray[np.float64]:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _write(path: Path, entries: dict[str, npt.NDArray[np.float64]]) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    for key, value in entries.items():
        fs.write(key, np.asarray(value, np.float64))
    fs.release()
    return path


K_CAM = np.array([[1750.0, 0, 640], [0, 1750.0, 512], [0, 0, 1]])
K_PROJ = np.array([[2500.0, 0, 960], [0, 2500.0, 540], [0, 0, 1]])
DIST = np.array([[-0.07, -0.18, 2e-4, 5e-4, 1.8]])
SIZE = np.array([[1280.0], [1024.0]])


def test_monocular_layout(tmp_path: Path) -> None:
    r, t = _rot_y(5.0), np.array([[-108.0], [-5.0], [-15.0]])
    path = _write(tmp_path / "caliInfo.yml", {"M1": K_CAM, "D1": DIST, "S": SIZE, "M4": K_PROJ, "D4": DIST,
                                              "Rlp": r, "Tlp": t})  # fmt: skip
    calib = read_calibration(path, projector_size=(1920, 1080))
    assert list(calib.devices) == ["L", PROJECTOR_NAME]
    cam, proj = calib.devices["L"], calib.devices[PROJECTOR_NAME]
    assert (cam.width, cam.height) == (1280, 1024) and (proj.width, proj.height) == (1920, 1080)
    np.testing.assert_array_equal(cam.R, np.eye(3))
    np.testing.assert_allclose(proj.K, K_PROJ)
    np.testing.assert_allclose(cam.dist, DIST.ravel())
    # X_P = Rlp X_C + Tlp: a camera-frame point maps into the projector frame by (R, T) as stored
    x_c = np.array([[10.0, -20.0, 700.0]])
    np.testing.assert_allclose(proj.to_device(x_c), x_c @ r.T + t.ravel())
    with pytest.raises(CalibrationError, match="no projector size"):
        read_calibration(path)


def test_binocular_layout(tmp_path: Path) -> None:
    r, t = _rot_y(-20.0), np.array([[-196.0], [0.04], [39.0]])
    path = _write(tmp_path / "caliInfo.yml", {"M1": K_CAM, "D1": DIST, "M2": K_CAM, "D2": DIST, "S": SIZE,
                                              "Rlr": r, "Tlr": t, "R1": np.eye(3)})  # fmt: skip
    calib = read_calibration(path)
    assert list(calib.devices) == ["L", "R"] and calib.projector is None
    right = calib.devices["R"]
    np.testing.assert_allclose(right.center, -r.T @ t.ravel())  # X_R = Rlr X_L + Tlr


def test_bad_slmaster_files_are_named(tmp_path: Path) -> None:
    only_cam = _write(tmp_path / "a.yml", {"M1": K_CAM, "D1": DIST, "S": SIZE})
    with pytest.raises(CalibrationError, match="camera M1 only"):
        read_calibration(only_cam)
    not_rot = _write(tmp_path / "b.yml", {"M1": K_CAM, "D1": DIST, "M2": K_CAM, "D2": DIST, "S": SIZE,
                                          "Rlr": 2 * np.eye(3), "Tlr": np.zeros((3, 1))})  # fmt: skip
    with pytest.raises(CalibrationError, match=r"b\.yml: the rotation of R is not a rotation"):
        read_calibration(not_rot)
    short = _write(tmp_path / "c.yml", {"M1": K_CAM, "D1": DIST, "M2": K_CAM, "D2": DIST, "S": SIZE,
                                        "Rlr": np.eye(3), "Tlr": np.zeros((2, 1))})  # fmt: skip
    with pytest.raises(CalibrationError, match="Tlr: has 2 values"):
        read_calibration(short)


def test_real_slmaster_files() -> None:
    mono, bino = DATA / "slmaster_monocular" / "caliInfo.yml", DATA / "slmaster_binocular" / "caliInfo.yml"
    if not (mono.is_file() and bino.is_file()):
        pytest.skip("the SLMaster data folders are absent (shared data folder not mounted)")
    m = read_calibration(mono, projector_size=(1920, 1080))
    np.testing.assert_allclose(m.devices[PROJECTOR_NAME].center, [106.4, 4.2, 25.3], atol=0.1)  # its README
    near, far = default_depth_range_mm([m.devices["L"]], [m.devices[PROJECTOR_NAME]])
    assert near < 694 and far > 775  # the scene's depth range (README) is inside the default
    b = read_calibration(bino)
    np.testing.assert_allclose(b.devices["R"].center, [197.7, -0.03, 30.5], atol=0.1)
    near, far = default_depth_range_mm([b.devices["L"]], [b.devices["R"]])
    assert near < 507 and far > 644
