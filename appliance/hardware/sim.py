"""The ``sim`` backends: cameras, projector and button of the virtual rig.

The projector "shows" frame ``i`` by telling every armed camera; each camera renders what it would see
(:class:`~appliance.sim.rig.VirtualRig`) in its own thread, writes it into the scan's preallocated buffer
and reports it through the frame callback, like a real camera's acquisition thread does.
"""

from __future__ import annotations

import asyncio
import queue
import threading
import time
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.config.backends import SimCameraConfig, SimTriggerConfig
from appliance.errors import CameraError, ProjectorError
from appliance.hardware.base import ButtonOnly, CameraInfo, FrameCallback, TriggerEvent
from appliance.patterns.sequence import Sequence
from appliance.sim.rig import VirtualRig

# Module-level so tests can shorten them.
FRAME_POLL_S = 0.05


class SimWorld:
    """What the simulated devices share: the rig, the sequence on the projector, the armed cameras."""

    def __init__(self, rig: VirtualRig) -> None:
        self.rig = rig
        self.sequence: Sequence | None = None
        self.intensity: float | None = None
        """Projector intensity 0..1 of the frames shown now (None: ``imaging.projector_intensity``)."""
        self._cameras: list[SimCamera] = []
        self._lock = threading.Lock()

    def attach(self, cam: SimCamera) -> None:
        with self._lock:
            if cam not in self._cameras:
                self._cameras.append(cam)

    def detach(self, cam: SimCamera) -> None:
        with self._lock:
            if cam in self._cameras:
                self._cameras.remove(cam)

    def show(self, index: int) -> None:
        """The projector shows frame ``index``: every armed camera exposes once."""
        with self._lock:
            cams = list(self._cameras)
        for cam in cams:
            cam.expose(index)


class SimCamera:
    """A virtual-rig camera: renders each triggered frame in its own acquisition thread.

    The simulated projector exposes it frame by frame (:meth:`SimWorld.show`), like a hardware trigger line;
    :meth:`trigger` exposes a frame by software.
    """

    needs_software_trigger = False

    def __init__(self, name: str, cfg: SimCameraConfig, world: SimWorld) -> None:
        self.name = name
        self.cfg = cfg
        self.world = world
        self._queue: queue.Queue[int | tuple[str, float] | None] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._out: npt.NDArray[Any] | None = None
        self._on_frame: FrameCallback | None = None
        self._n = 0
        self._received = 0
        self._done = threading.Event()
        self._error: str | None = None
        self._rng = np.random.default_rng(world.rig.cfg.imaging.seed)
        self.frames_delivered = 0
        self.exposure_us: float | None = None
        """Exposure of the next frames (µs; None: ``virtual_rig.imaging.exposure_us``)."""

    async def open(self) -> CameraInfo:
        if self.name not in self.world.rig.cameras:
            raise CameraError(f"camera {self.name!r} (sim): not in virtual_rig.cameras; add its optics there")
        model = self.world.rig.cameras[self.name]
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"sim-camera-{self.name}", daemon=True)
            self._thread.start()
        bits = self.world.rig.cfg.imaging.bit_depth
        return CameraInfo(self.name, "sim", "virtual rig camera", f"SIM-{self.name}", model.width,
                          model.height, "Mono8" if bits == 8 else f"Mono{bits}")

    async def arm(self, n_frames: int, out: npt.NDArray[Any], on_frame: FrameCallback | None = None) -> None:
        model = self.world.rig.cameras[self.name]
        if out.shape[0] < n_frames or out.shape[1:] != (model.height, model.width):
            raise CameraError(
                f"camera {self.name!r} (sim): buffer of shape {out.shape} cannot hold {n_frames} frames of "
                f"{model.width}x{model.height}"
            )
        self._out, self._on_frame, self._n = out, on_frame, n_frames
        self._received = 0
        self._error = None
        self._done.clear()
        self.world.attach(self)

    async def set_exposure(self, exposure_us: float) -> None:
        """Expose the following frames for ``exposure_us`` (µs), e.g. between the passes of an HDR scan.

        Frames already triggered keep the exposure they were triggered with.
        """
        self.world.rig.light_scale(exposure_us)  # a bad value is refused here, not in the render thread
        self._queue.put(("exposure", float(exposure_us)))

    def expose(self, index: int) -> None:
        """Expose frame ``index`` (any thread): queued for the acquisition thread."""
        self._queue.put(index)

    async def trigger(self, index: int) -> None:
        self.expose(index)

    def _run(self) -> None:
        while True:
            index = self._queue.get()
            if index is None:
                return
            if isinstance(index, tuple):  # a setting, in order with the triggers
                self.exposure_us = index[1]
                continue
            out, seq = self._out, self.world.sequence
            if out is None or seq is None or index >= self._n:
                continue
            limit = self.cfg.fail_after_frames
            if limit is not None and self._received >= limit:
                continue  # a dead camera: the trigger is lost
            if self.cfg.frame_delay_ms:
                time.sleep(self.cfg.frame_delay_ms / 1000)
            try:
                self.world.rig.render_frame(seq.frames[index], self.name, out=out[index], rng=self._rng,
                                            exposure_us=self.exposure_us, intensity=self.world.intensity)
            except Exception as exc:  # a render failure is a camera failure for the scan
                self._error = f"render of frame {index} failed: {exc}"
                self._done.set()
                continue
            self._received += 1
            self.frames_delivered += 1
            if self._on_frame is not None:
                self._on_frame(index, out[index])
            if self._received >= self._n:
                self._done.set()

    async def wait_frames(self, timeout_s: float) -> None:
        loop = asyncio.get_running_loop()
        ok = await loop.run_in_executor(None, self._done.wait, timeout_s)
        self.world.detach(self)
        if self._error is not None:
            raise CameraError(f"camera {self.name!r} (sim): {self._error}")
        if not ok:
            raise CameraError(
                f"camera {self.name!r} (sim): only {self._received} of {self._n} frames arrived within "
                f"{timeout_s:.1f} s; the next missing is frame {self._received} (check the camera/trigger)"
            )

    async def close(self) -> None:
        self.world.detach(self)
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=5)
            self._thread = None


class SimProjector:
    """The virtual rig's projector: steps through the loaded sequence on its own clock."""

    def __init__(self, world: SimWorld, period_s: float = 0.0) -> None:
        self.name = "projector"
        self.world = world
        self.period_s = period_s
        self._sequence: Sequence | None = None

    async def open(self) -> None:
        return None

    async def load(self, sequence: Sequence) -> None:
        proj = self.world.rig.projector
        if (sequence.width, sequence.height) != (proj.width, proj.height):
            raise ProjectorError(
                f"projector (sim): sequence is {sequence.width}x{sequence.height} but the projector is "
                f"{proj.width}x{proj.height}; generate the sequence for the projector's size"
            )
        self._sequence = sequence
        self.world.sequence = sequence

    async def start(self) -> None:
        if self._sequence is None:
            raise ProjectorError("projector (sim): start() before load(); load a sequence first")
        for i in range(len(self._sequence)):
            self.world.show(i)
            if self.period_s:
                await asyncio.sleep(self.period_s)

    async def set_intensity(self, intensity: float) -> None:
        """Show the following frames at projector intensity ``intensity`` (0..1], e.g. per HDR pass."""
        self.world.rig.light_scale(None, intensity)
        self.world.intensity = float(intensity)

    async def stop(self) -> None:
        return None

    async def close(self) -> None:
        return None


class SimTrigger(ButtonOnly):
    """A simulated button, pressed with :meth:`press` (control socket, tests) or Enter on stdin."""

    def __init__(self, cfg: SimTriggerConfig) -> None:
        self.name = "sim-button"
        self.cfg = cfg
        self._events: asyncio.Queue[TriggerEvent] | None = None

    def _queue(self) -> asyncio.Queue[TriggerEvent]:
        if self._events is None:
            self._events = asyncio.Queue()
        return self._events

    async def open(self) -> None:
        self._queue()

    def press(self, detail: str = "") -> None:
        """Press the button (call from the event loop's thread)."""
        self._queue().put_nowait(TriggerEvent("sim-button", time.monotonic_ns(), detail))

    async def next_event(self) -> TriggerEvent:
        return await self._queue().get()

    async def close(self) -> None:
        return None
