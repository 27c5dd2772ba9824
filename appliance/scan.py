"""One scan: sequence -> hardware -> frames -> streaming decode -> triangulation -> cloud.

:class:`Scanner` owns everything that lives across scans (frame buffers, streaming decoders, ray tables),
so a scan allocates nothing per frame. It drives devices only through the hardware protocols. From the
decoded maps on, a scan runs the replay path's code (:mod:`appliance.replay`), as an offline decode does.

With ``sequence.exposures_us`` set, a scan is a multi-exposure (HDR) capture: the projector shows its one-pass
sequence once per exposure, each camera's exposure is set before each pass, and the frames of all passes go
(in capture indices) into one :class:`~appliance.reconstruct.hdr.HdrStreamingDecoder`, which fuses them per
pixel as an offline ``scan3d decode`` of the recorded capture does.
"""

from __future__ import annotations

import asyncio
import dataclasses
import mmap
import re
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from enum import Enum
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance import replay
from appliance.calibration.health import TrendStore
from appliance.calibration.scan_health import trend_for
from appliance.config.schema import AppConfig
from appliance.errors import ApplianceError, CameraError, HardwareError, ScanError
from appliance.geometry.calibration_file import Calibration
from appliance.hardware.base import (
    Camera,
    CameraInfo,
    FrameArray,
    exposure_control,
    intensity_control,
    pulse_source,
)
from appliance.hardware.registry import Rig, build_rig
from appliance.patterns.from_config import build_capture
from appliance.patterns.from_config import build_sequence as build_sequence  # re-exported for callers
from appliance.patterns.sequence import WhiteFrame
from appliance.reconstruct.decode import DecodeParams, StreamingDecoder
from appliance.reconstruct.hdr import HdrStreamingDecoder, capture_record, capture_summary, fused_white
from appliance.reconstruct.pipeline import Reconstruction, Reconstructor, white_to_uint8
from appliance.reconstruct.types import DecodedMaps
from appliance.replay import ScanResult as ScanResult  # re-exported for callers

# Module-level so tests can shorten it: extra time allowed per frame on top of the projector timing.
FRAME_TIMEOUT_S = 5.0
FRAME_TIMEOUT_PER_FRAME_S = 0.5


def pixel_format_bits(pixel_format: str) -> int:
    """Significant bits of a GenICam mono pixel format (``Mono8`` -> 8, ``Mono12`` -> 12, ``Mono12Packed`` -> 12).

    Raises
    ------
    HardwareError
        For a format that is not ``Mono<bits>`` with 8..16 bits.
    """
    match = re.fullmatch(r"Mono(\d+)(Packed|p)?", pixel_format)
    if match is None or not 8 <= int(match.group(1)) <= 16:
        raise HardwareError(f"pixel format {pixel_format!r}: not a Mono8..Mono16 format; set the camera to MonoN")
    return int(match.group(1))


def virtual_calibration(virtual: Any) -> Calibration:
    """The exact calibration of a virtual rig (its ground-truth camera and projector models)."""
    devices = dict(virtual.cameras)
    devices["projector"] = virtual.projector
    return Calibration(devices)


class ScanPhase(Enum):
    """What a scan is doing, as :class:`Scanner` reports it to its ``on_phase`` callback."""

    CAPTURED = "captured"
    """Every camera has all its frames; the last decodes and the reconstruction follow."""
    RECONSTRUCTING = "reconstructing"
    """The decoded maps are being turned into the cloud."""


class FrameMemory:
    """A camera's frame buffer (F, H, W) in its own anonymous memory map, whose frames can be given back.

    A released frame reads as zeros until written again; its pages return to the system at once
    (``madvise(MADV_DONTNEED)``) and are mapped again, zeroed, when the camera next writes it.

    Parameters
    ----------
    shape : tuple of int
        (frames, height, width).
    dtype : numpy dtype
        uint8 or uint16.
    """

    def __init__(self, shape: tuple[int, int, int], dtype: np.dtype[Any]) -> None:
        self.frame_bytes = int(shape[1]) * int(shape[2]) * dtype.itemsize
        # private: given-back pages are freed (a shared anonymous map would keep them in shmem)
        self._map = mmap.mmap(-1, max(1, int(shape[0]) * self.frame_bytes),
                              flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)  # fmt: skip
        self.frames: FrameArray = np.frombuffer(
            self._map, dtype=dtype, count=int(np.prod(shape))
        ).reshape(shape)

    def release(self, index: int) -> None:
        """Give back the whole pages of frame ``index`` (the partial pages at its ends stay)."""
        page = mmap.PAGESIZE
        start = -(-index * self.frame_bytes // page) * page
        stop = (index + 1) * self.frame_bytes // page * page
        if stop > start:
            self._map.madvise(mmap.MADV_DONTNEED, start, stop - start)


class Scanner:
    """Runs scans on one rig with one calibration and one configuration.

    Parameters
    ----------
    cfg : AppConfig
        The configuration.
    rig : Rig
        The devices (see :func:`appliance.hardware.registry.build_rig`).
    calibration : Calibration
        Camera(s) and projector models; camera names must match ``cfg.cameras``.
    keep_frames : bool
        Keep every captured frame until the next scan (:attr:`ScanResult.frames`). False (the service): each
        frame's memory goes back to the system once the decoder is done with it, so a camera holds about the
        white frame and the frames in flight instead of its whole sequence (27 MB for 22 frames of
        1280x1024), and ``ScanResult.frames`` is empty.
    on_phase : callable, optional
        Called on the event loop with each :class:`ScanPhase` a scan enters (the service's status).

    Raises
    ------
    ScanError
        When the calibration lacks the projector or a configured camera.
    CameraError
        When ``sequence.exposures_us`` is set and a camera cannot set its exposure.
    """

    def __init__(
        self,
        cfg: AppConfig,
        rig: Rig,
        calibration: Calibration,
        *,
        keep_frames: bool = True,
        on_phase: Callable[[ScanPhase], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.rig = rig
        self.calibration = calibration
        proj = calibration.projector
        if proj is None:
            raise ScanError("calibration has no 'projector' entry; calibrate the projector (scan3d calibrate)")
        missing = [n for n in cfg.cameras if n not in calibration.devices]
        if missing:
            raise ScanError(
                f"calibration has no entry for camera(s) {missing} (it has {list(calibration.devices)}); "
                "calibrate them or rename the cameras in the configuration"
            )
        self.sequence = build_sequence(cfg.sequence, proj.width, proj.height)
        """One pass: what the projector shows (once per exposure)."""
        self.capture, self.exposures = build_capture(cfg.sequence, proj.width, proj.height)
        """Every frame of every pass in capture order, and per frame its ``(exposure_us, intensity)`` (None: one
        pass at the cameras' own exposure): what the decoder sees and a recording's manifest holds."""
        self.pass_exposures_us: tuple[float, ...] = tuple(float(e) for e in cfg.sequence.exposures_us)
        """The exposure of each pass (µs), in capture order; empty for a one-pass scan."""
        if self.pass_exposures_us:
            for name, cam in rig.cameras.items():
                if exposure_control(cam) is None:
                    raise CameraError(
                        f"camera {name!r} ({cfg.cameras[name].type}): cannot set its exposure, but "
                        f"sequence.exposures_us = {list(cfg.sequence.exposures_us)} captures one pass per "
                        "exposure; use a camera backend with exposure control (aravis, uvc, sim) or remove "
                        "sequence.exposures_us"
                    )
        levels = tuple(float(i) for i in cfg.sequence.intensities)
        self.pass_intensities: tuple[float, ...] = levels if any(i != 1.0 for i in levels) else ()
        """The projector intensity of each pass (0-1], in capture order; empty: every pass at full intensity."""
        if self.pass_intensities and intensity_control(rig.projector) is None:
            raise HardwareError(
                f"projector ({cfg.projector.type}): cannot set its intensity between passes, but "
                f"sequence.intensities = {list(cfg.sequence.intensities)} asks for it; use a projector backend "
                "with intensity control (lightcrafter4500, sim), or take every pass at full intensity (remove "
                "sequence.intensities and vary exposures_us)"
            )
        if rig.virtual is not None:  # its renderers keep projector coordinates of the coded axes only
            rig.virtual.coded_axes = frozenset(str(a) for f in self.sequence.frames if (a := getattr(f, "axis", None)))
        rc = cfg.reconstruction
        self.params = DecodeParams.from_settings(rc)
        self.reconstructor = Reconstructor(calibration, cfg.sequence.axes, rc, self.sequence)
        self._trend: TrendStore | None = None
        self._white_index = next(
            (i for i, f in enumerate(self.sequence.frames) if isinstance(f, WhiteFrame)), None
        )
        n_pass = len(self.sequence)
        # the white frame of every pass stays in memory until the scan's grey image is made
        self._kept: frozenset[int] = frozenset(
            () if self._white_index is None else (k * n_pass + self._white_index for k in range(self.n_passes))
        )
        self.keep_frames = keep_frames
        self._buffers: dict[str, FrameArray] = {}
        self._releasable: dict[str, FrameMemory] = {}
        self._unreleased: dict[str, set[int]] = {}
        self._bits: dict[str, int] = {}
        self._decoders: dict[str, StreamingDecoder | HdrStreamingDecoder] = {}
        self._executors: dict[str, ThreadPoolExecutor] = {}
        self._opened = False
        self.scans_done = 0
        self.on_phase = on_phase
        self.camera_info: dict[str, CameraInfo] = {}
        """What each camera said when it was opened (model, serial, size, pixel format)."""

    @property
    def n_passes(self) -> int:
        """Passes of the sequence a scan captures (one per configured exposure; 1 without)."""
        return max(1, len(self.pass_exposures_us))

    async def open(self) -> None:
        """Open every device, allocate the buffers (for every pass) and load the sequence into the projector."""
        n = len(self.capture)
        for name, cam in self.rig.cameras.items():
            info = await cam.open()
            self.camera_info[name] = info
            shape = (info.height, info.width)
            model = self.calibration.devices[name]
            if (model.width, model.height) != (info.width, info.height):
                raise HardwareError(
                    f"camera {name!r}: delivers {info.width}x{info.height} but is calibrated at "
                    f"{model.width}x{model.height}; set the camera's resolution or recalibrate"
                )
            bits = pixel_format_bits(info.pixel_format)
            if name not in self._buffers or self._buffers[name].shape != (n, *shape) or self._bits.get(name) != bits:
                # frame buffers and decoder state, ~100-400 MB of fresh memory: allocated off the event loop
                await asyncio.to_thread(self._allocate, name, (n, *shape), bits)
        await self.rig.projector.open()
        await self.rig.projector.load(self.sequence)
        self._opened = True

    def _allocate(self, name: str, shape: tuple[int, int, int], bits: int) -> None:
        dtype = np.uint8 if bits == 8 else np.uint16
        if self.keep_frames:
            buf: FrameArray = np.zeros(shape, dtype)  # type: ignore[assignment]
        else:
            mem = FrameMemory(shape, np.dtype(dtype))
            self._releasable[name] = mem
            buf = mem.frames
        self._unreleased[name] = set()
        self._buffers[name] = buf
        self._bits[name] = bits
        # thresholds in the camera's own scale (Mono12: 0..4095 in uint16)
        params = dataclasses.replace(self.params, max_value=float((1 << bits) - 1))
        # the frames stay in this buffer for the whole scan: the decoder keeps references, not copies
        if self.exposures is None:
            self._decoders[name] = StreamingDecoder(self.sequence, shape[1:], dtype, params, borrow_frames=True)
        else:
            self._decoders[name] = HdrStreamingDecoder(self.capture, self.exposures, (shape[1], shape[2]), dtype,
                                                       params, borrow_frames=True)  # fmt: skip
        self._executors[name] = ThreadPoolExecutor(1, thread_name_prefix=f"decode-{name}")

    async def warm_up(self) -> None:
        """Compile (or load from cache) every numba kernel a scan uses, before the first real scan.

        Runs the streaming decoders and the reconstruction once on the (blank) frame buffers, and on a
        virtual rig precomputes its geometry and renders one frame of each kind per camera.
        """
        if not self._opened:
            await self.open()
        loop = asyncio.get_running_loop()
        virtual = self.rig.virtual
        if virtual is not None:
            def warm_sim() -> None:
                virtual.prepare()
                # one frame of each kind (white, Gray, XOR Gray, phase...): each has its own shading kernel
                kinds = {(type(f), getattr(f, "xor_with", None) is not None): f for f in reversed(self.sequence.frames)}
                firsts = list(kinds.values())
                for name in self.rig.cameras:
                    if name in virtual.cameras:
                        for frame in firsts:
                            virtual.render_frame(frame, name)

            await loop.run_in_executor(None, warm_sim)

        def warm_decode(name: str) -> tuple[DecodedMaps, npt.NDArray[np.uint8], dict[str, object]]:
            dec, buf = self._decoders[name], self._buffers[name]
            dec.reset()
            for i in range(buf.shape[0]):
                self._push(name, i, buf[i])
            done = self._finish(name)
            dec.reset()
            return done

        names = list(self._decoders)
        finished = await asyncio.gather(
            *(loop.run_in_executor(self._executors[n], warm_decode, n) for n in names)
        )
        maps = {n: f[0] for n, f in zip(names, finished, strict=True)}
        white: dict[str, npt.NDArray[np.generic]] = {n: f[1] for n, f in zip(names, finished, strict=True)}
        await loop.run_in_executor(None, self.reconstructor.run, maps, white)
        await loop.run_in_executor(None, self.reconstructor.warm_up)  # the camera-camera matcher's kernels

    def _phase(self, phase: ScanPhase) -> None:
        if self.on_phase is not None:
            self.on_phase(phase)

    async def scan(self) -> ScanResult:
        """Run one scan (every exposure pass) and reconstruct it.

        Raises
        ------
        ScanError
            When a device fails or a frame is missing; the scanner stays usable for the next scan.
        """
        if not self._opened:
            await self.open()
        loop = asyncio.get_running_loop()
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        pushes: list[asyncio.Future[None]] = []

        def on_frame_factory(name: str, offset: int) -> Any:
            ex = self._executors[name]

            def on_frame(index: int, frame: FrameArray) -> None:  # camera thread
                # the camera counts the frames of its pass; the decoder those of the whole capture
                fut: Future[None] = ex.submit(self._push, name, offset + index, frame)
                loop.call_soon_threadsafe(pushes.append, asyncio.wrap_future(fut, loop=loop))

            return on_frame

        # each decoder is reset in its own thread (clearing its state is ~100 MB of writes): after any push
        # still queued there from an earlier scan, and off the event loop
        await asyncio.gather(*(loop.run_in_executor(self._executors[n], d.reset) for n, d in self._decoders.items()))
        try:
            for k in range(self.n_passes):
                if self.pass_exposures_us:
                    t_e = time.perf_counter()
                    await asyncio.gather(*(self._set_exposure(name, cam, self.pass_exposures_us[k])
                                           for name, cam in self.rig.cameras.items()))  # fmt: skip
                    timings["set_exposure_ms"] = timings.get("set_exposure_ms", 0.0) + (time.perf_counter() - t_e) * 1e3
                if self.pass_intensities:
                    await self._set_intensity(self.pass_intensities[k])
                await self._capture_pass(k, on_frame_factory, timings, t0)
            if self.pass_intensities and self.pass_intensities[-1] != 1.0:
                await self._set_intensity(1.0)  # what else the projector shows (calibration, focus) at full
            await asyncio.sleep(0)  # let the last call_soon_threadsafe callbacks run
            await asyncio.gather(*pushes)
        except (CameraError, HardwareError) as exc:
            await self._settle(pushes)
            await self._abort()
            raise ScanError(f"scan failed: {exc}") from exc
        except ApplianceError:
            await self._settle(pushes)
            await self._abort()
            raise
        except BaseException:  # cancelled (timeout, stop) or a bug: the pushes in flight still finish first
            await asyncio.shield(self._settle(pushes))
            raise
        timings["capture_ms"] = (time.perf_counter() - t0) * 1e3
        self._phase(ScanPhase.CAPTURED)
        t1 = time.perf_counter()

        def finish(name: str) -> tuple[DecodedMaps, npt.NDArray[np.uint8], dict[str, object]]:
            done = self._finish(name)
            timings[f"decode_finish_{name}_ms"] = (time.perf_counter() - t1) * 1e3
            return done

        names = list(self._decoders)
        finished = await asyncio.gather(*(loop.run_in_executor(self._executors[n], finish, n) for n in names))
        maps = {n: f[0] for n, f in zip(names, finished, strict=True)}
        white = {n: f[1] for n, f in zip(names, finished, strict=True)}
        timings["decode_finish_ms"] = (time.perf_counter() - t1) * 1e3
        self._phase(ScanPhase.RECONSTRUCTING)
        t2 = time.perf_counter()
        rec, health = await loop.run_in_executor(None, self._reconstruct, maps, white)
        timings.update(rec.timings_ms)
        timings["reconstruct_ms"] = (time.perf_counter() - t2) * 1e3
        timings["scan_ms"] = (time.perf_counter() - t0) * 1e3
        self.scans_done += 1
        shapes = {name: (int(b.shape[1]), int(b.shape[2])) for name, b in self._buffers.items()}
        frames = dict(self._buffers) if self.keep_frames else {}
        capture: dict[str, object] = {}
        if self.exposures is not None:
            per_camera = {n: f[2] for n, f in zip(names, finished, strict=True)}
            capture = capture_record(self.exposures, per_camera)
        return ScanResult(rec, maps, white, timings, shapes, dict(health), frames, capture)

    async def _set_intensity(self, intensity: float) -> None:
        control = intensity_control(self.rig.projector)
        if control is None:  # checked when the scanner was made; a rig swapped since
            raise HardwareError("projector: cannot set its intensity; remove sequence.intensities")
        await control.set_intensity(intensity)

    async def _set_exposure(self, name: str, cam: Camera, exposure_us: float) -> None:
        control = exposure_control(cam)
        if control is None:  # checked when the scanner was made; a rig swapped since
            raise CameraError(f"camera {name!r}: cannot set its exposure; remove sequence.exposures_us")
        await control.set_exposure(exposure_us)

    async def _capture_pass(self, k: int, on_frame_factory: Any, timings: dict[str, float], t0: float) -> None:
        """Pass ``k``: arm the cameras for its frames (their part of the buffers), run the projector and the
        triggers once, wait for every frame."""
        n = len(self.sequence)
        off = k * n
        for name, cam in self.rig.cameras.items():
            await cam.arm(n, self._buffers[name][off:off + n], on_frame_factory(name, off))
        await self.rig.projector.start()
        # a trigger controller emits the camera (and projector) pulses of the whole pass
        pulser = pulse_source(self.rig.trigger)
        if pulser is not None:
            pulses = await pulser.run_sequence(n)
            if len(pulses) != n:
                raise HardwareError(
                    f"trigger {self.rig.trigger.name!r}: emitted {len(pulses)} of {n} pulses; check the "
                    "controller's log (scan3d status) and its cable"
                )
        # cameras without a hardware trigger line (software-timed) are fired frame by frame
        software = [c for c in self.rig.cameras.values() if c.needs_software_trigger]
        for i in range(n if software else 0):
            await asyncio.gather(*(c.trigger(i) for c in software))
        timeout = FRAME_TIMEOUT_S + n * FRAME_TIMEOUT_PER_FRAME_S

        async def captured(name: str, cam: Any) -> None:
            await cam.wait_frames(timeout)
            timings[f"capture_{name}_ms"] = (time.perf_counter() - t0) * 1e3

        results = await asyncio.gather(
            *(captured(name, cam) for name, cam in self.rig.cameras.items()), return_exceptions=True
        )
        errors = [r for r in results if isinstance(r, BaseException)]
        if errors:
            raise errors[0]

    def _finish(self, name: str) -> tuple[DecodedMaps, npt.NDArray[np.uint8], dict[str, object]]:
        """Finish camera ``name``'s decode (in its decode thread): its maps, its grey image (0..255; per pixel
        from the pass its code came from) and, for a multi-exposure capture, what each pass gave."""
        dec, buf = self._decoders[name], self._buffers[name]
        maps = dec.finish()
        if not isinstance(dec, HdrStreamingDecoder):
            return maps, self._white_u8(buf[self._white_index] if self._white_index is not None else None, name), {}
        assert dec.choice is not None
        greys = [self._white_u8(None if self._white_index is None else buf[idx[self._white_index]], name)
                 for _light, idx in dec.passes]  # fmt: skip
        white = fused_white(maps, greys, dec.passes, dec.choice)
        assert self.exposures is not None
        return maps, white, capture_summary(self.exposures, dec.passes, dec.choice, maps.mask)

    def _push(self, name: str, index: int, frame: FrameArray) -> None:
        """Push frame ``index`` (of the whole capture) of camera ``name`` into its decoder (in its decode thread);
        without ``keep_frames``, give back the memory of every frame the decoder no longer reads (not the white
        frames, read for the grey image after the decode)."""
        dec = self._decoders[name]
        dec.push(index, frame)
        mem = self._releasable.get(name)
        if mem is None:
            return
        pending = self._unreleased[name]
        pending.add(index)
        held = dec.borrowed
        for i in [i for i in pending if i not in held and i not in self._kept]:
            mem.release(i)
            pending.discard(i)

    def _reconstruct(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.uint8]]
    ) -> tuple[Reconstruction, dict[str, object]]:
        """Reconstruct (in a worker thread), then judge the scan's residuals and record their trend."""
        if self._trend is None:
            self._trend = trend_for(self.cfg.service.state_directory, self.sequence.describe())
        return replay.reconstruct(self.reconstructor, maps, white, self._trend,
                                  self.cfg.calibration.health_tolerance_px)  # fmt: skip

    def _white_u8(self, white: FrameArray | None, name: str) -> npt.NDArray[np.uint8]:
        if white is None:
            return np.zeros(self._buffers[name].shape[1:], np.uint8)
        # the camera's significant bits, not the container's
        return white_to_uint8(white, self._bits.get(name, 16))

    @staticmethod
    async def _settle(pushes: list[asyncio.Future[None]]) -> None:
        """Wait for the frame pushes already handed to the decode threads (a failed scan ends after them)."""
        await asyncio.sleep(0)  # the last call_soon_threadsafe callbacks add their futures
        await asyncio.gather(*pushes, return_exceptions=True)

    async def _abort(self) -> None:
        try:
            await self.rig.projector.stop()
        except ApplianceError:
            pass

    async def close(self) -> None:
        """Stop the projector, close every device and the decode threads."""
        for cam in self.rig.cameras.values():
            await cam.close()
        await self.rig.projector.stop()
        await self.rig.projector.close()
        executors = list(self._executors.values())
        self._executors.clear()
        if executors:  # waits for the decode threads: not on the event loop

            def shutdown() -> None:
                for ex in executors:
                    ex.shutdown(wait=True)

            await asyncio.get_running_loop().run_in_executor(None, shutdown)
        self._opened = False


async def scan_once(cfg: AppConfig, rig: Rig | None = None) -> tuple[ScanResult, Scanner]:
    """One scan on the configured rig (or ``rig``) with its calibration, then close (tests, the bench).

    Returns the result and the (closed) scanner, for its sequence and parameters; ``scanner.rig.virtual`` is
    the virtual rig's ground truth when the rig is simulated.
    """
    def prepare(rig: Rig | None) -> Scanner:  # renders the virtual rig, builds ray tables: not on the loop
        rig = rig if rig is not None else build_rig(cfg)
        return Scanner(cfg, rig, load_calibration_for(cfg, rig))

    scanner = await asyncio.to_thread(prepare, rig)
    try:
        return await scanner.scan(), scanner
    finally:
        await scanner.close()


def load_calibration_for(cfg: AppConfig, rig: Rig) -> Calibration:
    """The configured calibration file, or the virtual rig's exact calibration when none is set."""
    from appliance.geometry.calibration_file import read_calibration

    if cfg.calibration_file is not None:
        return read_calibration(cfg.calibration_file)
    if rig.virtual is None:
        raise ScanError("no calibration_file configured and no virtual rig; set calibration_file")
    return virtual_calibration(rig.virtual)
