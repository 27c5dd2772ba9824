"""Live calibration on the configured rig: capture board poses, guide the person, calibrate, write the file.

Each capture projects a white frame and a Gray + phase sequence on both projector axes and grabs every
camera through the hardware protocols (as a scan does). The board is found in the white frame and its
corners' projector coordinates come from the decoding (:func:`~appliance.calibration.projector.procam_view`).
On a virtual rig the board is moved to the next of the preset poses before each capture
(:class:`~appliance.calibration.virtual.VirtualBoard`); on real hardware the operator moves it, guided after
each capture by where the board is still missing in each device's image
(:func:`~appliance.calibration.advice.next_pose_hint`).
"""

from __future__ import annotations

import asyncio
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np
import numpy.typing as npt

from appliance.calibration.advice import next_pose_hint
from appliance.calibration.boards import BoardSpec
from appliance.calibration.intrinsics import coverage_map
from appliance.calibration.projector import ProcamView, procam_view
from appliance.calibration.report import write_rig_calibration
from appliance.calibration.rig import RigCalibration, calibrate_rig
from appliance.config.schema import AppConfig, SequenceConfig
from appliance.errors import CalibrationError, CameraError, HardwareError
from appliance.geometry.calibration_file import PROJECTOR_NAME
from appliance.hardware.base import FrameArray
from appliance.hardware.registry import Rig
from appliance.patterns.sequence import Sequence, gray_phase_sequence

if TYPE_CHECKING:
    from appliance.calibration.virtual import VirtualBoard

F64 = npt.NDArray[np.float64]

CAPTURE_TIMEOUT_S = 10.0
"""Extra time allowed for one capture on top of 0.25 s per frame (module level so tests can change it)."""


def calibration_sequence(cfg: SequenceConfig, width: int, height: int) -> Sequence:
    """White, black, then Gray + phase on both projector axes (the configured periods and steps)."""
    return gray_phase_sequence(
        width, height, "xy", periods=cfg.periods_px, steps=cfg.steps, inverses=cfg.inverses
    )


@dataclass
class PoseCapture:
    """What one capture found.

    Attributes
    ----------
    index : int
        Capture number (0-based).
    views : dict of str to ProcamView
        Per camera: the board and its projector coordinates.
    """

    index: int
    views: dict[str, ProcamView]

    def line(self, n_points: int) -> str:
        """One line: board points per camera and projector points."""
        parts = []
        for name, v in self.views.items():
            nc = len(v.camera) if v.camera is not None else 0
            npj = len(v.projector) if v.projector is not None else 0
            parts.append(f"{name} {nc}/{n_points} board points, {npj} with a projector coordinate")
        return f"pose {self.index + 1}: " + "; ".join(parts)


@dataclass
class LiveCalibration:
    """A live calibration session on an opened rig.

    Parameters
    ----------
    cfg : AppConfig
        Configuration (``calibration`` section: board, poses wanted, coverage target, models).
    rig : Rig
        The devices (see :func:`appliance.hardware.registry.build_rig`).
    poses_hint : int
        On a virtual rig: number of preset board poses to cycle through.
    save_frames : Path, optional
        Folder where each capture's white frame is kept per camera (``pose_NN_<camera>.png``), e.g. to
        calibrate a camera again offline with ``scan3d calibrate camera``.
    """

    cfg: AppConfig
    rig: Rig
    poses_hint: int = 15
    save_frames: Path | None = None
    captures: list[PoseCapture] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.board = BoardSpec.from_config(self.cfg.calibration.board)
        self._virtual_board: VirtualBoard | None = None
        self._buffers: dict[str, FrameArray] = {}
        self._sizes: dict[str, tuple[int, int]] = {}
        self.sequence: Sequence | None = None

    async def open(self) -> None:
        """Open the devices, load the calibration sequence, allocate the frame buffers."""
        if self.rig.virtual is not None:
            from appliance.calibration.virtual import VirtualBoard

            # board poses and renderings, sequences and buffers are computed in threads, not on the loop
            self._virtual_board = await asyncio.to_thread(
                VirtualBoard, self.rig.virtual, self.board, max(self.poses_hint, 1)
            )
        proj_size = await self._projector_size()
        self.sequence = await asyncio.to_thread(calibration_sequence, self.cfg.sequence, *proj_size)
        n = len(self.sequence)
        for name, cam in self.rig.cameras.items():
            info = await cam.open()
            self._sizes[name] = (info.width, info.height)
            dtype = np.uint8 if info.pixel_format == "Mono8" else np.uint16
            self._buffers[name] = await asyncio.to_thread(np.zeros, (n, info.height, info.width), dtype)
        await self.rig.projector.open()
        await self.rig.projector.load(self.sequence)
        await self.rig.trigger.open()

    async def _projector_size(self) -> tuple[int, int]:
        if self.rig.virtual is not None:
            p = self.rig.virtual.projector
            return int(p.width), int(p.height)
        w, h = getattr(self.rig.projector, "width", None), getattr(self.rig.projector, "height", None)
        if isinstance(w, int) and isinstance(h, int):
            return w, h
        if self.cfg.calibration_file is not None and self.cfg.calibration_file.exists():
            from appliance.geometry.calibration_file import read_calibration

            proj = read_calibration(self.cfg.calibration_file).projector
            if proj is not None:
                return proj.width, proj.height
        raise CalibrationError(
            f"calibrate --live: the projector ({self.cfg.projector.type}) does not report its resolution and "
            "calibration_file holds no projector; write a first calibration with 'scan3d calibrate projector'"
        )

    @property
    def projector_size(self) -> tuple[int, int]:
        """(width, height) of the projector (px)."""
        assert self.sequence is not None
        return (self.sequence.width, self.sequence.height)

    async def capture(self) -> PoseCapture:
        """Capture one board pose on every camera and find the board and its projector coordinates.

        Raises
        ------
        CalibrationError
            When a camera delivers too few frames.
        """
        if self.sequence is None:
            await self.open()
        seq = self.sequence
        assert seq is not None
        loop = asyncio.get_running_loop()
        if self._virtual_board is not None:
            await loop.run_in_executor(None, self._virtual_board.advance)
        n = len(seq)
        try:
            for name, cam in self.rig.cameras.items():
                await cam.arm(n, self._buffers[name])
            await self.rig.projector.start()
            await asyncio.gather(
                *(c.wait_frames(CAPTURE_TIMEOUT_S + 0.25 * n) for c in self.rig.cameras.values())
            )
        except (CameraError, HardwareError) as exc:
            await self.rig.projector.stop()
            raise CalibrationError(
                f"calibrate --live: capture of pose {len(self.captures) + 1} failed: {exc}"
            ) from exc
        board = self.board
        views = {}
        for name, buf in self._buffers.items():
            views[name] = await loop.run_in_executor(None, procam_view, buf, seq, board)
            if self.save_frames is not None:
                await loop.run_in_executor(None, self._save_white, name, buf)
        cap = PoseCapture(len(self.captures), views)
        self.captures.append(cap)
        return cap

    def _save_white(self, camera: str, frames: FrameArray) -> None:
        import cv2

        from appliance.calibration.projector import white_frame_index

        assert self.save_frames is not None and self.sequence is not None
        path = self.save_frames / f"pose_{len(self.captures):02d}_{camera}.png"
        try:
            self.save_frames.mkdir(parents=True, exist_ok=True)
            ok = cv2.imwrite(str(path), frames[white_frame_index(self.sequence)])
        except OSError as exc:
            raise CalibrationError(f"calibrate --live: cannot write {path} ({exc.strerror}); check the folder") from exc
        if not ok:
            raise CalibrationError(f"calibrate --live: cannot write {path}; check the folder (--save-frames)")

    def _detections(self) -> tuple[dict[str, list[F64]], list[F64]]:
        """Board corners found so far: per camera (image px), and all projector views together."""
        cam_pts: dict[str, list[F64]] = {name: [] for name in self._sizes}
        proj_pts: list[F64] = []
        for c in self.captures:
            for name in self._sizes:
                cam, proj = c.views[name].camera, c.views[name].projector
                if cam is not None:
                    cam_pts[name].append(cam.image_points)
                if proj is not None:
                    proj_pts.append(proj.image_points)
        return cam_pts, proj_pts

    def coverage(self) -> dict[str, float]:
        """Share of each device's image the board has covered so far (cameras and the projector)."""
        out: dict[str, float] = {}
        cam_pts, proj_pts = self._detections()
        for name, size in self._sizes.items():
            pts = cam_pts[name]
            out[name] = float(np.mean(coverage_map(pts, size) > 0)) if pts else 0.0
        out[PROJECTOR_NAME] = (
            float(np.mean(coverage_map(proj_pts, self.projector_size) > 0)) if proj_pts else 0.0
        )
        return out

    def good_poses(self) -> int:
        """Poses in which the reference camera found the board with projector coordinates."""
        ref = next(iter(self._sizes))
        return sum(
            1 for c in self.captures if c.views[ref].camera is not None and c.views[ref].projector is not None
        )

    def enough(self) -> bool:
        """True when the wanted number of poses is reached and every camera's coverage is on target.

        The projector's coverage is shown but not required: its field is usually wider than the cameras'
        view, so the board cannot reach its corners.
        """
        cc = self.cfg.calibration
        cams = [f for n, f in self.coverage().items() if n != PROJECTOR_NAME]
        return self.good_poses() >= cc.poses_wanted and min(cams) >= cc.coverage_target

    def hints(self) -> list[str]:
        """Per camera (then the projector): where to put the board next; empty when all is covered."""
        out: list[str] = []
        cam_pts, proj_pts = self._detections()
        for name, size in self._sizes.items():
            hint = next_pose_hint(cam_pts[name], size, name)
            if hint is not None:
                out.append(hint)
        if not out and proj_pts:
            hint = next_pose_hint(proj_pts, self.projector_size, PROJECTOR_NAME)
            if hint is not None:
                out.append(hint + " (if the cameras can see it there)")
        return out

    def progress(self) -> str:
        """Coverage per device, what is still missing and where to put the board next."""
        cc = self.cfg.calibration
        cov = ", ".join(f"{n} {100 * f:.0f} %" for n, f in self.coverage().items())
        line = f"  coverage: {cov} (camera target {100 * cc.coverage_target:.0f} %); " \
               f"{self.good_poses()} of " \
               f"{cc.poses_wanted} poses wanted"  # fmt: skip
        if self.enough():
            line += "\n  enough poses and coverage: calibrate now (or add poses where coverage is thin)"
        for hint in self.hints():
            line += "\n  " + hint
        return line

    def calibrate(self) -> RigCalibration:
        """Calibrate every device from the captured poses (pairwise start + joint refinement)."""
        names = list(self._sizes)
        views = {n: [c.views[n] for c in self.captures] for n in names}
        cc = self.cfg.calibration
        return calibrate_rig(views, self._sizes, self.projector_size, camera_model=cc.camera_model,
                             projector_model=cc.projector_model)  # fmt: skip

    async def close(self) -> None:
        """Stop the projector and close the devices."""
        for cam in self.rig.cameras.values():
            await cam.close()
        await self.rig.projector.stop()
        await self.rig.projector.close()
        await self.rig.trigger.close()


def _stdin_lines(stream: TextIO, loop: asyncio.AbstractEventLoop) -> asyncio.Queue[str | None]:
    """Lines of ``stream`` as an asyncio queue (a daemon thread reads; None at end of input)."""
    queue: asyncio.Queue[str | None] = asyncio.Queue()

    def pump() -> None:
        try:
            for line in stream:
                loop.call_soon_threadsafe(queue.put_nowait, line.strip())
            loop.call_soon_threadsafe(queue.put_nowait, None)
        except RuntimeError:  # the session ended (event loop closed) before the input did
            return

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


async def calibrate_live(
    config: Path | None,
    poses: int | None = None,
    out: Path | None = None,
    stdin: TextIO | None = None,
    save_frames: Path | None = None,
) -> int:
    """``scan3d calibrate --live``: capture board poses on the configured rig, calibrate, write the file.

    Interactive (``poses`` None): each button press or Enter captures a pose and prints what was detected,
    how the coverage of every device grows and where to put the board next, until there are enough poses;
    ``c`` + Enter calibrates, ``q`` + Enter quits. With ``poses`` N it captures N poses without asking
    (tests, scripted runs). On a virtual rig the board moves to the next preset pose before each capture.

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
    save_frames : Path, optional
        Keep each pose's white frame per camera there (see :class:`LiveCalibration`).

    Returns
    -------
    int
        0 when a calibration was written, 1 when the operator quit.
    """
    from appliance.config.loader import load_config

    cfg = await asyncio.to_thread(load_config, config) if config is not None else AppConfig()
    target = out or cfg.calibration_file or Path("calibration.yaml")
    if poses is not None and poses < 3:
        raise CalibrationError(f"calibrate --live --poses {poses}: need >= 3 poses (better >= 10)")
    return await _live(cfg, poses, target, stdin if stdin is not None else sys.stdin, save_frames)


async def _live(cfg: AppConfig, poses: int | None, out: Path, stdin: TextIO, save_frames: Path | None) -> int:
    from appliance.hardware.registry import build_rig

    rig = await asyncio.to_thread(build_rig, cfg)  # the virtual rig renders its scene: not on the loop
    session = LiveCalibration(cfg, rig, poses_hint=poses or cfg.calibration.poses_wanted, save_frames=save_frames)
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
                print(await asyncio.to_thread(session.progress))  # coverage maps: not on the loop
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
                print(await asyncio.to_thread(session.progress))  # coverage maps: not on the loop
        if session.good_poses() < 3:
            raise CalibrationError(
                f"calibrate --live: the board was found with projector coordinates in only "
                f"{session.good_poses()} of {len(session.captures)} poses; need >= 3 (check the board "
                "settings in calibration.board, focus and exposure)"
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
