"""Projector calibration from structured light on a board (the projector as an inverse camera).

At each board pose the camera sees the board under white light (to find the corners) and under a Gray
(+ phase) sequence (decoded into projector coordinates ``u, v`` per camera pixel). Each corner's
projector coordinate comes from a robust local fit of the decoded maps around the corner:
a plane board makes the camera -> projector mapping a homography, so a homography is fitted to the
decoded pixels of a window around the corner (RANSAC on affine triples, then iteratively reweighted least
squares with Tukey weights) and evaluated at the corner's sub-pixel position. Outlier pixels (wrong Gray
bits, dark squares, specular spots) get zero weight. The projector is then calibrated like a camera from
(board point, projector point) pairs, and the camera-projector pose by stereo calibration with fixed
intrinsics (:mod:`appliance.calibration.stereo`).
"""

from __future__ import annotations

from collections.abc import Sequence as Sequence_
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.calibration.boards import BoardSpec, Detection, detect
from appliance.calibration.intrinsics import CameraResult
from appliance.calibration.stereo import StereoResult
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel
from appliance.patterns.sequence import Sequence, WhiteFrame

F64 = npt.NDArray[np.float64]

RANSAC_TRIALS = 64
RANSAC_SCORE_PIXELS = 200
RANSAC_INLIER_PX = 2.0  # projector px; Gray-only decoding is quantised to +-0.5 px
TUKEY_C = 4.685
MIN_SCALE_PX = 0.3  # floor of the robust residual scale (projector px)
MIN_PIXELS = 30
IRLS_ITERATIONS = 6


@dataclass(frozen=True)
class CornerFit:
    """Projector coordinates of board corners.

    Attributes
    ----------
    points : ndarray, shape (N, 2), float64
        Projector (u, v) of each corner (projector px); NaN where the fit failed.
    residual_rms : ndarray, shape (N,)
        RMS of the inlier residuals of each fit (projector px); NaN where it failed.
    inliers : ndarray, shape (N,), int
        Decoded pixels that supported each fit.
    """

    points: F64
    residual_rms: F64
    inliers: npt.NDArray[np.int64]

    @property
    def valid(self) -> npt.NDArray[np.bool_]:
        """True where the corner has a projector coordinate."""
        return np.asarray(np.isfinite(self.points).all(axis=1), dtype=np.bool_)


def corner_spacing_px(image_points: F64) -> float:
    """Median distance (px) from each point to its nearest neighbour."""
    pts = np.asarray(image_points, np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return float("nan")
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def corner_projector_coords(
    u: npt.NDArray[np.floating],
    v: npt.NDArray[np.floating],
    corners_px: F64,
    radius_px: float | None = None,
    *,
    min_pixels: int = MIN_PIXELS,
    seed: int = 0,
) -> CornerFit:
    """Sub-pixel projector coordinates of camera-image points by a robust local homography fit.

    Parameters
    ----------
    u, v : ndarray, shape (H, W), float
        Decoded projector column / row per camera pixel (projector px), NaN where undecoded.
    corners_px : ndarray, shape (N, 2)
        Camera-image positions (x, y) of the board corners (px).
    radius_px : float, optional
        Half-size of the square fitting window (camera px); default 0.4 x the corner spacing, 6..40 px.
    min_pixels : int
        A corner needs at least this many inlier pixels, in two opposite quadrants around it.
    seed : int
        Seed of the RANSAC sampling (the result is deterministic for a given seed).

    Returns
    -------
    CornerFit
    """
    u = np.asarray(u)
    v = np.asarray(v)
    if u.shape != v.shape or u.ndim != 2:
        raise CalibrationError(f"decoded maps: u {u.shape} and v {v.shape} must be equal (H, W) arrays")
    corners = np.asarray(corners_px, np.float64).reshape(-1, 2)
    if radius_px is None:
        spacing = corner_spacing_px(corners)
        radius_px = float(np.clip(0.4 * spacing, 6.0, 40.0)) if np.isfinite(spacing) else 15.0
    r = int(np.ceil(radius_px))
    h, w = u.shape
    rng = np.random.default_rng(seed)
    n = len(corners)
    out = np.full((n, 2), np.nan)
    rms = np.full(n, np.nan)
    count = np.zeros(n, np.int64)
    for k, (cx, cy) in enumerate(corners):
        x0, x1 = max(int(np.floor(cx)) - r, 0), min(int(np.ceil(cx)) + r + 1, w)
        y0, y1 = max(int(np.floor(cy)) - r, 0), min(int(np.ceil(cy)) + r + 1, h)
        if x1 <= x0 or y1 <= y0:
            continue
        pu = u[y0:y1, x0:x1].astype(np.float64)
        pv = v[y0:y1, x0:x1].astype(np.float64)
        ok = np.isfinite(pu) & np.isfinite(pv)
        ys, xs = np.nonzero(ok)
        dx = (xs + x0 - cx) / radius_px
        dy = (ys + y0 - cy) / radius_px
        keep = (np.abs(dx) <= 1.0) & (np.abs(dy) <= 1.0)
        if keep.sum() < min_pixels:
            continue
        fit = _robust_homography(dx[keep], dy[keep], pu[ok][keep], pv[ok][keep], rng, min_pixels)
        if fit is not None:
            out[k], rms[k], count[k] = fit
    return CornerFit(out, rms, count)


def _robust_homography(
    dx: F64, dy: F64, pu: F64, pv: F64, rng: np.random.Generator, min_pixels: int
) -> tuple[F64, float, int] | None:
    m = len(dx)
    u0, v0 = float(np.median(pu)), float(np.median(pv))
    tu, tv = pu - u0, pv - v0
    design = np.stack([np.ones(m), dx, dy], axis=1)
    # RANSAC on affine triples, scored on a subset: a consensus start that wrong Gray bits cannot drag
    idx = rng.integers(0, m, size=(RANSAC_TRIALS, 3))
    A = design[idx]
    good = np.abs(np.linalg.det(A)) > 1e-6
    if not good.any():
        return None
    coef = np.linalg.solve(A[good], np.stack([tu[idx[good]], tv[idx[good]]], axis=2))
    sub = rng.choice(m, size=min(m, RANSAC_SCORE_PIXELS), replace=False)
    pred = design[sub] @ coef  # (trials, subset, 2)
    score = (np.hypot(pred[..., 0] - tu[sub], pred[..., 1] - tv[sub]) < RANSAC_INLIER_PX).sum(axis=1)
    best = coef[int(np.argmax(score))]
    pred_all = design @ best
    inl = np.hypot(pred_all[:, 0] - tu, pred_all[:, 1] - tv) < RANSAC_INLIER_PX
    weights = inl.astype(np.float64)
    if weights.sum() < min_pixels:
        return None
    p = np.zeros(8)
    for _ in range(IRLS_ITERATIONS):
        p = _weighted_homography(dx, dy, tu, tv, weights)
        den = 1.0 + p[6] * dx + p[7] * dy
        res = np.hypot((p[0] + p[1] * dx + p[2] * dy) / den - tu, (p[3] + p[4] * dx + p[5] * dy) / den - tv)
        scale = max(1.4826 * float(np.median(res[weights > 0])), MIN_SCALE_PX)
        z = res / (TUKEY_C * scale)
        weights = np.where(z < 1.0, (1.0 - z * z) ** 2, 0.0)
    inliers = weights > 0
    if inliers.sum() < min_pixels or not _surrounds(dx[inliers], dy[inliers]):
        return None
    resid = float(np.sqrt(np.mean(res[inliers] ** 2)))
    return np.array([p[0] + u0, p[3] + v0]), resid, int(inliers.sum())


def _weighted_homography(dx: F64, dy: F64, tu: F64, tv: F64, w: F64) -> F64:
    # u (1 + g1 dx + g2 dy) = a0 + a1 dx + a2 dy, likewise v; at the corner (dx = dy = 0): (a0, b0)
    m = len(dx)
    z, o = np.zeros(m), np.ones(m)
    rows_u = np.stack([o, dx, dy, z, z, z, -tu * dx, -tu * dy], axis=1)
    rows_v = np.stack([z, z, z, o, dx, dy, -tv * dx, -tv * dy], axis=1)
    M = np.concatenate([rows_u, rows_v])
    ww = np.concatenate([w, w])
    b = np.concatenate([tu, tv])
    normal = (M * ww[:, None]).T @ M  # 8 x 8 normal equations: well conditioned on the unit window
    try:
        return np.asarray(np.linalg.solve(normal, (M * ww[:, None]).T @ b), np.float64)
    except np.linalg.LinAlgError:
        sol, *_ = np.linalg.lstsq(normal, (M * ww[:, None]).T @ b, rcond=None)
        return np.asarray(sol, np.float64)


def _surrounds(dx: F64, dy: F64) -> bool:
    # two opposite quadrants hold >= 5 % of the support each, so the fit interpolates at the corner;
    # on a chessboard the dark squares decode poorly and the two light squares are opposite
    q = np.bincount((dx > 0).astype(np.int64) + 2 * (dy > 0), minlength=4) >= max(3, 0.05 * len(dx))
    return bool((q[0] and q[3]) or (q[1] and q[2]))


def projector_detection(cam: Detection, fit: CornerFit, projector_size: tuple[int, int]) -> Detection | None:
    """The board as the projector "sees" it: the corners with a projector coordinate.

    Parameters
    ----------
    cam : Detection
        The board corners in the camera image.
    fit : CornerFit
        Their projector coordinates (from :func:`corner_projector_coords`).
    projector_size : tuple of int
        (width, height) of the projector (px).

    Returns
    -------
    Detection or None
        None when fewer than 4 corners have a projector coordinate.
    """
    pw, ph = projector_size
    pts = fit.points
    ok = fit.valid
    ok[ok] &= (pts[ok, 0] > -0.5) & (pts[ok, 0] < pw - 0.5) & (pts[ok, 1] > -0.5) & (pts[ok, 1] < ph - 0.5)
    if ok.sum() < 4:
        return None
    return Detection(cam.ids[ok], pts[ok], cam.object_points[ok], (pw, ph))


@dataclass(frozen=True)
class ProcamView:
    """One board pose seen by a camera under white light and structured light.

    Attributes
    ----------
    camera : Detection or None
        The board in the white frame (None: not found).
    projector : Detection or None
        The corners with a projector coordinate, as the projector "sees" them (None: fewer than 4).
    fit : CornerFit or None
        The local fits behind ``projector``.
    """

    camera: Detection | None
    projector: Detection | None
    fit: CornerFit | None


def white_frame_index(sequence: Sequence) -> int:
    """Index of the first all-white frame of ``sequence`` (the board is found in it)."""
    for i, f in enumerate(sequence.frames):
        if isinstance(f, WhiteFrame):
            return i
    raise CalibrationError(
        f"sequence {sequence.describe()}: has no white frame; projector calibration finds the board "
        "under white light: add a 'white' frame to the capture"
    )


def procam_view(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    sequence: Sequence,
    board: BoardSpec,
    *,
    radius_px: float | None = None,
) -> ProcamView:
    """Find the board and its corners' projector coordinates in one captured pose.

    Parameters
    ----------
    frames : ndarray, shape (F, H, W), uint8 or uint16
        The camera's frames in the order of ``sequence`` (one white frame, Gray (+ phase) frames).
    sequence : Sequence
        What each frame shows.
    board : BoardSpec
        The board.
    radius_px : float, optional
        Local fit window half-size (camera px); see :func:`corner_projector_coords`.

    Returns
    -------
    ProcamView
    """
    from appliance.reconstruct.decode import decode

    det = detect(frames[white_frame_index(sequence)], board)
    if det is None:
        return ProcamView(None, None, None)
    maps = decode(frames, sequence)
    fit = corner_projector_coords(maps.u, maps.v, det.image_points, radius_px)
    return ProcamView(det, projector_detection(det, fit, (sequence.width, sequence.height)), fit)


@dataclass(frozen=True)
class ProcamResult:
    """A calibrated camera + projector pair.

    Attributes
    ----------
    camera, projector : CameraResult
        Intrinsics of each device (the projector as an inverse camera).
    stereo : StereoResult
        Camera -> projector pose (``x_projector = R x_camera + T``, mm) and the stereo RMS.
    """

    camera: CameraResult
    projector: CameraResult
    stereo: StereoResult

    def devices(self) -> dict[str, CameraModel]:
        """Camera (world frame) and projector with its pose, ready for a calibration file."""
        cam = self.camera.camera
        proj = self.projector.camera.with_pose(self.stereo.R, self.stereo.T)
        return {cam.name: cam, proj.name: proj}

    def summary(self) -> str:
        """Human summary of both devices and the stereo pose."""
        st = self.stereo
        return "\n".join(
            [
                self.camera.summary(),
                self.projector.summary(),
                f"stereo {self.camera.camera.name} -> {self.projector.camera.name}: RMS {st.rms:.3f} px over "
                f"{len(st.views)} poses, baseline {st.baseline_mm:.2f} mm, T = "
                + " ".join(f"{t:.2f}" for t in st.T)
                + " mm",
            ]
        )


def calibrate_procam(
    views: Sequence_[ProcamView],
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    *,
    camera_model: str = "k3p",
    projector_model: str = "k2p",
    camera_name: str = "cam0",
    projector_name: str = "projector",
) -> ProcamResult:
    """Calibrate a camera, a projector (inverse camera) and their relative pose.

    Parameters
    ----------
    views : sequence of ProcamView
        One per board pose (see :func:`procam_view`).
    camera_size, projector_size : tuple of int
        (width, height) of the camera and the projector (px).
    camera_model, projector_model : str
        Distortion models (:data:`~appliance.calibration.intrinsics.DISTORTION_MODELS`); projectors
        usually have little distortion, so the default is k1 k2 p1 p2.
    camera_name, projector_name : str
        Device names in the result.

    Returns
    -------
    ProcamResult
    """
    from appliance.calibration.intrinsics import calibrate_camera
    from appliance.calibration.stereo import stereo_calibrate

    cam = calibrate_camera([v.camera for v in views], camera_size, camera_model, name=camera_name)
    proj = calibrate_camera(
        [v.projector for v in views], projector_size, projector_model, name=projector_name
    )
    pairs = [
        (v.camera, v.projector) if i in cam.views and i in proj.views else (None, None)
        for i, v in enumerate(views)
    ]
    st = stereo_calibrate(cam.camera, proj.camera, pairs, fix_intrinsics=True)
    return ProcamResult(cam, proj, st)
