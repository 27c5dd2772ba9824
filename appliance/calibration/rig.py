"""Calibration of a whole rig: every camera, the projector and all poses, refined jointly.

Starting values come from the pairwise methods (per camera :func:`~appliance.calibration.intrinsics.
calibrate_camera`, the projector from the reference camera's decoding, camera -> projector and
camera -> camera by :func:`~appliance.calibration.stereo.stereo_calibrate`); then
:func:`~appliance.calibration.bundle.bundle_adjust` refines all intrinsics, extrinsics and board poses
together, using the projector corners decoded by every camera.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.calibration.advice import Weakness, assess
from appliance.calibration.boards import Detection
from appliance.calibration.bundle import BundleResult, Observation, bundle_adjust
from appliance.calibration.intrinsics import CameraResult, coverage_map
from appliance.calibration.projector import ProcamView
from appliance.calibration.selection import (
    HELD_OUT_ITERATIONS,
    HELD_OUT_REL_TOL,
    ModelChoice,
    pnp_error,
    select_model,
)
from appliance.calibration.stereo import StereoEntry, StereoResult, stereo_calibrate
from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import PROJECTOR_NAME
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]


GUARD_TOLERANCE = 0.0
"""The joint refinement may not raise a device's held-out error above its pairwise one by more than this share."""


@dataclass(frozen=True)
class GuardEntry:
    """How the joint refinement did against the pairwise calibration of one device, on left-out views.

    Attributes
    ----------
    device : str
        Device name.
    pairwise_px : float
        Held-out RMS of the pairwise intrinsics (px).
    joint_px : float
        Held-out RMS of the jointly refined intrinsics (px); for a device held at its pairwise values, the
        error of the refinement that was refused.
    kept_pairwise : bool
        True when the joint refinement was worse, so the device's intrinsics were held at the pairwise values.
    transfer_pairwise_px, transfer_joint_px : float
        Non-reference devices: RMS over left-out views of the device's board points predicted from the
        reference camera's PnP pose of the board and the extrinsics (px), for the pairwise calibration and
        the joint refinement (of its last check) - what intrinsics and extrinsics together get right.
    """

    device: str
    pairwise_px: float
    joint_px: float
    kept_pairwise: bool
    transfer_pairwise_px: float = float("nan")
    transfer_joint_px: float = float("nan")

    def line(self) -> str:
        """One human line."""
        verdict = ("worse: intrinsics held at the pairwise values" if self.kept_pairwise
                   else "not worse: refined intrinsics kept")  # fmt: skip
        out = (f"{self.device}: held-out error pairwise {self.pairwise_px:.4f} px, joint "
               f"{self.joint_px:.4f} px ({verdict})")  # fmt: skip
        if np.isfinite(self.transfer_pairwise_px) or np.isfinite(self.transfer_joint_px):
            out += (f"; predicted from the reference camera's pose of a left-out board: pairwise "
                    f"{self.transfer_pairwise_px:.4f} px, joint {self.transfer_joint_px:.4f} px")  # fmt: skip
        return out


@dataclass
class RigCalibration:
    """A calibrated rig.

    Attributes
    ----------
    devices : dict of str to CameraModel
        Cameras (first = world frame) and the projector, with poses (mm); ready for a calibration file.
    results : list of CameraResult
        Per device, for the report (after the joint refinement when it ran).
    stereo : list of StereoEntry
        Reference camera -> every other device.
    initial : dict of str to CameraModel
        The pairwise (starting) calibration.
    bundle : BundleResult or None
        The joint refinement (None when it was not run).
    choices : dict of str to ModelChoice
        Per device: the distortion model candidates, their held-out errors and the choice.
    guard : list of GuardEntry
        Per device: held-out error of the pairwise and the joint intrinsics (empty without refinement).
    weaknesses : dict of str to list of Weakness
        Per device: what makes the calibration weak and which poses to add.
    """

    devices: dict[str, CameraModel]
    results: list[CameraResult]
    stereo: list[StereoEntry]
    initial: dict[str, CameraModel]
    bundle: BundleResult | None
    choices: dict[str, ModelChoice] = dataclasses.field(default_factory=dict)
    guard: list[GuardEntry] = dataclasses.field(default_factory=list)
    weaknesses: dict[str, list[Weakness]] = dataclasses.field(default_factory=dict)

    def model_lines(self) -> list[str]:
        """Model selection and the joint-refinement check, as human lines."""
        lines = [line for c in self.choices.values() for line in c.lines()]
        if self.guard:
            lines.append("joint refinement against the pairwise calibration, on left-out views:")
            lines += ["  " + g.line() for g in self.guard]
        return lines

    def weakness_lines(self) -> list[str]:
        """What to improve, one line per weakness (empty when the calibration is not weak)."""
        return [f"{name}: {w.line()}" for name, ws in self.weaknesses.items() for w in ws]

    def summary(self) -> str:
        """Human summary: model choice, every device's intrinsics, RMS and pose, weaknesses."""
        lines = self.model_lines()
        if self.bundle is not None:
            b = self.bundle
            lines.append(
                f"joint refinement of {len(self.devices)} devices over {len(b.board_poses)} poses: RMS "
                f"{b.rms:.3f} px after {b.iterations} iterations ({b.dropped_points} outlier points dropped)"
            )
        for res in self.results:
            lines.append(res.summary())
        for e in self.stereo:
            st = e.result
            lines.append(
                f"stereo {e.first} -> {e.second}: RMS {st.rms:.3f} px, baseline {st.baseline_mm:.3f} mm, "
                "T = " + " ".join(f"{t:.3f}" for t in st.T) + " mm"
            )
        weak = self.weakness_lines()
        if weak:
            lines.append("the calibration is weak:")
            lines += ["  " + w for w in weak]
        return "\n".join(lines)


def _inverse_compose(R_dev: F64, T_dev: F64, rvec: F64, tvec: F64) -> tuple[F64, F64]:
    """Board -> world from board -> device and world -> device."""
    import cv2

    R_bd, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    R = R_dev.T @ R_bd
    t = R_dev.T @ (np.asarray(tvec, np.float64).ravel() - T_dev)
    r, _ = cv2.Rodrigues(R)
    return np.asarray(r, np.float64).ravel(), t


def _forced(model: str) -> str | None:
    return None if model == "auto" else model


def calibrate_rig(
    views: Mapping[str, Sequence[ProcamView]],
    camera_sizes: Mapping[str, tuple[int, int]],
    projector_size: tuple[int, int] | None,
    *,
    camera_model: str = "auto",
    projector_model: str = "auto",
    refine: bool = True,
) -> RigCalibration:
    """Calibrate cameras, the projector and their poses: pairwise start, then one joint refinement.

    Each device's distortion model is chosen by leave-one-view-out error
    (:func:`~appliance.calibration.selection.select_model`). The joint refinement of all devices is then
    checked on left-out views: a device whose refined intrinsics predict left-out views worse than its
    pairwise ones keeps the pairwise intrinsics (only poses are refined for it).

    Parameters
    ----------
    views : mapping of str to sequence of ProcamView
        Per camera (first = reference, the world frame), one view per board pose, same pose order. Without
        a projector the views carry camera detections only.
    camera_sizes : mapping of str to (int, int)
        (width, height) per camera (px).
    projector_size : tuple of int or None
        (width, height) of the projector (px); None: cameras only.
    camera_model, projector_model : str
        Distortion models; ``auto`` selects by held-out error.
    refine : bool
        Run the joint refinement of all devices (otherwise the pairwise result is returned).

    Returns
    -------
    RigCalibration

    Raises
    ------
    CalibrationError
        Too few usable poses for a device, or a failed optimisation.
    """
    names = list(views)
    if not names:
        raise CalibrationError("calibrate rig: no camera views given")
    n_views = {len(v) for v in views.values()}
    if len(n_views) != 1:
        raise CalibrationError(f"calibrate rig: cameras have different numbers of poses {sorted(n_views)}")
    ref = names[0]
    cam_results: dict[str, CameraResult] = {}
    choices: dict[str, ModelChoice] = {}
    for c in names:
        cam_results[c], choices[c] = select_model(
            [v.camera for v in views[c]], camera_sizes[c], name=c, forced=_forced(camera_model)
        )
    initial: dict[str, CameraModel] = {ref: cam_results[ref].camera}
    stereo: dict[str, StereoResult] = {}
    for c in names[1:]:
        res = cam_results[c]
        pairs = [
            (a.camera, b.camera) if i in cam_results[ref].views and i in res.views else (None, None)
            for i, (a, b) in enumerate(zip(views[ref], views[c], strict=True))
        ]
        st = stereo_calibrate(cam_results[ref].camera, res.camera, pairs)
        initial[c] = res.camera.with_pose(st.R, st.T)
        stereo[c] = st
    all_results = dict(cam_results)
    if projector_size is not None:
        proj, choices[PROJECTOR_NAME] = select_model(
            [v.projector for v in views[ref]], projector_size, name=PROJECTOR_NAME,
            forced=_forced(projector_model),
        )  # fmt: skip
        pairs = [
            (v.camera, v.projector) if i in cam_results[ref].views and i in proj.views else (None, None)
            for i, v in enumerate(views[ref])
        ]
        st = stereo_calibrate(cam_results[ref].camera, proj.camera, pairs, fix_intrinsics=True)
        initial[PROJECTOR_NAME] = proj.camera.with_pose(st.R, st.T)
        stereo[PROJECTOR_NAME] = st
        all_results[PROJECTOR_NAME] = proj
    others = [n for n in initial if n != ref]
    if not refine:
        entries = [StereoEntry(ref, n, stereo[n]) for n in others]
        out = RigCalibration(dict(initial), list(all_results.values()), entries, initial, None, choices)
        out.weaknesses = {n: assess(r, choices.get(n)) for n, r in all_results.items()}
        return out

    poses: dict[int, tuple[F64, F64]] = {}
    for c in names:
        res = cam_results[c]
        for k, i in enumerate(res.views):
            if i not in poses:
                dev = initial[c]
                poses[i] = _inverse_compose(dev.R, dev.T, res.rvecs[k], res.tvecs[k])
    observations: list[Observation] = []
    for c in names:
        used = set(cam_results[c].views)
        for i, v in enumerate(views[c]):
            if v.camera is not None and i in used:
                observations.append(Observation(c, i, v.camera.object_points, v.camera.image_points, c))
    if projector_size is not None:
        proj_views = set(all_results[PROJECTOR_NAME].views)
        for c in names:
            for i, v in enumerate(views[c]):
                if v.projector is not None and (c != ref or i in proj_views):
                    observations.append(
                        Observation(PROJECTOR_NAME, i, v.projector.object_points, v.projector.image_points, c)
                    )
    models = {n: choices[n].chosen for n in initial}
    bundle, guard, loo_devices = _guarded_bundle(initial, models, observations, poses, choices, all_results)
    guard = _with_transfer(guard, views, ref, choices, loo_devices)
    results = [_refined_result(all_results[n], bundle, observations, n) for n in initial]
    entries = [StereoEntry(ref, n, _refined_stereo(bundle, observations, ref, n)) for n in others]
    out = RigCalibration(dict(bundle.devices), results, entries, initial, bundle, choices, guard)
    out.weaknesses = {r.camera.name: assess(r, choices.get(r.camera.name), all_results[r.camera.name])
                      for r in results}  # fmt: skip
    return out


def _guarded_bundle(
    initial: dict[str, CameraModel],
    models: dict[str, str],
    observations: list[Observation],
    poses: dict[int, tuple[F64, F64]],
    choices: Mapping[str, ModelChoice],
    pairwise: Mapping[str, CameraResult],
) -> tuple[BundleResult, list[GuardEntry], dict[int, dict[str, CameraModel]]]:
    """Joint refinement whose intrinsics are never worse than the pairwise ones on left-out views.

    Each view is left out in turn: the refinement is solved without it (starting from the solution on all
    views) and every device's left-out error is measured by PnP with its refined intrinsics, as the
    pairwise held-out error was. A device that does worse keeps its pairwise intrinsics, and the
    refinement is repeated with them fixed, until no device does worse.
    """
    fixed: set[str] = set()
    bundle = bundle_adjust(initial, models, observations, poses)
    joint_px: dict[str, float] = {}
    loo_devices: dict[int, dict[str, CameraModel]] = {}
    for _ in range(len(initial)):
        errors, loo_devices = _joint_held_out(bundle, models, observations, choices, fixed)
        joint_px.update(errors)
        worse = {
            n for n, e in joint_px.items()
            if n not in fixed and e > choices[n].best.held_out.rms_px * (1 + GUARD_TOLERANCE)
        }  # fmt: skip
        if not worse:
            break
        fixed |= worse
        start = {n: (pairwise[n].camera.with_pose(d.R, d.T) if n in fixed else d)
                 for n, d in bundle.devices.items()}  # fmt: skip
        bundle = bundle_adjust(start, models, observations, bundle.board_poses, fixed=fixed)
    guard = [
        GuardEntry(n, choices[n].best.held_out.rms_px, joint_px.get(n, float("nan")), n in fixed)
        for n in initial
    ]  # fmt: skip
    return bundle, guard, loo_devices


def _joint_held_out(
    bundle: BundleResult,
    models: dict[str, str],
    observations: list[Observation],
    choices: Mapping[str, ModelChoice],
    fixed: set[str],
) -> tuple[dict[str, float], dict[int, dict[str, CameraModel]]]:
    """Per device not in ``fixed``: RMS over left-out views of the refinement solved without each view;
    and the devices of each of those refinements."""
    solved: dict[int, dict[str, CameraModel]] = {}
    sq = dict.fromkeys(bundle.devices, 0.0)
    cnt = dict.fromkeys(bundle.devices, 0)
    ref_obs: dict[tuple[str, int], Observation] = {}
    for o in observations:
        # the pairwise held-out error of a projector used the reference camera's decoding
        ref_obs.setdefault((o.device, o.view), o)
    views = sorted({v for n in bundle.devices if n not in fixed for v in choices[n].best.held_out.views})
    for v in views:
        rest = [o for o in observations if o.view != v]
        poses = {k: p for k, p in bundle.board_poses.items() if k != v}
        if not rest or not poses:
            continue
        try:
            loo = bundle_adjust(bundle.devices, models, rest, poses, fixed=fixed, rel_tol=HELD_OUT_REL_TOL,
                                max_iterations=HELD_OUT_ITERATIONS, covariance=False)  # fmt: skip
        except CalibrationError:
            continue
        solved[v] = loo.devices
        for n, dev in loo.devices.items():
            if n in fixed or v not in choices[n].best.held_out.views:
                continue
            held = ref_obs.get((n, v))
            if held is None:
                continue
            cam = CameraModel(n, dev.K, dev.dist, dev.width, dev.height)
            s, m = pnp_error(cam, Detection(np.arange(len(held.image_points), dtype=np.int32), held.image_points,
                                            held.object_points, (dev.width, dev.height)))  # fmt: skip
            if np.isfinite(s):
                sq[n] += s
                cnt[n] += m
    errors = {n: float(np.sqrt(sq[n] / cnt[n])) if cnt[n] else float("nan") for n in bundle.devices if n not in fixed}
    return errors, solved


def _transfer_error(
    ref_cam: CameraModel, dev: CameraModel, seen_ref: Detection, seen_dev: Detection
) -> tuple[float, int]:
    """Squared error sum (px^2) and count of ``seen_dev`` predicted through the board pose ``ref_cam`` finds."""
    import cv2

    obj = np.ascontiguousarray(seen_ref.object_points, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(seen_ref.image_points, np.float64).reshape(-1, 1, 2)
    ok, rv, tv = cv2.solvePnP(obj, img, ref_cam.K, ref_cam.dist)
    if not ok:
        return float("nan"), 0
    rv, tv = cv2.solvePnPRefineLM(obj, img, ref_cam.K, ref_cam.dist, rv, tv)
    R, _ = cv2.Rodrigues(rv)
    world = np.asarray(seen_dev.object_points, np.float64) @ R.T + np.asarray(tv, np.float64).ravel()
    e = dev.project(world)[0] - seen_dev.image_points
    return float(np.sum(e * e)), len(e)


def _with_transfer(
    guard: list[GuardEntry],
    views: Mapping[str, Sequence[ProcamView]],
    ref: str,
    choices: Mapping[str, ModelChoice],
    loo_devices: dict[int, dict[str, CameraModel]],
) -> list[GuardEntry]:
    """The guard entries with each non-reference device's left-out transfer error (pairwise and joint)."""
    out = []
    ref_ho = choices[ref].best.held_out
    for g in guard:
        if g.device == ref:
            out.append(g)
            continue
        ho = choices[g.device].best.held_out

        def seen(i: int, device: str = g.device) -> Detection | None:
            v = views[ref][i] if device == PROJECTOR_NAME else views[device][i]
            return v.projector if device == PROJECTOR_NAME else v.camera

        sums = {"pairwise": [0.0, 0], "joint": [0.0, 0]}
        for v in sorted(set(ho.views) & set(ref_ho.views)):
            a, b = views[ref][v].camera, seen(v)
            if a is None or b is None:
                continue
            ref_cam = ref_ho.cameras[ref_ho.views.index(v)]
            dev_cam = ho.cameras[ho.views.index(v)]
            pairs = [(views[ref][i].camera, seen(i)) if i != v and i in ho.views and i in ref_ho.views
                     else (None, None) for i in range(len(views[ref]))]  # fmt: skip
            try:
                st = stereo_calibrate(ref_cam, dev_cam, pairs)
                s, m = _transfer_error(ref_cam, dev_cam.with_pose(st.R, st.T), a, b)
            except CalibrationError:
                s, m = float("nan"), 0
            if np.isfinite(s) and m:
                sums["pairwise"][0] += s
                sums["pairwise"][1] += m
            if v in loo_devices:
                devs = loo_devices[v]
                s, m = _transfer_error(devs[ref], devs[g.device], a, b)
                if np.isfinite(s) and m:
                    sums["joint"][0] += s
                    sums["joint"][1] += m
        rms = {k: float(np.sqrt(sq / n)) if n else float("nan") for k, (sq, n) in sums.items()}
        out.append(dataclasses.replace(g, transfer_pairwise_px=rms["pairwise"], transfer_joint_px=rms["joint"]))
    return out


def _refined_result(
    base: CameraResult, bundle: BundleResult, obs: list[Observation], name: str
) -> CameraResult:
    """``base`` with the refined device, residuals, per-view errors and standard deviations."""
    pts: list[F64] = []
    res: list[F64] = []
    views: list[int] = []
    for o, r in zip(obs, bundle.residuals, strict=True):
        if o.device != name:
            continue
        ok = np.isfinite(r).all(axis=1)
        pts.append(o.image_points[ok])
        res.append(r[ok])
        views.append(o.view)
    per_view = np.array([np.sqrt(np.mean(np.sum(r * r, axis=1))) if len(r) else np.nan for r in res])
    cam = bundle.devices[name]
    cam_at_origin = CameraModel(cam.name, cam.K, cam.dist, cam.width, cam.height, rms=cam.rms)
    intrinsic = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    sd = {k: v for k, v in bundle.std_devs[name].items() if k in intrinsic}
    corr = {k: v for k, v in bundle.correlations.get(name, {}).items() if k in intrinsic}
    coverage = coverage_map(pts, (cam.width, cam.height))
    return dataclasses.replace(
        base, camera=cam_at_origin, rms=cam.rms, per_view_errors=per_view, std_devs=sd, views=views,
        image_points=pts, residuals=res, coverage=coverage, coverage_fraction=float(np.mean(coverage > 0)),
        correlations=corr or base.correlations,
    )  # fmt: skip


def _refined_stereo(bundle: BundleResult, obs: list[Observation], first: str, second: str) -> StereoResult:
    """Pose of ``second`` in ``first`` (the reference) from the refinement, with per-view RMS of both."""
    dev = bundle.devices[second]
    by_view: dict[int, list[list[F64]]] = {}
    for o, r in zip(obs, bundle.residuals, strict=True):
        if o.device in (first, second):
            slot = by_view.setdefault(o.view, [[], []])
            slot[0 if o.device == first else 1].append(r[np.isfinite(r).all(axis=1)])
    views = sorted(v for v, (a, b) in by_view.items() if a and b)
    per_view = np.zeros((len(views), 2))
    residuals: list[tuple[F64, F64]] = []
    sq, n = 0.0, 0
    for k, v in enumerate(views):
        a, b = (np.concatenate(x) for x in by_view[v])
        per_view[k] = np.sqrt(np.mean(np.sum(a * a, axis=1))), np.sqrt(np.mean(np.sum(b * b, axis=1)))
        residuals.append((a, b))
        sq += float(np.sum(a * a) + np.sum(b * b))
        n += len(a) + len(b)
    rms = float(np.sqrt(sq / max(n, 1)))
    return StereoResult(dev.R.copy(), dev.T.copy(), rms, per_view, views, residuals)
