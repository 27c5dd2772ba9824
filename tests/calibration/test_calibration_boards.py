"""Board detection: real ChArUco and chessboard photos, and synthetic views of every board type."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from procam_helpers import PROCAM, procam_white_detections

from appliance.calibration.boards import BoardSpec, board_from_args, detect, render_board
from appliance.errors import CalibrationError

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
CHARUCO = DATA / "charuco_sample"

CHARUCO_SPEC = BoardSpec(
    type="charuco", cols=5, rows=7, square_mm=40, marker_mm=20, dictionary="DICT_6X6_250"
)


def _need(folder: Path) -> None:
    if not folder.is_dir():
        pytest.skip(f"test data {folder} is absent (shared data folder not mounted)")


def test_charuco_full_view_finds_all_24_corners() -> None:
    _need(CHARUCO)
    det = detect(cv2.imread(str(CHARUCO / "choriginal.jpg")), CHARUCO_SPEC)
    assert det is not None
    assert len(det) == 24
    np.testing.assert_array_equal(det.ids, np.arange(24))
    # every corner sits where a plane homography of the board puts it (no outliers, sub-pixel)
    H, _ = cv2.findHomography(det.object_points[:, :2], det.image_points)
    pred = cv2.perspectiveTransform(det.object_points[:, :2].reshape(-1, 1, 2), H).reshape(-1, 2)
    assert np.abs(pred - det.image_points).max() < 1.0


def test_charuco_occluded_view_gives_visible_corners_only() -> None:
    _need(CHARUCO)
    full = detect(cv2.imread(str(CHARUCO / "choriginal.jpg")), CHARUCO_SPEC)
    occ = detect(cv2.imread(str(CHARUCO / "chocclusion_original.jpg")), CHARUCO_SPEC)
    assert full is not None and occ is not None
    assert 12 <= len(occ) < 24  # the README: about 16 visible
    assert set(occ.ids.tolist()) <= set(full.ids.tolist())
    # the two photos share the board pose up to a homography: fit it on all occluded-view corners
    # and check each corner individually, so one false corner cannot hide
    src = full.image_points[np.searchsorted(full.ids, occ.ids)]
    H, _ = cv2.findHomography(src, occ.image_points, 0)
    pred = cv2.perspectiveTransform(src.reshape(-1, 1, 2), H).reshape(-1, 2)
    err = np.linalg.norm(pred - occ.image_points, axis=1)
    assert err.max() < 1.5, f"corner ids {occ.ids[err >= 1.5]} are off by {err[err >= 1.5]} px"
    np.testing.assert_allclose(occ.object_points, CHARUCO_SPEC.object_points()[occ.ids])


def test_chessboard_on_procam_white_frames() -> None:
    _need(PROCAM)
    for pose, det in enumerate(procam_white_detections()):
        assert det is not None, f"capture_{pose}"
        assert len(det) == 63
        assert det.image_size == (1280, 1024)
        # canonical order: id 0 is nearer the image's top-left than the last id
        assert det.image_points[0].sum() < det.image_points[-1].sum()
        H, _ = cv2.findHomography(det.object_points[:, :2], det.image_points)
        pred = cv2.perspectiveTransform(det.object_points[:, :2].reshape(-1, 1, 2), H).reshape(-1, 2)
        assert np.abs(pred - det.image_points).max() < 3.0  # lens distortion only


def test_no_board_in_a_black_frame() -> None:
    _need(PROCAM)
    spec = BoardSpec(type="chessboard", cols=9, rows=7, square_mm=75)
    img = np.zeros((480, 640), np.uint8)
    assert detect(img, spec) is None


@pytest.mark.parametrize(
    "spec",
    [
        BoardSpec(type="chessboard", cols=9, rows=6, square_mm=25),
        BoardSpec(type="circles", cols=7, rows=5, pitch_mm=20),
        BoardSpec(type="acircles", cols=4, rows=11, pitch_mm=15),
        CHARUCO_SPEC,
    ],
    ids=lambda s: s.type,
)
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_synthetic_views_of_every_board(spec: BoardSpec, dtype: type) -> None:
    px_per_mm = 3.0
    img, origin = render_board(spec, px_per_mm)
    H = np.array([[0.9, 0.12, 40.0], [-0.05, 0.95, 30.0], [1.2e-4, 5e-5, 1.0]])
    view = cv2.warpPerspective(img, H, (img.shape[1] + 150, img.shape[0] + 150), borderValue=255)
    view = (view.astype(np.float64) * (257 if dtype == np.uint16 else 1)).astype(dtype)
    det = detect(view, spec)
    assert det is not None
    assert len(det) == spec.n_points
    truth = cv2.perspectiveTransform((det.object_points[:, :2] * px_per_mm + origin).reshape(-1, 1, 2), H)
    assert np.abs(truth.reshape(-1, 2) - det.image_points).max() < 0.6


def test_board_from_args_messages() -> None:
    assert board_from_args("acircles", 4, 11, square_mm=15).pitch_mm == 15
    with pytest.raises(CalibrationError, match="marker_mm"):
        board_from_args("charuco", 5, 7, square_mm=40)
    with pytest.raises(CalibrationError, match="square_mm"):
        board_from_args("chessboard", 9, 6)
    with pytest.raises(CalibrationError, match="dictionary"):
        board_from_args("charuco", 5, 7, square_mm=40, marker_mm=20, dictionary="DICT_9X9")


def test_object_points_layouts() -> None:
    a = BoardSpec(type="acircles", cols=4, rows=3, pitch_mm=10).object_points()
    np.testing.assert_allclose(a[:5, :2], [[0, 0], [20, 0], [40, 0], [60, 0], [10, 10]])
    c = CHARUCO_SPEC.object_points()
    np.testing.assert_allclose(c[[0, 1, 4]], [[40, 40, 0], [80, 40, 0], [40, 80, 0]])
