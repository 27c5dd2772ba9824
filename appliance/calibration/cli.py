"""The ``scan3d calibrate`` commands: read inputs, calibrate, print, write the file and its report."""

from __future__ import annotations

import argparse
from pathlib import Path

from appliance.calibration.boards import BoardSpec, detect
from appliance.calibration.boards import board_from_args as _board_from_values
from appliance.calibration.intrinsics import calibrate_camera
from appliance.calibration.projector import ProcamView, calibrate_procam, procam_view
from appliance.calibration.report import StereoEntry, write_report
from appliance.calibration.stereo import stereo_calibrate
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel


def board_from_args(a: argparse.Namespace) -> BoardSpec:
    """The board described by ``--board --cols --rows --square-mm --marker-mm --dictionary``."""
    return _board_from_values(
        a.board,
        a.cols,
        a.rows,
        square_mm=getattr(a, "square_mm", None),
        pitch_mm=getattr(a, "pitch_mm", None),
        marker_mm=getattr(a, "marker_mm", None),
        dictionary=getattr(a, "dictionary", None),
    )


def _write(out: Path, devices: dict[str, CameraModel]) -> None:
    from appliance.geometry.calibration_file import Calibration, write_calibration

    write_calibration(out, Calibration(devices=devices))


def calibrate_camera_cli(images: list[Path], board: BoardSpec, out: Path, model: str = "standard") -> int:
    """``scan3d calibrate camera IMAGE...``: calibrate ``cam0`` from board photos.

    Prints the RMS, the intrinsics with their standard deviations and the per-view errors; writes the
    calibration file ``out`` (one camera, ``cam0``) and its report beside it.

    Returns
    -------
    int
        0 on success (errors raise :class:`~appliance.errors.CalibrationError`).
    """
    import cv2

    if not images:
        raise CalibrationError("calibrate camera: no images given; pass one board photo per pose")
    dets = []
    size: tuple[int, int] | None = None
    for p in images:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CalibrationError(f"calibrate camera: image {p} is missing or unreadable; check the path")
        this = (int(img.shape[1]), int(img.shape[0]))
        if size is None:
            size = this
        det = detect(img, board)
        print(f"{p}: {len(det) if det is not None else 0} of {board.n_points} board points")
        dets.append(det)
    assert size is not None
    res = calibrate_camera(dets, size, model, name="cam0")
    print(res.summary())
    _write(out, {"cam0": res.camera})
    page = write_report(out, [res], title="Camera calibration", notes=[f"board: {board.describe()}"])
    print(f"wrote {out} and report {page}")
    return 0


def calibrate_projector_cli(manifests: list[Path], board: BoardSpec, out: Path) -> int:
    """``scan3d calibrate projector MANIFEST...``: cameras + projector from one manifest per board pose.

    Each manifest holds a white frame (the board is found in it) and a Gray (+ phase) sequence. The first
    camera of the manifests is the world frame; with more cameras each gets its own intrinsics and its
    pose relative to the first by stereo calibration on the board corners.

    Returns
    -------
    int
        0 on success (errors raise :class:`~appliance.errors.CalibrationError`).
    """
    from appliance.patterns.manifest import read_manifest

    if not manifests:
        raise CalibrationError("calibrate projector: no manifests given; pass one manifest per board pose")
    mans = [read_manifest(p) for p in manifests]
    cameras = mans[0].cameras
    proj_size = (mans[0].sequence.width, mans[0].sequence.height)
    for m in mans[1:]:
        if m.cameras != cameras or (m.sequence.width, m.sequence.height) != proj_size:
            raise CalibrationError(
                f"{m.path}: cameras {list(m.cameras)} / projector {m.sequence.width}x{m.sequence.height} "
                f"differ from {mans[0].path} ({list(cameras)}, {proj_size[0]}x{proj_size[1]}); "
                "use one rig for all poses"
            )
    views: dict[str, list[ProcamView]] = {c: [] for c in cameras}
    sizes: dict[str, tuple[int, int]] = {}
    for m in mans:
        for c in cameras:
            stack = m.load_stack(c)
            sizes[c] = (int(stack.shape[2]), int(stack.shape[1]))
            v = procam_view(stack, m.sequence, board)
            n_cam = len(v.camera) if v.camera is not None else 0
            n_proj = len(v.projector) if v.projector is not None else 0
            print(f"{m.path} {c}: {n_cam} board points, {n_proj} with a projector coordinate")
            views[c].append(v)
    ref = cameras[0]
    result = calibrate_procam(views[ref], sizes[ref], proj_size, camera_name=ref)
    print(result.summary())
    devices = result.devices()
    reports = [result.camera, result.projector]
    stereo = [StereoEntry(ref, "projector", result.stereo)]
    for c in cameras[1:]:
        other = calibrate_procam(views[c], sizes[c], proj_size, camera_name=c)
        pairs = [(a.camera, b.camera) for a, b in zip(views[ref], views[c], strict=True)]
        st = stereo_calibrate(result.camera.camera, other.camera.camera, pairs)
        print(other.camera.summary())
        print(f"stereo {ref} -> {c}: RMS {st.rms:.3f} px, baseline {st.baseline_mm:.2f} mm")
        devices[c] = other.camera.camera.with_pose(st.R, st.T)
        reports.append(other.camera)
        stereo.append(StereoEntry(ref, c, st))
    _write(out, devices)
    page = write_report(
        out,
        reports,
        stereo,
        title="Camera-projector calibration",
        notes=[f"board: {board.describe()}", f"poses: {len(mans)}"],
    )
    print(f"wrote {out} and report {page}")
    return 0


def calibrate_live_cli(config: Path | None) -> int:
    """``scan3d calibrate --live``: capture board poses on the configured rig and calibrate.

    Raises
    ------
    CalibrationError
        Always, for now: live capture is not implemented yet.
    """
    raise CalibrationError(
        "calibrate --live: live capture is not implemented yet; capture one manifest per board pose "
        "(scan3d grab) and run 'scan3d calibrate projector MANIFEST...'"
    )


__all__ = [
    "board_from_args",
    "calibrate_camera_cli",
    "calibrate_live_cli",
    "calibrate_projector_cli",
]
