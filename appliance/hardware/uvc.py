"""The ``uvc`` camera backend: a V4L2 webcam through OpenCV, with software-timed capture.

A webcam has no trigger input, so the scan paces it: for each frame it shows the pattern, then calls
:meth:`UvcCamera.trigger`, which waits ``settle_ms`` (the projector and the camera's exposure catch up),
drops ``flush_frames`` frames (V4L2 keeps old frames queued: when its buffers are full the driver stops
capturing, so the queue holds frames from *before* the pattern change) and grabs the next one into the
scan's buffer, converted to 8-bit gray. All device calls happen in one worker thread.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from appliance.config.backends import UvcCameraConfig
from appliance.errors import BackendUnavailableError, CameraError
from appliance.hardware.base import CameraInfo, FrameCallback

T = TypeVar("T")


class CaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` this backend uses."""

    def isOpened(self) -> bool: ...
    def set(self, prop: int, value: float) -> bool: ...
    def grab(self) -> bool: ...
    def read(self) -> tuple[bool, Any]: ...
    def release(self) -> None: ...


def _open_capture(device: str) -> CaptureLike:
    try:
        import cv2
    except ImportError as exc:
        raise BackendUnavailableError(
            f"backend 'uvc' is unavailable ({exc}); install it with: pip install opencv-python-headless"
        ) from exc
    source: int | str = int(device) if device.isdigit() else device
    cap: CaptureLike = cv2.VideoCapture(source, cv2.CAP_V4L2)
    return cap


# OpenCV property ids (cv2.CAP_PROP_*), so a fake capture needs no OpenCV.
_PROP_FRAME_WIDTH, _PROP_FRAME_HEIGHT, _PROP_BUFFERSIZE = 3, 4, 38
_PROP_AUTO_EXPOSURE, _PROP_EXPOSURE = 21, 15
_V4L2_MANUAL_EXPOSURE = 1.0
_V4L2_EXPOSURE_UNIT_US = 100.0  # V4L2's exposure_time_absolute counts 100 µs units


class UvcCamera:
    """A V4L2 webcam (implements :class:`~appliance.hardware.base.Camera`, software-timed).

    Parameters
    ----------
    name : str
        The camera's name in the configuration.
    config : UvcCameraConfig
        Device, requested size (px), exposure, settle time (ms), frames to flush.
    capture_factory : callable, optional
        ``factory(device) -> capture`` (default: ``cv2.VideoCapture`` on V4L2); tests pass a fake.
    sleep : callable, optional
        ``sleep(seconds)`` used for the settle wait (tests pass a virtual clock's).
    """

    backend = "uvc"
    needs_software_trigger = True

    def __init__(
        self,
        name: str,
        config: UvcCameraConfig,
        *,
        capture_factory: Callable[[str], CaptureLike] | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.name = name
        self.config = config
        self._factory = capture_factory or _open_capture
        self._sleep = sleep
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._cap: CaptureLike | None = None
        self.info: CameraInfo | None = None
        self._out: npt.NDArray[np.uint8] | None = None
        self._on_frame: FrameCallback | None = None
        self._n = 0
        self._done: set[int] = set()
        self._error: CameraError | None = None
        self._all = threading.Event()
        self._exposure: float | None = config.exposure  # device units; set_exposure() changes it

    def _msg(self, text: str) -> str:
        return f"camera {self.name!r} (uvc, {self.config.device}): {text}"

    async def _run(self, fn: Callable[..., T], *args: Any) -> T:
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"uvc-{self.name}")
        return await asyncio.wrap_future(self._executor.submit(fn, *args))

    async def open(self) -> CameraInfo:
        """Open the device, request the size and exposure, and read one frame to learn the real size."""
        return await self._run(self._open)

    def _open(self) -> CameraInfo:
        if self._cap is not None and self.info is not None:
            return self.info
        cfg = self.config
        cap = self._factory(cfg.device)
        if not cap.isOpened():
            raise CameraError(
                self._msg(
                    "cannot be opened; check the device path, permissions (group video) "
                    "and that no other program uses it"
                )
            )
        cap.set(_PROP_FRAME_WIDTH, cfg.width)
        cap.set(_PROP_FRAME_HEIGHT, cfg.height)
        cap.set(_PROP_BUFFERSIZE, 1)
        if self._exposure is not None:
            cap.set(_PROP_AUTO_EXPOSURE, _V4L2_MANUAL_EXPOSURE)
            cap.set(_PROP_EXPOSURE, self._exposure)
        ok, frame = cap.read()
        if not ok or frame is None:
            cap.release()
            raise CameraError(
                self._msg("opened but delivers no frames; check the cable and the USB bandwidth")
            )
        if np.asarray(frame).ndim == 3:
            import cv2  # noqa: F401  (imported here, not on the first grab: the import can take seconds)
        self._cap = cap
        height, width = np.asarray(frame).shape[:2]
        self.info = CameraInfo(self.name, "uvc", "V4L2 webcam", cfg.device, width, height, "Mono8")
        return self.info

    async def arm(self, n_frames: int, out: npt.NDArray[Any], on_frame: FrameCallback | None = None) -> None:
        """Prepare to capture ``n_frames`` frames into ``out`` (shape (n_frames, H, W), uint8)."""
        info = await self.open()
        if (
            out.dtype != np.uint8
            or out.ndim != 3
            or out.shape[0] < n_frames
            or out.shape[1:] != (info.height, info.width)
        ):
            raise CameraError(
                self._msg(
                    f"buffer of shape {out.shape} {out.dtype} cannot hold {n_frames} frames of "
                    f"{info.width}x{info.height} Mono8; allocate (n, {info.height}, {info.width}) uint8"
                )
            )
        self._out, self._on_frame, self._n = out, on_frame, n_frames
        self._done = set()
        self._error = None
        self._all.clear()

    async def set_exposure(self, exposure_us: float) -> None:
        """Switch to manual exposure of ``exposure_us`` (µs; V4L2 ``exposure_time_absolute`` in 100 µs units)
        for the following frames, e.g. between the passes of an HDR scan; the next ``settle_ms`` lets it apply.

        Raises
        ------
        CameraError
            When the driver refuses manual exposure or the value (a webcam without exposure control).
        """
        await self._run(self._set_exposure, float(exposure_us))

    def _set_exposure(self, exposure_us: float) -> None:
        self._open()
        cap = self._cap
        assert cap is not None
        units = max(1.0, round(exposure_us / _V4L2_EXPOSURE_UNIT_US))
        if not (cap.set(_PROP_AUTO_EXPOSURE, _V4L2_MANUAL_EXPOSURE) and cap.set(_PROP_EXPOSURE, units)):
            raise CameraError(self._msg(
                f"exposure {exposure_us:g} µs (V4L2 exposure_time_absolute {units:g}) was refused: the "
                "driver offers no manual exposure control; use a camera that has one, or empty "
                "sequence.exposures_us"))  # fmt: skip
        self._exposure = units

    async def trigger(self, index: int) -> None:
        """Capture frame ``index`` now: the scan has just shown its pattern.

        Waits ``settle_ms``, drops ``flush_frames`` queued frames, grabs one into ``out[index]``.

        Raises
        ------
        CameraError
            When no acquisition is armed, ``index`` is out of range, or the grab fails or takes longer
            than ``frame_timeout_ms``.
        """
        if self._out is None or not 0 <= index < self._n:
            raise CameraError(self._msg(f"trigger({index}) without an armed acquisition of that many frames"))
        try:
            await asyncio.wait_for(
                self._run(self._capture, index),
                self.config.frame_timeout_ms / 1000 + self.config.settle_ms / 1000,
            )
        except TimeoutError:
            self._fail(
                CameraError(
                    self._msg(
                        f"frame {index} of {self._n} (counting from 0): no frame within "
                        f"{self.config.frame_timeout_ms:.0f} ms; check the cable and the USB bandwidth"
                    )
                )
            )
        except CameraError as exc:
            self._fail(exc)

    def _fail(self, exc: CameraError) -> None:
        if self._error is None:
            self._error = exc
        self._all.set()
        raise exc

    def _capture(self, index: int) -> None:
        cap, out = self._cap, self._out
        assert cap is not None and out is not None
        self._sleep(self.config.settle_ms / 1000)
        for _ in range(self.config.flush_frames):
            cap.grab()
        ok, frame = cap.read()
        if not ok or frame is None:
            raise CameraError(
                self._msg(f"frame {index} of {self._n} (counting from 0): the read failed; check the cable")
            )
        _to_gray(np.asarray(frame), out[index])
        self._done.add(index)
        if self._on_frame is not None:
            self._on_frame(index, out[index])
        if len(self._done) >= self._n:
            self._all.set()

    async def wait_frames(self, timeout_s: float) -> None:
        """Wait until every armed frame was captured; raise :class:`CameraError` naming the first missing."""
        ok = await asyncio.to_thread(self._all.wait, timeout_s)
        if self._error is not None:
            raise self._error
        if not ok:
            missing = min(set(range(self._n)) - self._done)
            raise CameraError(
                self._msg(
                    f"only {len(self._done)} of {self._n} frames within {timeout_s:.1f} s; frame {missing} "
                    "(counting from 0) was never triggered; the scan must call trigger() for every frame"
                )
            )

    async def close(self) -> None:
        """Release the device; idempotent."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        cap, self._cap = self._cap, None
        if cap is not None:
            await asyncio.wrap_future(executor.submit(cap.release))
        await asyncio.to_thread(executor.shutdown, True)
        self.info = None


def _to_gray(frame: npt.NDArray[Any], dest: npt.NDArray[np.uint8]) -> None:
    """Write an 8-bit BGR or gray frame into ``dest`` as gray (BT.601 weights, like OpenCV)."""
    if frame.ndim == 2:
        np.copyto(dest, frame, casting="unsafe")
        return
    import cv2

    cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY, dst=dest)
