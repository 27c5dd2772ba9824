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

from appliance.calibration.bundle import BundleResult, Observation, bundle_adjust
from appliance.calibration.intrinsics import CameraResult, calibrate_camera, coverage_map
from appliance.calibration.projector import ProcamView, calibrate_procam
from appliance.calibration.report import StereoEntry
from appliance.calibration.stereo import StereoResult, stereo_calibrate
from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import PROJECTOR_NAME
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]


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
    """

    devices: dict[str, CameraModel]
    results: list[CameraResult]
    stereo: list[StereoEntry]
    initial: dict[str, CameraModel]
    bundle: BundleResult | None

    def summary(self) -> str:
        """Human summary: every device's intrinsics, RMS and pose."""
        lines = []
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
        return "\n".join(lines)


def _inverse_compose(R_dev: F64, T_dev: F64, rvec: F64, tvec: F64) -> tuple[F64, F64]:
    """Board -> world from board -> device and world -> device."""
    import cv2

    R_bd, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    R = R_dev.T @ R_bd
    t = R_dev.T @ (np.asarray(tvec, np.float64).ravel() - T_dev)
    r, _ = cv2.Rodrigues(R)
    return np.asarray(r, np.float64).ravel(), t


def calibrate_rig(
    views: Mapping[str, Sequence[ProcamView]],
    camera_sizes: Mapping[str, tuple[int, int]],
    projector_size: tuple[int, int],
    *,
    camera_model: str = "k3p",
    projector_model: str = "k2p",
    refine: bool = True,
) -> RigCalibration:
    """Calibrate cameras, projector and their poses from board poses under structured light.

    Parameters
    ----------
    views : mapping of str to sequence of ProcamView
        Per camera (first = reference, the world frame), one view per board pose, same pose order.
    camera_sizes : mapping of str to (int, int)
        (width, height) per camera (px).
    projector_size : tuple of int
        (width, height) of the projector (px).
    camera_model, projector_model : str
        Distortion models.
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
    procam = calibrate_procam(
        views[ref], camera_sizes[ref], projector_size, camera_model=camera_model,
        projector_model=projector_model, camera_name=ref, projector_name=PROJECTOR_NAME,
    )  # fmt: skip
    initial: dict[str, CameraModel] = {ref: procam.camera.camera}
    cam_results: dict[str, CameraResult] = {ref: procam.camera}
    stereo: dict[str, StereoResult] = {}
    for c in names[1:]:
        res = calibrate_camera([v.camera for v in views[c]], camera_sizes[c], camera_model, name=c)
        pairs = [
            (a.camera, b.camera) if i in procam.camera.views and i in res.views else (None, None)
            for i, (a, b) in enumerate(zip(views[ref], views[c], strict=True))
        ]
        st = stereo_calibrate(procam.camera.camera, res.camera, pairs)
        initial[c] = res.camera.with_pose(st.R, st.T)
        cam_results[c] = res
        stereo[c] = st
    initial[PROJECTOR_NAME] = procam.projector.camera.with_pose(procam.stereo.R, procam.stereo.T)
    stereo[PROJECTOR_NAME] = procam.stereo
    if not refine:
        results = [*cam_results.values(), procam.projector]
        entries = [StereoEntry(ref, n, stereo[n]) for n in [*names[1:], PROJECTOR_NAME]]
        return RigCalibration(dict(initial), results, entries, initial, None)

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
    for c in names:
        for i, v in enumerate(views[c]):
            if v.projector is not None and (c != ref or i in procam.projector.views):
                observations.append(
                    Observation(PROJECTOR_NAME, i, v.projector.object_points, v.projector.image_points, c)
                )
    models = {**{c: camera_model for c in names}, PROJECTOR_NAME: projector_model}
    bundle = bundle_adjust(initial, models, observations, poses)
    base = {**cam_results, PROJECTOR_NAME: procam.projector}
    results = [_refined_result(base[n], bundle, observations, n) for n in [*names, PROJECTOR_NAME]]
    entries = [
        StereoEntry(ref, n, _refined_stereo(bundle, observations, ref, n))
        for n in [*names[1:], PROJECTOR_NAME]
    ]
    return RigCalibration(dict(bundle.devices), results, entries, initial, bundle)


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
    coverage = coverage_map(pts, (cam.width, cam.height))
    return dataclasses.replace(
        base, camera=cam_at_origin, rms=cam.rms, per_view_errors=per_view, std_devs=sd, views=views,
        image_points=pts, residuals=res, coverage=coverage, coverage_fraction=float(np.mean(coverage > 0)),
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
