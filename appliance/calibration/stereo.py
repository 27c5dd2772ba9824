"""Extrinsics between devices: pairwise stereo calibration and a joint refinement of all devices.

Conventions (as :class:`~appliance.geometry.camera.CameraModel`): ``x_second = R @ x_first + T`` (mm);
the first camera is the world frame. A projector is an inverse camera and takes part like a camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.calibration.boards import Detection
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]
MIN_COMMON_POINTS = 6


@dataclass(frozen=True)
class StereoResult:
    """The pose of a second device relative to a first one.

    Attributes
    ----------
    R : ndarray, shape (3, 3)
        Rotation first -> second.
    T : ndarray, shape (3,)
        Translation first -> second (mm).
    rms : float
        Reprojection RMS over both devices' points (px).
    per_view_errors : ndarray, shape (V, 2)
        RMS of each used view in the first and the second device (px).
    views : list of int
        Indices (into the input pairs) of the views used.
    residuals : list of tuple of ndarray
        Per used view: (N, 2) residuals (observed minus reprojected) in the first and second device (px).
    """

    R: F64
    T: F64
    rms: float
    per_view_errors: F64
    views: list[int]
    residuals: list[tuple[F64, F64]]

    @property
    def baseline_mm(self) -> float:
        """Distance between the two optical centres (mm)."""
        return float(np.linalg.norm(self.T))


@dataclass(frozen=True)
class StereoEntry:
    """A stereo result with the names of its two devices."""

    first: str
    second: str
    result: StereoResult


def common_points(a: Detection, b: Detection) -> tuple[F64, F64, F64]:
    """Board points seen in both detections: object (N, 3) mm, image points in ``a`` and ``b`` (N, 2) px."""
    _, ia, ib = np.intersect1d(a.ids, b.ids, assume_unique=True, return_indices=True)
    return a.object_points[ia], a.image_points[ia], b.image_points[ib]


def stereo_calibrate(
    first: CameraModel,
    second: CameraModel,
    pairs: Sequence[tuple[Detection | None, Detection | None]],
    *,
    fix_intrinsics: bool = True,
) -> StereoResult:
    """Pose of ``second`` relative to ``first`` from views both see.

    Parameters
    ----------
    first, second : CameraModel
        Calibrated devices (intrinsics used as they are when ``fix_intrinsics``).
    pairs : sequence of (Detection or None, Detection or None)
        The board in both devices, one pair per board pose.
    fix_intrinsics : bool
        Keep both devices' intrinsics and distortion fixed (``CALIB_FIX_INTRINSIC``).

    Returns
    -------
    StereoResult

    Raises
    ------
    CalibrationError
        Fewer than one pose seen by both devices, or OpenCV failed.
    """
    import cv2

    views: list[int] = []
    obj: list[npt.NDArray[np.float32]] = []
    img1: list[npt.NDArray[np.float32]] = []
    img2: list[npt.NDArray[np.float32]] = []
    for i, (a, b) in enumerate(pairs):
        if a is None or b is None:
            continue
        o, p1, p2 = common_points(a, b)
        if len(o) < MIN_COMMON_POINTS:
            continue
        views.append(i)
        obj.append(np.ascontiguousarray(o, np.float32).reshape(-1, 1, 3))
        img1.append(np.ascontiguousarray(p1, np.float32).reshape(-1, 1, 2))
        img2.append(np.ascontiguousarray(p2, np.float32).reshape(-1, 1, 2))
    if not views:
        raise CalibrationError(
            f"stereo {first.name} -> {second.name}: no board pose seen by both with >= {MIN_COMMON_POINTS} "
            "common points; capture poses where both see the board"
        )
    flags = cv2.CALIB_FIX_INTRINSIC if fix_intrinsics else cv2.CALIB_USE_INTRINSIC_GUESS
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    K1, d1, K2, d2 = first.K.copy(), first.dist.copy(), second.K.copy(), second.dist.copy()
    try:
        out: Any = cv2.stereoCalibrateExtended(
            obj,
            img1,
            img2,
            K1,
            d1,
            K2,
            d2,
            first.size,
            np.eye(3),
            np.zeros((3, 1)),
            flags=flags,
            criteria=crit,
        )
    except cv2.error as exc:
        raise CalibrationError(f"stereo {first.name} -> {second.name}: OpenCV failed: {exc.err}") from exc
    rms, K1o, d1o, K2o, d2o, R, T, _E, _F, rvecs, tvecs, per_view = out
    R_: F64 = np.asarray(R, np.float64)
    T_: F64 = np.asarray(T, np.float64).ravel()
    cam1 = CameraModel(first.name, K1o, np.asarray(d1o).ravel()[: max(first.dist.size, 5)], *first.size)
    cam2 = CameraModel(second.name, K2o, np.asarray(d2o).ravel()[: max(second.dist.size, 5)], *second.size)
    residuals = []
    for ob, q1, q2, rv, tv in zip(obj, img1, img2, rvecs, tvecs, strict=True):
        R0, _ = cv2.Rodrigues(np.asarray(rv, np.float64))
        t0 = np.asarray(tv, np.float64).ravel()
        x1 = ob.reshape(-1, 3).astype(np.float64) @ R0.T + t0
        r1 = q1.reshape(-1, 2).astype(np.float64) - cam1.project(x1)[0]
        r2 = q2.reshape(-1, 2).astype(np.float64) - cam2.with_pose(R_, T_).project(x1)[0]
        residuals.append((r1, r2))
    per_view_errors = np.asarray(per_view, np.float64).reshape(-1, 2)
    return StereoResult(R_, T_, float(rms), per_view_errors, views, residuals)
