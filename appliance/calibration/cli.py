"""The ``scan3d calibrate`` commands: read inputs, calibrate, print, write the file and its report."""

from __future__ import annotations

import argparse
import hashlib
import os
from pathlib import Path

import numpy as np

from appliance.atomic_write import same_file
from appliance.calibration.boards import BoardSpec, detect
from appliance.calibration.boards import board_from_args as _board_from_values
from appliance.calibration.projector import ProcamView, procam_view
from appliance.calibration.report import write_rig_calibration
from appliance.config.yamlfile import read_bytes_file
from appliance.errors import CalibrationError


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


MAX_IMAGE_BYTES = 512 * 1024 * 1024
"""Largest board image read (bytes)."""


def check_output(out: Path, inputs: list[tuple[str, Path]]) -> None:
    """Before any work: the calibration file ``out`` is none of the inputs, and its folder exists (or is made)
    and is writable.

    Raises
    ------
    CalibrationError
        Naming ``out``, the input it would destroy or the folder's problem, and the fix.
    """
    clash = same_file(out, inputs)
    if clash is not None:
        raise CalibrationError(f"calibrate: --out {out} is also {clash[0]}: writing the calibration would destroy "
                               "it; choose another --out (e.g. calibration.yaml)")
    if out.is_dir():
        raise CalibrationError(f"calibrate: --out {out} is a folder; give a file name such as {out}/calibration.yaml")
    folder = out.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise CalibrationError(f"calibrate: --out {out}: its folder cannot be made ({why}); give a writable "
                               "folder") from exc
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CalibrationError(f"calibrate: --out {out}: the folder {folder} is not writable; give a writable "
                               "folder")


def _check_models(*models: str) -> None:
    """Fail before any image is read when a forced model name is unknown."""
    from appliance.calibration.intrinsics import model_flags

    for m in models:
        if m != "auto":
            model_flags(m)


def calibrate_camera_cli(
    images: list[Path], board: BoardSpec, out: Path, model: str = "auto"
) -> int:
    """``scan3d calibrate camera IMAGE...``: calibrate ``cam0`` from board photos.

    The distortion model is chosen by leave-one-view-out error unless ``model`` forces one; the camera is
    then refined like a rig (one joint refinement, never worse than the pairwise fit on left-out views).
    Prints the model choice, the RMS, the intrinsics with their standard deviations, the per-view errors
    and what makes the calibration weak; writes the calibration file ``out`` (one camera, ``cam0``) and its
    report beside it.

    Returns
    -------
    int
        0 on success (errors raise :class:`~appliance.errors.CalibrationError`).
    """
    import cv2

    from appliance.calibration.rig import calibrate_rig

    if not images:
        raise CalibrationError("calibrate camera: no images given; pass one board photo per pose")
    _check_models(model)
    check_output(out, [("a board image", Path(p)) for p in images])
    views: list[ProcamView] = []
    size: tuple[int, int] | None = None
    seen: dict[str, Path] = {}
    for p in images:
        # a regular file of sane size only: a FIFO would block, and OpenCV's own reader logs beside our line
        data = read_bytes_file(p, what="board image", error=CalibrationError, limit_bytes=MAX_IMAGE_BYTES,
                               fix="check the path")
        digest = hashlib.sha256(data).hexdigest()
        if digest in seen:  # one pose given twice would weigh twice and fake agreement
            print(f"{p}: the same image as {seen[digest]}; counted once")
            continue
        seen[digest] = Path(p)
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if img is None:
            raise CalibrationError(f"calibrate camera: image {p} is not an image OpenCV can read; check the file")
        this = (int(img.shape[1]), int(img.shape[0]))
        if size is None:
            size = this
        det = detect(img, board)
        print(f"{p}: {len(det) if det is not None else 0} of {board.n_points} board points")
        views.append(ProcamView(det, None, None))
    assert size is not None
    result = calibrate_rig({"cam0": views}, {"cam0": size}, None, camera_model=model)
    print(result.summary())
    page = write_rig_calibration(out, result, board, "Camera calibration")
    print(f"wrote {out} and report {page}")
    return 0


def calibrate_projector_cli(
    manifests: list[Path],
    board: BoardSpec,
    out: Path,
    model: str = "auto",
    projector_model: str = "auto",
) -> int:
    """``scan3d calibrate projector MANIFEST...``: cameras + projector from one manifest per board pose.

    Each manifest holds a white frame (the board is found in it) and a Gray (+ phase) sequence. The first
    camera of the manifests is the world frame; with more cameras each gets its own intrinsics and its
    pose relative to the first. Distortion models are chosen by leave-one-view-out error unless forced
    (``model`` for the cameras, ``projector_model``); all devices end in one joint refinement.

    Returns
    -------
    int
        0 on success (errors raise :class:`~appliance.errors.CalibrationError`).
    """
    from appliance.calibration.rig import calibrate_rig
    from appliance.patterns.manifest import read_manifest

    if not manifests:
        raise CalibrationError("calibrate projector: no manifests given; pass one manifest per board pose")
    _check_models(model, projector_model)
    mans = [read_manifest(p) for p in manifests]
    inputs = [("a manifest", m.path) for m in mans]
    for m in mans:
        inputs += [("a frame", f) for files in (m.images or {}).values() for f in files]
        inputs += [("a frame stack", f) for f in (m.stacks or {}).values()]
    check_output(out, inputs)
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
    result = calibrate_rig(views, sizes, proj_size, camera_model=model, projector_model=projector_model)
    print(result.summary())
    page = write_rig_calibration(out, result, board, "Camera-projector calibration")
    print(f"wrote {out} and report {page}")
    return 0


__all__ = [
    "board_from_args",
    "calibrate_camera_cli",
    "calibrate_projector_cli",
    "check_output",
]
