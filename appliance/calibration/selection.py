"""Distortion model selection by leave-one-view-out reprojection error.

The RMS over the views a model was fitted to always falls as parameters are added, so it cannot choose a
model. Instead each candidate is fitted once per view with that view left out; the left-out view's board
pose is then found with the candidate's intrinsics (PnP) and its reprojection error measured. A model wins
by predicting views it has not seen. A candidate is only admitted when the views determine the parameters
it adds over the base model (k1 k2 p1 p2): each added coefficient's standard deviation must be below its
magnitude, otherwise the fit only follows noise (k3 on a few views of a narrow lens is the usual case); a
refused candidate is not fitted view by view (it could not be chosen anyway), and a coefficient one
candidate cannot determine is not freed by a richer one either (no rational model when k3 alone is noise).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from appliance.calibration.boards import Detection
from appliance.calibration.intrinsics import MODEL_ALIASES, CameraResult, calibrate_camera, model_flags
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]

CANDIDATE_MODELS: tuple[str, ...] = ("k2p", "k3p", "rational")
"""Candidates in order of complexity: k1 k2 p1 p2; + k3; rational (k1..k6 p1 p2)."""
ADDED_PARAMETERS: dict[str, tuple[str, ...]] = {"k3p": ("k3",), "rational": ("k3", "k4", "k5", "k6")}
"""Coefficients a candidate adds over the base model; each must be determined by the views."""
HELD_OUT_REL_TOL = 1e-7
"""Left-out fits start at the full fit's minimum; they stop when a step gains less than this share."""
HELD_OUT_ITERATIONS = 30
"""At most this many Levenberg-Marquardt iterations per left-out fit."""
PARSIMONY = 0.01
"""A more complex model must lower the held-out error by more than this share to be chosen."""


@dataclass(frozen=True)
class HeldOut:
    """Leave-one-view-out errors of one device model.

    Attributes
    ----------
    views : list of int
        Input indices of the views that were left out in turn.
    per_view_px : ndarray, shape (V,)
        Reprojection RMS of each left-out view, pose by PnP with the intrinsics fitted without it (px).
    rms_px : float
        RMS over all left-out points (px).
    cameras : list of CameraModel
        The intrinsics fitted without each view (same order as ``views``).
    """

    views: list[int]
    per_view_px: F64
    rms_px: float
    cameras: list[CameraModel] = field(default_factory=list)


@dataclass(frozen=True)
class Candidate:
    """One candidate distortion model of a device.

    Attributes
    ----------
    model : str
        Model name (:data:`~appliance.calibration.intrinsics.DISTORTION_MODELS`).
    rms_px : float
        RMS over the views it was fitted to (px).
    held_out : HeldOut
        Leave-one-view-out errors.
    undetermined : dict of str to (float, float)
        Added coefficients the views cannot determine: name -> (value, standard deviation).
    result : CameraResult
        The fit on all views.
    """

    model: str
    rms_px: float
    held_out: HeldOut
    undetermined: dict[str, tuple[float, float]]
    result: CameraResult

    @property
    def admissible(self) -> bool:
        """True when the views determine every coefficient the model adds."""
        return not self.undetermined


@dataclass(frozen=True)
class ModelChoice:
    """The distortion model chosen for a device and why.

    Attributes
    ----------
    device : str
        Device name.
    chosen : str
        The model used.
    candidates : list of Candidate
        Every model tried.
    reason : str
        Why ``chosen`` was taken.
    forced : bool
        True when the model was given (``--model``), not selected.
    """

    device: str
    chosen: str
    candidates: list[Candidate]
    reason: str
    forced: bool = False

    @property
    def best(self) -> Candidate:
        """The chosen candidate."""
        return next(c for c in self.candidates if c.model == self.chosen)

    def lines(self) -> list[str]:
        """Human report: one line per candidate and the reason."""
        out = [f"{self.device}: distortion model {self.chosen} ({'forced' if self.forced else 'selected'})"]
        for c in self.candidates:
            note = ""
            if c.undetermined:
                note = "; not determined: " + ", ".join(
                    f"{k} = {v:.3g} ± {s:.3g}" for k, (v, s) in c.undetermined.items()
                )
            held = (f"held-out {c.held_out.rms_px:.4f} px" if c.held_out.views
                    else "held-out not computed (refused)")  # fmt: skip
            mark = "  <- chosen" if c.model == self.chosen else ""
            out.append(f"  {c.model:8s} RMS {c.rms_px:.4f} px, {held}{note}{mark}")
        out.append(f"  why: {self.reason}")
        return out


def pnp_error(camera: CameraModel, det: Detection) -> tuple[float, int]:
    """Sum of squared reprojection errors (px^2) and point count of a view, pose by PnP with ``camera``."""
    import cv2

    obj = np.ascontiguousarray(det.object_points, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(det.image_points, np.float64).reshape(-1, 1, 2)
    ok, rv, tv = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return float("nan"), len(obj)
    rv, tv = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rv, tv)
    px, _ = cv2.projectPoints(obj, rv, tv, camera.K, camera.dist)
    e = px.reshape(-1, 2) - img.reshape(-1, 2)
    return float(np.sum(e * e)), len(obj)


def held_out_errors(
    detections: Sequence[Detection | None],
    image_size: tuple[int, int],
    model: str,
    views: Sequence[int],
    *,
    name: str = "cam0",
    start: CameraResult | None = None,
) -> HeldOut:
    """Leave-one-view-out reprojection error of a distortion model.

    Parameters
    ----------
    detections : sequence of Detection or None
        One per view (None: board not found).
    image_size : tuple of int
        (width, height) (px).
    model : str
        Distortion model.
    views : sequence of int
        The usable views (indices into ``detections``); each is left out in turn.
    name : str
        Device name (for messages).
    start : CameraResult, optional
        The fit of ``model`` on all ``views``: each left-out fit then starts from it (intrinsics and board
        poses) and is solved by :func:`~appliance.calibration.bundle.bundle_adjust` - the same least-squares
        problem, a few iterations from its minimum. Without it every left-out fit is a fresh OpenCV one.

    Returns
    -------
    HeldOut
        NaN for a view whose calibration without it failed (fewer than 3 views left).
    """
    per_view = np.full(len(views), np.nan)
    cams: list[CameraModel] = []
    sq, n = 0.0, 0
    for k, i in enumerate(views):
        det = detections[i]
        assert det is not None
        cam = _fit_without(detections, i, image_size, model, name, start)
        if cam is None:
            cams.append(CameraModel(name, np.eye(3), np.zeros(5), *image_size))
            continue
        cams.append(cam)
        s, m = pnp_error(cam, det)
        per_view[k] = np.sqrt(s / m)
        if np.isfinite(s):
            sq += s
            n += m
    rms = float(np.sqrt(sq / n)) if n else float("nan")
    return HeldOut(list(views), per_view, rms, cams)


def _fit_without(
    dets: Sequence[Detection | None],
    left_out: int,
    size: tuple[int, int],
    model: str,
    name: str,
    start: CameraResult | None,
) -> CameraModel | None:
    """The fit of every view but ``left_out``; None when it fails (too few views left)."""
    from appliance.calibration.bundle import Observation, bundle_adjust

    if start is not None and len(start.views) > 3:
        obs, poses = [], {}
        for k, i in enumerate(start.views):
            d = dets[i]
            if i == left_out or d is None:
                continue
            obs.append(Observation(name, i, d.object_points, d.image_points))
            poses[i] = (start.rvecs[k], start.tvecs[k])
        try:
            res = bundle_adjust({name: start.camera}, {name: model}, obs, poses, reject_outliers=False,
                                rel_tol=HELD_OUT_REL_TOL, max_iterations=HELD_OUT_ITERATIONS,
                                covariance=False)  # fmt: skip
            cam = res.devices[name]
            return CameraModel(name, cam.K, cam.dist, cam.width, cam.height)
        except CalibrationError:
            pass
    rest = [d if j != left_out else None for j, d in enumerate(dets)]
    try:
        return calibrate_camera(rest, size, model, name=name).camera
    except CalibrationError:
        return None


def _undetermined(result: CameraResult, model: str) -> dict[str, tuple[float, float]]:
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    values = dict(zip(names, result.camera.dist, strict=False))
    out = {}
    for p in ADDED_PARAMETERS.get(model, ()):
        v, s = float(values.get(p, 0.0)), float(result.std_devs.get(p, np.inf))
        if not np.isfinite(s) or s >= abs(v):
            out[p] = (v, s)
    return out


def select_model(
    detections: Sequence[Detection | None],
    image_size: tuple[int, int],
    *,
    name: str = "cam0",
    candidates: Sequence[str] = CANDIDATE_MODELS,
    forced: str | None = None,
) -> tuple[CameraResult, ModelChoice]:
    """Calibrate a device with the distortion model that predicts left-out views best.

    Parameters
    ----------
    detections : sequence of Detection or None
        Board detections, one per view.
    image_size : tuple of int
        (width, height) (px).
    name : str
        Device name.
    candidates : sequence of str
        Models to compare, simplest first.
    forced : str, optional
        Use this model (``--model``); it is still scored, for the report.

    Returns
    -------
    result : CameraResult
        The calibration with the chosen model.
    choice : ModelChoice

    Raises
    ------
    CalibrationError
        Too few usable views, or an unknown forced model.
    """
    if forced is not None:
        forced = MODEL_ALIASES.get(forced, forced)
        model_flags(forced)  # validates the name
        names = [forced]
    else:
        names = [MODEL_ALIASES.get(c, c) for c in candidates]
    scored: list[Candidate] = []
    undetermined: dict[str, tuple[float, float]] = {}
    for model in names:
        res = calibrate_camera(detections, image_size, model, name=name)
        und = _undetermined(res, model)
        # a coefficient a simpler model could not determine is not determined by a richer one either
        und.update({p: undetermined[p] for p in ADDED_PARAMETERS.get(model, ()) if p in undetermined and p not in und})
        undetermined.update(und)
        if und and forced is None:  # refused whatever its held-out error: spare the left-out fits
            ho = HeldOut([], np.zeros(0), float("nan"))
        else:
            ho = held_out_errors(detections, image_size, model, res.views, name=name, start=res)
        scored.append(Candidate(model, res.rms, ho, und, res))
    if forced is not None:
        c = scored[0]
        return c.result, ModelChoice(name, forced, scored, f"forced by --model {forced}", forced=True)
    ok = [c for c in scored if c.admissible and np.isfinite(c.held_out.rms_px)]
    if not ok:
        ok = scored[:1]
    best = ok[0]
    for c in ok[1:]:
        if c.held_out.rms_px < best.held_out.rms_px * (1 - PARSIMONY):
            best = c
    parts = [f"{best.model} predicts left-out views best ({best.held_out.rms_px:.4f} px)"]
    for c in ok:
        if c is best:
            continue
        if c.held_out.rms_px < best.held_out.rms_px:
            parts.append(f"{c.model} ({c.held_out.rms_px:.4f} px) is not > {100 * PARSIMONY:.0f} % better, "
                         "so the simpler model is kept")  # fmt: skip
        else:
            parts.append(f"{c.model} {c.held_out.rms_px:.4f} px")
    for c in scored:
        if not c.admissible:
            why = ", ".join(f"{k} std {sd:.3g} >= |{v:.3g}|" for k, (v, sd) in c.undetermined.items())
            parts.append(f"{c.model} refused: the views do not determine it ({why})")
    reason = "; ".join(parts)
    return best.result, ModelChoice(name, best.model, scored, reason)
