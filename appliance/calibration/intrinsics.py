"""Camera intrinsics from several views of a board.

:func:`calibrate_camera` rejects unusable views (board not found, too few or collinear points, a per-view
error far above the others), calibrates with the configured distortion model, and reports the RMS, the
per-view errors, parameter standard deviations, a coverage map and warnings (fewer than 10 views, parts of
the image no view covers).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np
import numpy.typing as npt

from appliance.calibration.boards import Detection
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]

DistortionModel = Literal["none", "k1", "k2", "k2p", "k3", "k3p", "rational"]
"""Distortion model: ``kN`` = radial k1..kN, ``p`` = tangential p1 p2, ``rational`` = k1..k6 + p1 p2."""
DISTORTION_MODELS: tuple[str, ...] = get_args(DistortionModel)
MODEL_ALIASES = {"standard": "k3p", "simple": "k2p"}
"""Command-line names: ``standard`` = k1 k2 p1 p2 k3, ``simple`` = k1 k2 p1 p2."""

PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
MIN_VIEWS_WARN = 10
MIN_COVERAGE_WARN = 0.6
COVERAGE_CELL_PX = 16


def model_flags(model: str) -> tuple[int, int, tuple[str, ...]]:
    """OpenCV flags for a distortion model.

    Returns
    -------
    flags : int
        ``calibrateCamera`` flags.
    n_dist : int
        Number of distortion coefficients to keep (OpenCV order).
    params : tuple of str
        Names of the estimated intrinsic parameters.
    """
    import cv2

    model = MODEL_ALIASES.get(model, model)
    if model not in DISTORTION_MODELS:
        known = ", ".join([*DISTORTION_MODELS, *MODEL_ALIASES])
        raise CalibrationError(f"distortion model {model!r}: must be one of {known}")
    if model == "rational":
        return cv2.CALIB_RATIONAL_MODEL, 8, PARAM_NAMES
    radial = 0 if model == "none" else int(model[1])
    flags = 0
    for k, flag in ((1, cv2.CALIB_FIX_K1), (2, cv2.CALIB_FIX_K2), (3, cv2.CALIB_FIX_K3)):
        if k > radial:
            flags |= flag
    tangential = model.endswith("p")
    if not tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    names: tuple[str, ...] = ("fx", "fy", "cx", "cy", *(f"k{k}" for k in range(1, min(radial, 2) + 1)))
    names += ("p1", "p2") if tangential else ()
    names += ("k3",) if radial == 3 else ()
    return flags, 5, names


@dataclass
class CameraResult:
    """A calibrated camera (or projector) and how well the calibration went.

    Attributes
    ----------
    camera : CameraModel
        Intrinsics and distortion; pose = identity; ``rms`` set.
    rms : float
        Reprojection RMS over all used points (px).
    per_view_errors : ndarray, shape (V,)
        RMS of each used view (px).
    std_devs : dict of str to float
        Standard deviation of each estimated intrinsic parameter (px for fx fy cx cy; unitless otherwise).
    warnings : list of str
        Things a person should look at (few views, poor coverage, rejected views).
    coverage : ndarray, shape (GH, GW), int32
        How many views' board hulls cover each cell of ``COVERAGE_CELL_PX`` px.
    coverage_fraction : float
        Share of the image covered by at least one view.
    views : list of int
        Indices (into the input list) of the views used, in the order of the per-view arrays.
    rejected : dict of int to str
        Input index -> why the view was not used.
    rvecs, tvecs : ndarray, shape (V, 3)
        Board pose of each used view (Rodrigues vector; mm).
    object_points, image_points, residuals : list of ndarray
        Per used view: (N, 3) mm, (N, 2) px observed, (N, 2) px observed minus reprojected.
    ids : list of ndarray
        Per used view: board point ids (N,).
    correlations : dict of str to (str, float)
        Per estimated intrinsic: the other intrinsic it correlates with most strongly and the coefficient
        (from the joint refinement; empty before it).
    """

    camera: CameraModel
    rms: float
    per_view_errors: F64
    std_devs: dict[str, float]
    warnings: list[str]
    coverage: npt.NDArray[np.int32]
    coverage_fraction: float
    views: list[int]
    rejected: dict[int, str]
    rvecs: F64
    tvecs: F64
    object_points: list[F64] = field(default_factory=list)
    image_points: list[F64] = field(default_factory=list)
    residuals: list[F64] = field(default_factory=list)
    ids: list[npt.NDArray[np.int32]] = field(default_factory=list)
    correlations: dict[str, tuple[str, float]] = field(default_factory=dict)

    def summary(self) -> str:
        """Human summary: RMS, intrinsics with uncertainties, per-view errors, warnings."""
        cam = self.camera
        sd = self.std_devs
        lines = [
            f"{cam.name}: RMS {self.rms:.3f} px over {len(self.views)} views ({cam.width}x{cam.height})",
            f"  fx {cam.K[0, 0]:.2f} ± {sd.get('fx', 0):.2f}  fy {cam.K[1, 1]:.2f} ± {sd.get('fy', 0):.2f}  "
            f"cx {cam.K[0, 2]:.2f} ± {sd.get('cx', 0):.2f}  cy {cam.K[1, 2]:.2f} ± {sd.get('cy', 0):.2f} px",
            "  dist " + " ".join(f"{v:.5g}" for v in cam.dist),
            "  per-view RMS (px): "
            + ", ".join(f"#{i}: {e:.3f}" for i, e in zip(self.views, self.per_view_errors, strict=True)),
        ]
        strong = sorted({tuple(sorted((a, b))): r for a, (b, r) in self.correlations.items() if abs(r) >= 0.9}.items())
        if strong:
            lines.append("  strongly correlated: " + ", ".join(f"{a}-{b} {r:+.2f}" for (a, b), r in strong))
        lines += [f"  rejected view #{i}: {why}" for i, why in sorted(self.rejected.items())]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def check_view(det: Detection | None, min_points: int) -> str | None:
    """Why a detection cannot be used for calibration, or None when it can."""
    if det is None:
        return "board not found"
    if len(det) < min_points:
        return f"only {len(det)} board points (need >= {min_points})"
    obj = det.object_points[:, :2] - det.object_points[:, :2].mean(axis=0)
    sv = np.linalg.svd(obj, compute_uv=False)
    if sv[-1] < 1e-3 * sv[0]:
        return "board points are collinear"
    return None


def calibrate_camera(
    detections: Sequence[Detection | None],
    image_size: tuple[int, int],
    model: str = "k3p",
    *,
    name: str = "cam0",
    min_points: int = 6,
    max_view_rms_px: float = 1.0,
    outlier_factor: float = 3.0,
    flags: int = 0,
    K_guess: F64 | None = None,
    dist_guess: F64 | None = None,
) -> CameraResult:
    """Calibrate one camera from board detections.

    Parameters
    ----------
    detections : sequence of Detection or None
        One entry per view (None where the board was not found).
    image_size : tuple of int
        (width, height) of the images (px).
    model : str
        Distortion model, one of :data:`DISTORTION_MODELS`.
    name : str
        Device name of the result.
    min_points : int
        Views with fewer board points are rejected.
    max_view_rms_px, outlier_factor : float
        After a first calibration, a view whose RMS exceeds both ``max_view_rms_px`` and ``outlier_factor``
        times the median view RMS is rejected and the calibration is repeated.
    flags : int
        Extra OpenCV calibration flags (e.g. ``CALIB_FIX_ASPECT_RATIO``).
    K_guess : ndarray, shape (3, 3), optional
        Initial camera matrix (sets ``CALIB_USE_INTRINSIC_GUESS``).
    dist_guess : ndarray, optional
        Initial distortion (OpenCV order), used with ``K_guess``.

    Returns
    -------
    CameraResult

    Raises
    ------
    CalibrationError
        Fewer than 3 usable views, or the optimisation failed.
    """
    width, height = image_size
    rejected: dict[int, str] = {}
    usable: list[int] = []
    for i, det in enumerate(detections):
        why = check_view(det, min_points)
        if why is None and det is not None and det.image_size != (width, height):
            why = f"image is {det.image_size[0]}x{det.image_size[1]}, not {width}x{height}"
        if why is None:
            usable.append(i)
        else:
            rejected[i] = why
    base_flags, n_dist, names = model_flags(model)
    base_flags |= flags
    for _ in range(3):
        if len(usable) < 3:
            raise CalibrationError(
                f"{name}: only {len(usable)} usable views of {len(detections)} "
                f"({'; '.join(f'#{i}: {w}' for i, w in sorted(rejected.items())) or 'none rejected'}); "
                "need >= 3, better >= 10 with the board tilted and in every part of the image"
            )
        dets = [detections[i] for i in usable]
        fit = _fit(dets, (width, height), base_flags, K_guess, dist_guess)  # type: ignore[arg-type]
        errs = fit["per_view"]
        limit = max(max_view_rms_px, outlier_factor * float(np.median(errs)))
        bad = [usable[k] for k in range(len(usable)) if errs[k] > limit]
        if not bad or len(usable) - len(bad) < 3:
            break
        for i in bad:
            rejected[i] = f"view RMS {errs[usable.index(i)]:.2f} px > {limit:.2f} px (unreliable detection)"
        usable = [i for i in usable if i not in bad]
    dist = np.asarray(fit["dist"], np.float64).ravel()[:n_dist]
    camera = CameraModel(name, fit["K"], dist, width, height, rms=float(fit["rms"]))
    std = np.asarray(fit["std"], np.float64).ravel()
    std_devs = {p: float(std[PARAM_NAMES.index(p)]) for p in names if PARAM_NAMES.index(p) < std.size}
    dets = [detections[i] for i in usable]
    used = [d for d in dets if d is not None]
    residuals = [
        d.image_points - reproject(camera, d.object_points, r, t)
        for d, r, t in zip(used, fit["rvecs"], fit["tvecs"], strict=True)
    ]
    coverage = coverage_map([d.image_points for d in used], (width, height))
    cov_fraction = float(np.mean(coverage > 0))
    warnings = _warnings(len(usable), coverage, rejected)
    return CameraResult(
        camera=camera,
        rms=float(fit["rms"]),
        per_view_errors=np.asarray(errs, np.float64).ravel(),
        std_devs=std_devs,
        warnings=warnings,
        coverage=coverage,
        coverage_fraction=cov_fraction,
        views=usable,
        rejected=rejected,
        rvecs=np.asarray(fit["rvecs"], np.float64).reshape(-1, 3),
        tvecs=np.asarray(fit["tvecs"], np.float64).reshape(-1, 3),
        object_points=[d.object_points for d in used],
        image_points=[d.image_points for d in used],
        residuals=residuals,
        ids=[d.ids for d in used],
    )


def _fit(
    dets: list[Detection], size: tuple[int, int], flags: int, K_guess: F64 | None, dist_guess: F64 | None = None
) -> dict[str, Any]:
    import cv2

    obj = [np.ascontiguousarray(d.object_points, np.float32).reshape(-1, 1, 3) for d in dets]
    img = [np.ascontiguousarray(d.image_points, np.float32).reshape(-1, 1, 2) for d in dets]
    K: Any = None if K_guess is None else np.array(K_guess, np.float64)
    if K is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    no_dist: Any = None
    if K is not None and dist_guess is not None:
        no_dist = np.zeros(max(8 if flags & cv2.CALIB_RATIONAL_MODEL else 5, len(dist_guess)))
        no_dist[: len(dist_guess)] = dist_guess
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs, std_i, _std_e, per_view = cv2.calibrateCameraExtended(
            obj, img, size, K, no_dist, flags=flags, criteria=crit
        )
    except cv2.error as exc:
        raise CalibrationError(
            f"calibration failed in OpenCV: {exc.err}; check the views and the board"
        ) from exc
    if not np.isfinite(rms):
        raise CalibrationError("calibration diverged (RMS is not finite); add views with more board tilt")
    # OpenCV's per-view error is sqrt(sum e^2 / N) per view
    return {
        "rms": rms, "K": K, "dist": dist, "rvecs": rvecs, "tvecs": tvecs, "std": std_i,
        "per_view": np.asarray(per_view, np.float64).ravel(),
    }  # fmt: skip


def reproject(camera: CameraModel, object_points: F64, rvec: F64, tvec: F64) -> F64:
    """Pixels (N, 2) of board points (N, 3) mm seen at board pose (rvec, tvec)."""
    import cv2

    px, _ = cv2.projectPoints(
        np.asarray(object_points, np.float64).reshape(-1, 1, 3),
        np.asarray(rvec, np.float64).reshape(3, 1),
        np.asarray(tvec, np.float64).reshape(3, 1),
        camera.K,
        camera.dist,
    )
    return np.asarray(px, np.float64).reshape(-1, 2)


def coverage_map(image_points: Sequence[F64], image_size: tuple[int, int]) -> npt.NDArray[np.int32]:
    """How many views' board hulls cover each cell of the image.

    Parameters
    ----------
    image_points : sequence of ndarray, shape (N, 2)
        Board points of each view (px).
    image_size : tuple of int
        (width, height) (px).

    Returns
    -------
    ndarray, shape (ceil(H / 16), ceil(W / 16)), int32
    """
    import cv2

    width, height = image_size
    s = COVERAGE_CELL_PX
    gw, gh = -(-width // s), -(-height // s)
    out = np.zeros((gh, gw), np.int32)
    one = np.zeros((gh, gw), np.uint8)
    for pts in image_points:
        if len(pts) < 3:
            continue
        hull = cv2.convexHull(np.asarray(pts, np.float32).reshape(-1, 1, 2) / s - 0.5)
        one[:] = 0
        cv2.fillConvexPoly(one, np.round(hull.reshape(-1, 2) * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        out += one
    return out


_REGIONS = (
    ("top-left", "top", "top-right"),
    ("left", "centre", "right"),
    ("bottom-left", "bottom", "bottom-right"),
)


def _warnings(n_views: int, coverage: npt.NDArray[np.int32], rejected: dict[int, str]) -> list[str]:
    out: list[str] = []
    if n_views < MIN_VIEWS_WARN:
        out.append(f"only {n_views} views used; use >= {MIN_VIEWS_WARN} for stable intrinsics")
    frac = float(np.mean(coverage > 0))
    if frac < MIN_COVERAGE_WARN:
        gh, gw = coverage.shape
        empty = []
        for r in range(3):
            for c in range(3):
                cell = coverage[r * gh // 3 : (r + 1) * gh // 3, c * gw // 3 : (c + 1) * gw // 3]
                if cell.size and np.mean(cell > 0) < 0.25:
                    empty.append(_REGIONS[r][c])
        out.append(
            f"views cover only {100 * frac:.0f} % of the image (want >= {100 * MIN_COVERAGE_WARN:.0f} %); "
            f"put the board into: {', '.join(empty) or 'the image corners'}"
        )
    if rejected:
        out.append(f"{len(rejected)} view(s) rejected: " + ", ".join(f"#{i}" for i in sorted(rejected)))
    return out
