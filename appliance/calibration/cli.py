"""The ``scan3d calibrate`` commands: read inputs, calibrate, print, write the file and its report."""

from __future__ import annotations

import argparse
import asyncio
import sys
import threading
from pathlib import Path
from typing import Any, TextIO

from appliance.calibration.boards import BoardSpec, detect
from appliance.calibration.boards import board_from_args as _board_from_values
from appliance.calibration.intrinsics import calibrate_camera
from appliance.calibration.projector import ProcamView, procam_view
from appliance.calibration.report import write_report
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
    from appliance.calibration.live import write_rig_calibration
    from appliance.calibration.rig import calibrate_rig

    result = calibrate_rig(views, sizes, proj_size)
    print(result.summary())
    page = write_rig_calibration(out, result, board, "Camera-projector calibration")
    print(f"wrote {out} and report {page}")
    return 0


def calibrate_live_cli(
    config: Path | None,
    poses: int | None = None,
    out: Path | None = None,
    stdin: TextIO | None = None,
) -> int:
    """``scan3d calibrate --live``: capture board poses on the configured rig, calibrate, write the file.

    Interactive (``poses`` None): each button press or Enter captures a pose and prints what was detected
    and how the coverage of every device grows, until there are enough poses; ``c`` + Enter calibrates,
    ``q`` + Enter quits. With ``poses`` N it captures N poses without asking (tests, scripted runs). On a
    virtual rig the board moves to the next preset pose before each capture.

    Parameters
    ----------
    config : Path or None
        Configuration file (None: the built-in virtual-rig defaults).
    poses : int, optional
        Non-interactive: number of poses to capture.
    out : Path, optional
        Calibration file to write (default: ``calibration_file`` of the configuration, else
        ``calibration.yaml``); the report goes beside it.
    stdin : text stream, optional
        Where Enter presses are read (default ``sys.stdin``).

    Returns
    -------
    int
        0 when a calibration was written, 1 when the operator quit.
    """
    from appliance.config.loader import load_config
    from appliance.config.schema import AppConfig

    cfg = load_config(config) if config is not None else AppConfig()
    target = out or cfg.calibration_file or Path("calibration.yaml")
    if poses is not None and poses < 3:
        raise CalibrationError(f"calibrate --live --poses {poses}: need >= 3 poses (better >= 10)")
    return asyncio.run(_live(cfg, poses, target, stdin if stdin is not None else sys.stdin))


def _stdin_lines(stream: TextIO, loop: asyncio.AbstractEventLoop) -> asyncio.Queue[str | None]:
    """Lines of ``stream`` as an asyncio queue (a daemon thread reads; None at end of input)."""
    queue: asyncio.Queue[str | None] = asyncio.Queue()

    def pump() -> None:
        for line in stream:
            loop.call_soon_threadsafe(queue.put_nowait, line.strip())
        loop.call_soon_threadsafe(queue.put_nowait, None)

    threading.Thread(target=pump, name="calibrate-stdin", daemon=True).start()
    return queue


async def _next_command(lines: asyncio.Queue[str | None], trigger: Any) -> str | None:
    """The next Enter line (``''`` for a plain Enter) or ``''`` for a button press; None at end of input."""
    get_line = asyncio.ensure_future(lines.get())
    get_press = asyncio.ensure_future(trigger.next_event())
    done, pending = await asyncio.wait({get_line, get_press}, return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
    if get_line in done:
        return get_line.result()
    return ""


async def _live(cfg: Any, poses: int | None, out: Path, stdin: TextIO) -> int:
    from appliance.calibration.live import LiveCalibration, write_rig_calibration
    from appliance.hardware.registry import build_rig

    rig = build_rig(cfg)
    session = LiveCalibration(cfg, rig, poses_hint=poses or cfg.calibration.poses_wanted)
    loop = asyncio.get_running_loop()
    await session.open()
    n_points = session.board.n_points
    print(
        f"calibrate --live: board {session.board.describe()}; {len(rig.cameras)} camera(s), projector "
        f"{session.projector_size[0]}x{session.projector_size[1]}, "
        f"{len(session.sequence or ())} frames per pose"
    )
    try:
        if poses is not None:
            for _ in range(poses):
                cap = await session.capture()
                print(cap.line(n_points))
                print(session.progress())
        else:
            print("move the board, then press the button or Enter to capture a pose; "
                  "'c' + Enter calibrates, 'q' + Enter quits")  # fmt: skip
            lines = _stdin_lines(stdin, loop)
            while True:
                cmd = await _next_command(lines, rig.trigger)
                if cmd is None or cmd.lower() in ("c", "calibrate", "done"):
                    if session.good_poses() >= 3:
                        break
                    if cmd is None:
                        print("end of input with fewer than 3 usable poses: nothing calibrated")
                        return 1
                    print(f"only {session.good_poses()} usable poses: capture at least 3 (better "
                          f"{cfg.calibration.poses_wanted})")  # fmt: skip
                    continue
                if cmd.lower() in ("q", "quit"):
                    print("quit: nothing calibrated")
                    return 1
                cap = await session.capture()
                print(cap.line(n_points))
                print(session.progress())
        if session.good_poses() < 3:
            raise CalibrationError(
                f"calibrate --live: the board was found with projector coordinates in only "
                f"{session.good_poses()} of {len(session.captures)} poses; need >= 3 (check the board "
                "settings "
                "in calibration.board, focus and exposure)"
            )
        result = await loop.run_in_executor(None, session.calibrate)
    finally:
        await session.close()
    print(result.summary())
    page = await loop.run_in_executor(
        None, write_rig_calibration, out, result, session.board, "Live calibration"
    )
    print(f"wrote {out} and report {page}")
    return 0


__all__ = [
    "board_from_args",
    "calibrate_camera_cli",
    "calibrate_live_cli",
    "calibrate_projector_cli",
]
