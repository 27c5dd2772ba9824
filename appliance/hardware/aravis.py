"""The ``aravis`` camera backend: GigE Vision / USB3 Vision cameras through Aravis 0.8 (PyGObject).

One worker thread per camera does every blocking Aravis call (connect, configure, acquire); the async
methods hand work to it and never block the event loop. A scan's frames are copied once, from the
Aravis buffer's data pointer straight into the caller's preallocated ``out[i]``, and reported through
the frame callback from the worker thread.

Cameras are opened by explicit IP address (no network traffic beyond that camera) or, when the
configuration names only a serial number, by id, which makes Aravis run device discovery (broadcasts on
every interface): that happens only when the user configured it so.

A lost camera (cable pulled, power cut) is marked disconnected by Aravis' ``control-lost`` signal or by a
failing register access; the next :meth:`AravisCamera.open` / :meth:`AravisCamera.arm` reconnects with
backoff, for at most ``reconnect_timeout_s``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import ctypes
import ipaddress
import logging
import queue
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt

from appliance.errors import BackendUnavailableError, CameraError
from appliance.hardware.base import CameraInfo, FrameArray, FrameCallback

if TYPE_CHECKING:  # the fake camera's process imports this module: keep pydantic out of it
    from appliance.config.backends import AravisCameraConfig

log = logging.getLogger(__name__)

INSTALL_HINT = (
    "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config "
    "&& pip install 'pygobject<3.51'"
)

# Module-level so tests can shorten them.
POP_SLICE_S = 0.05
"""Longest single wait on the stream, so an abort (close) is noticed quickly (s)."""
RECONNECT_BACKOFF_S = (0.2, 0.5, 1.0, 2.0)
"""Waits between reconnection attempts; the last one repeats (s)."""
SPARE_BUFFERS = 2
"""Buffers beyond the sequence length in the pool."""

_GEV_CCP = 0x0A00  # GigE Vision bootstrap register: control channel privilege

_PIXEL_DTYPES: dict[str, type[np.uint8] | type[np.uint16]] = {
    "Mono8": np.uint8,
    "Mono12": np.uint16,
    "Mono16": np.uint16,
}

_STATUS_HINTS = {
    "TIMEOUT": "the frame started but did not complete in time; check the link bandwidth and packet_delay_ns",
    "MISSING_PACKETS": (
        "packets were lost on the network; check the cable and switch, use a dedicated NIC with "
        "jumbo frames, or raise packet_delay_ns"
    ),
    "WRONG_PACKET_ID": "the stream was corrupted; check that no other application streams from this camera",
    "SIZE_MISMATCH": "the image was larger than the buffer; check pixel_format and the camera's region",
    "FILLING": "the frame was still being received; check the link bandwidth",
    "ABORTED": "the acquisition was aborted by the camera or the driver",
    "CLEARED": "the buffer was never filled; check the camera's trigger configuration",
    "UNKNOWN": "the driver returned an unknown buffer status; check the Aravis version",
}

T = TypeVar("T")


def load_aravis() -> tuple[ModuleType, ModuleType]:
    """Import PyGObject's ``Aravis`` 0.8 and ``GLib`` modules.

    Raises
    ------
    BackendUnavailableError
        When PyGObject or the Aravis 0.8 typelib is missing; names the packages to install.
    """
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as exc:
        raise BackendUnavailableError(
            f"backend 'aravis' is unavailable ({exc}); install it with: {INSTALL_HINT}"
        ) from exc
    return Aravis, GLib


_LIB: ctypes.CDLL | None = None


def libaravis() -> ctypes.CDLL:
    """The Aravis 0.8 shared library through ctypes (for data pointers PyGObject does not expose)."""
    global _LIB
    if _LIB is None:
        try:
            lib = ctypes.CDLL("libaravis-0.8.so.0")
        except OSError as exc:
            raise BackendUnavailableError(
                f"backend 'aravis' is unavailable (libaravis-0.8.so.0: {exc}); install it with: "
                f"{INSTALL_HINT}"
            ) from exc
        lib.arv_buffer_get_image_data.restype = ctypes.c_void_p
        lib.arv_buffer_get_image_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        _LIB = lib
    return _LIB


_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype = ctypes.c_void_p
_capsule_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]


def gobject_pointer(obj: Any) -> int:
    """The C address of a PyGObject wrapper's object (from its ``__gpointer__`` capsule)."""
    return int(_capsule_pointer(obj.__gpointer__, None))


def is_ip_address(address: str) -> bool:
    """True when ``address`` is a literal IPv4 address (opening it sends nothing but unicast GVCP)."""
    try:
        ipaddress.IPv4Address(address)
    except ValueError:
        return False
    return True


FOREIGN_STREAM_RETRIES = 3
"""New streams through Aravis' packet socket opened in a row, at most, when one received another camera's
packets (see ``AravisCamera._took_foreign_packets``); the stream after them receives through a UDP socket of
its own port."""


FOREIGN_SETTLE_S = 0.05
"""A new stream that has received nothing is looked at once more after this long (s) before its first
acquisition (once per stream: it costs this much on opening a camera, never per scan)."""


@dataclass
class AcquisitionStats:
    """Counters of one camera since it was created."""

    frames_ok: int = 0
    frames_lost: int = 0
    statuses: Counter[str] = field(default_factory=Counter)
    scans_ok: int = 0
    scans_failed: int = 0
    reconnects: int = 0
    foreign_streams: int = 0
    """New streams given up because they received another camera's packets before their first acquisition."""
    own_port_streams: int = 0
    """New streams opened with a UDP socket of their own port after ``FOREIGN_STREAM_RETRIES`` such streams."""


class FrameLostError(CameraError):
    """A frame of an armed sequence did not arrive intact.

    Attributes
    ----------
    frame_index : int
        Index of the frame in the sequence (from 0).
    status : str
        The Aravis buffer status (``MISSING_PACKETS``, ...), ``NO_FRAME`` or ``DISCONNECTED``.
    """

    def __init__(self, message: str, frame_index: int, status: str) -> None:
        super().__init__(message)
        self.frame_index = frame_index
        self.status = status


class _Aborted(Exception):
    pass


@dataclass
class _Job:
    n_frames: int
    out: npt.NDArray[Any]
    on_frame: FrameCallback | None
    software: bool
    auto_trigger: bool
    triggers: queue.Queue[int] = field(default_factory=queue.Queue)
    received: int = 0
    future: concurrent.futures.Future[None] = field(default_factory=concurrent.futures.Future)


class AravisCamera:
    """A GigE Vision / USB3 Vision camera through Aravis (a :class:`~appliance.hardware.base.Camera`).

    Parameters
    ----------
    name : str
        The camera's name in the configuration (``cameras.<name>``).
    config : AravisCameraConfig
        Address or serial, pixel format, exposure, gain, trigger and timeouts.
    """

    backend = "aravis"

    def __init__(self, name: str, config: AravisCameraConfig) -> None:
        if config.address is None and config.serial is None:
            raise CameraError(
                f"camera {name!r} (aravis): neither address nor serial is set; set cameras.{name}.address "
                "to the camera's IP address (or serial to open it by discovery)"
            )
        if config.address is not None and not is_ip_address(config.address):
            raise CameraError(
                f"camera {name!r} (aravis): address {config.address!r} is not an IPv4 address; give the "
                "camera's IP address (host names would make Aravis fall back to network discovery)"
            )
        self.name = name
        self.config = config
        self.stats = AcquisitionStats()
        self.info: CameraInfo | None = None
        self._aravis, self._glib = load_aravis()
        self._lib = libaravis()
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._camera: Any = None
        self._stream: Any = None
        self._device: Any = None
        self._control_lost_id = 0
        self._lost = threading.Event()
        self._abort = threading.Event()
        self._buffers: list[Any] = []
        self._buffer_size = 0
        self._fresh_stream = False  # no acquisition yet on the current stream
        self._own_port_socket = False  # the next stream receives through a UDP socket, not a packet socket
        self._job: _Job | None = None
        self._last_frame_id: int | None = None
        self._trigger_now = config.trigger
        self._exposure_us = float(config.exposure_us)  # what set_exposure() asked for; kept over reconnects

    # --- labels ---------------------------------------------------------------------------------------

    @property
    def where(self) -> str:
        """The camera's address (or serial) for messages."""
        return self.config.address or f"serial {self.config.serial}"

    @property
    def connected(self) -> bool:
        """True while the camera is open and has not been reported lost."""
        return self._camera is not None and not self._lost.is_set()

    @property
    def needs_software_trigger(self) -> bool:
        """True when the scan must call :meth:`trigger` once per frame."""
        return self.config.trigger == "Software" and self.config.software_trigger == "external"

    def _msg(self, text: str) -> str:
        return f"camera {self.name!r} (aravis, {self.where}): {text}"

    # --- worker thread ---------------------------------------------------------------------------------

    async def _run(self, fn: Callable[..., T], *args: Any) -> T:
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix=f"aravis-{self.name}"
            )
        return await asyncio.wrap_future(self._executor.submit(fn, *args))

    # --- protocol --------------------------------------------------------------------------------------

    async def open(self) -> CameraInfo:
        """Connect (with backoff, up to ``reconnect_timeout_s``) and configure; idempotent.

        Returns
        -------
        CameraInfo
            Model, serial, image size (px) and pixel format.

        Raises
        ------
        CameraError
            When the camera cannot be reached or refuses the configuration.
        """
        return await self._run(self._ensure_open)

    async def arm(
        self,
        n_frames: int,
        out: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
        on_frame: FrameCallback | None = None,
    ) -> None:
        """Start an acquisition of ``n_frames`` frames into ``out`` (shape (n_frames, H, W), C-contiguous).

        Reconnects first when the camera was lost. With ``trigger: Line1`` the camera then waits for hardware
        pulses; with ``trigger: Software`` the frames are triggered by the backend (``software_trigger:
        auto``) or by :meth:`trigger` calls (``external``).
        """
        await self._arm(
            n_frames,
            out,
            on_frame,
            software=self.config.trigger == "Software",
            auto=self.config.software_trigger == "auto",
        )

    async def trigger(self, index: int) -> None:
        """Fire the software trigger of frame ``index`` (``software_trigger: external`` only)."""
        job = self._job
        if job is None or job.auto_trigger or not job.software:
            raise CameraError(
                self._msg(
                    f"trigger({index}) needs an armed acquisition with trigger: Software and "
                    "software_trigger: external; check the camera's configuration"
                )
            )
        job.triggers.put(index)

    async def wait_frames(self, timeout_s: float) -> None:
        """Wait until every armed frame has arrived.

        Raises
        ------
        CameraError
            (a :class:`FrameLostError` for a bad or missing frame) naming the camera, its address, the frame
            index and what to check; or when the whole sequence took longer than ``timeout_s`` (s).
        """
        job = self._job
        if job is None:
            raise CameraError(self._msg("wait_frames() before arm(); arm the camera first"))
        try:
            await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(job.future)), timeout_s)
        except TimeoutError:
            self._abort.set()
            try:
                await asyncio.wrap_future(job.future)
            except CameraError:
                pass
            raise FrameLostError(
                self._msg(
                    f"only {job.received} of {job.n_frames} frames within {timeout_s:.1f} s; frame "
                    f"{job.received} of {job.n_frames} (counting from 0) never came; "
                    + self._no_frame_hint(job.software)
                ),
                job.received,
                "NO_FRAME",
            ) from None
        finally:
            if job.future.done():
                self._job = None

    async def grab(self, timeout_s: float | None = None) -> FrameArray:
        """Capture one frame on a software trigger (even when configured for Line1), e.g. for calibration.

        Returns
        -------
        ndarray, shape (H, W), uint8 (Mono8) or uint16 (Mono12, Mono16)
        """
        info = await self.open()
        out: npt.NDArray[Any] = np.empty((1, info.height, info.width), _PIXEL_DTYPES[info.pixel_format])
        self._trigger_now = "Software"
        try:
            await self._arm(1, out, None, software=True, auto=True)
            await self.wait_frames(timeout_s if timeout_s is not None else self.config.frame_timeout_ms / 500)
        finally:
            self._trigger_now = self.config.trigger
        frame: FrameArray = out[0]
        return frame

    async def set_exposure(self, exposure_us: float) -> None:
        """Set ``ExposureTime`` (µs) for the next acquisition, e.g. between the passes of an HDR scan.

        A reconnect keeps it (the camera is configured with the last exposure set here).

        Raises
        ------
        CameraError
            While an acquisition runs, or when the camera refuses the value (with the range it accepts).
        """
        if self._job is not None and not self._job.future.done():
            raise CameraError(self._msg("set_exposure() while a sequence is being captured; wait_frames() first"))
        await self._run(self._set_exposure, float(exposure_us))

    async def close(self) -> None:
        """Abort any acquisition, release the stream, then the camera; idempotent."""
        self._abort.set()
        executor, self._executor = self._executor, None
        if executor is None:
            return
        try:
            await asyncio.wrap_future(executor.submit(self._teardown))
        finally:
            await asyncio.to_thread(executor.shutdown, True)
            self._job = None
            self._abort.clear()

    def _set_exposure(self, exposure_us: float) -> None:
        self._ensure_open()
        camera, glib = self._camera, self._glib
        try:
            low, high = camera.get_exposure_time_bounds()
        except glib.Error:
            low, high = 0.0, float("inf")
        if not low <= exposure_us <= high:
            raise CameraError(self._msg(
                f"exposure {exposure_us:g} µs is outside the camera's ExposureTime range {low:g}..{high:g} µs; "
                "choose exposures in that range (sequence.exposures_us)"))  # fmt: skip
        try:
            camera.set_exposure_time(exposure_us)
        except glib.Error as exc:
            raise CameraError(self._msg(
                f"ExposureTime = {exposure_us:g} µs was refused ({exc.message}); check the camera's exposure "
                "range and that nothing else controls it")) from exc  # fmt: skip
        self._exposure_us = exposure_us

    # --- arm -------------------------------------------------------------------------------------------

    async def _arm(
        self,
        n_frames: int,
        out: npt.NDArray[Any],
        on_frame: FrameCallback | None,
        *,
        software: bool,
        auto: bool,
    ) -> None:
        if self._job is not None and not self._job.future.done():
            raise CameraError(
                self._msg("arm() while a sequence is still being captured; wait_frames() first")
            )
        if n_frames < 1 or out.ndim != 3 or out.shape[0] < n_frames or not out.flags.c_contiguous:
            raise CameraError(
                self._msg(
                    f"cannot capture {n_frames} frames into a buffer of shape {out.shape}; pass a "
                    "C-contiguous (n_frames, height, width) array"
                )
            )
        self._abort.clear()
        job = _Job(n_frames, out, on_frame, software, auto)
        await self._run(self._prepare, job)
        self._job = job
        assert self._executor is not None
        self._executor.submit(self._acquire, job)

    def _prepare(self, job: _Job) -> None:
        failed = foreign = 0
        while True:
            if self.connected:
                self._alive()  # one register read: notices a camera that restarted behind our back
            info = self._ensure_open()
            dtype = _PIXEL_DTYPES[info.pixel_format]
            if job.out.shape[1:] != (info.height, info.width) or job.out.dtype != dtype:
                raise CameraError(
                    self._msg(
                        f"buffer of shape {job.out.shape[1:]} {job.out.dtype} does not fit {info.width}x"
                        f"{info.height} {info.pixel_format} frames; allocate (n, {info.height}, "
                        f"{info.width}) {np.dtype(dtype).name}"
                    )
                )
            try:
                self._set_trigger(self._trigger_now)
                self._fill_pool(job.n_frames + SPARE_BUFFERS)
                if foreign <= FOREIGN_STREAM_RETRIES and self._took_foreign_packets():
                    foreign += 1
                    # the packet socket kept seeing another camera: one that cannot see its port next
                    self._own_port_socket = foreign >= FOREIGN_STREAM_RETRIES
                    continue
                self._fresh_stream = False
                self._own_port_socket = False
                return
            except self._glib.Error as exc:
                self._mark_lost(f"configuring the acquisition failed ({exc.message})")
                if failed:
                    raise CameraError(
                        self._msg(f"cannot configure the acquisition ({exc.message}); check the camera")
                    ) from exc
                failed += 1

    def _disable_packet_socket(self) -> None:
        """Make the next GigE Vision stream receive through a UDP socket bound to its own port (Aravis without
        the option keeps its default)."""
        try:
            self._device.set_stream_options(self._aravis.GvStreamOption.PACKET_SOCKET_DISABLED)
        except (AttributeError, TypeError):
            return
        self.stats.own_port_streams += 1
        log.warning("%s", self._msg("the new stream receives through a UDP socket of its own port"))

    def _took_foreign_packets(self) -> bool:
        """True (and the camera closed, to be reopened) when a new stream received packets before its first
        acquisition: another camera's.

        Where raw sockets are allowed (e.g. as root) Aravis receives through a packet socket that sees every
        GVSP packet on the interface until its port filter is attached. A stream opened while another camera
        streamed took that camera's frames, and their higher frame ids then made it discard its own first
        frames as late (frame 0 never arrived, 2 in 25 two-camera captures under load). A plain UDP socket
        (the service, without CAP_NET_RAW) only ever sees its own port. Replacing the stream once was not
        always enough under load (CI, 2026-12-04: three polluted streams in a row, and the fourth, not looked
        at, lost frame 0), so every new stream is looked at, and after ``FOREIGN_STREAM_RETRIES`` polluted
        ones the next receives through a UDP socket (``_own_port_socket``). The packet socket stays the first
        choice: it costs less CPU per packet, and a UDP socket's buffer (``net.core.rmem_max``) drops packets
        of a sender much faster than a GigE link, as the fakes on loopback are.
        """
        if not self._fresh_stream:
            return False
        try:
            received = int(self._stream.get_info_uint64_by_name("n_received_packets"))
            if received == 0:  # another camera's packets may still be on their way: look once more
                time.sleep(FOREIGN_SETTLE_S)
                received = int(self._stream.get_info_uint64_by_name("n_received_packets"))
        except (AttributeError, TypeError, self._glib.Error):  # Aravis before 0.8.23: no stream info
            return False
        if received == 0:
            return False
        log.warning("%s", self._msg(f"a new stream received {received} packets of another camera before its "
                                    "first acquisition; opening a new one"))  # fmt: skip
        self.stats.foreign_streams += 1
        self._teardown()
        return True

    # --- blocking helpers (worker thread) ---------------------------------------------------------------

    def _ensure_open(self) -> CameraInfo:
        if self.connected and self.info is not None:
            return self.info
        if self._camera is not None:
            self.stats.reconnects += 1
            log.warning("%s", self._msg("connection lost; reconnecting"))
        self._teardown()
        deadline = time.monotonic() + self.config.reconnect_timeout_s
        attempt = 0
        while True:
            try:
                return self._connect()
            except CameraError as exc:
                self._teardown()
                wait = RECONNECT_BACKOFF_S[min(attempt, len(RECONNECT_BACKOFF_S) - 1)]
                if self._abort.is_set() or time.monotonic() + wait > deadline:
                    raise exc
                attempt += 1
                time.sleep(wait)

    def _id_of_serial(self, serial: str) -> str:
        """The Aravis device id of the camera with this serial number, by discovery (broadcasts).

        ``Aravis.Camera.new`` matches ids, MAC and IP addresses but not serial numbers, so the serial is looked
        up in the discovered device list.
        """
        aravis = self._aravis
        aravis.update_device_list()  # configured by the user: cameras.<name>.serial without an address
        seen = []
        for i in range(aravis.get_n_devices()):
            if aravis.get_device_serial_nbr(i) == serial:
                return str(aravis.get_device_id(i))
            seen.append(f"{aravis.get_device_serial_nbr(i)} at {aravis.get_device_address(i)}")
        raise CameraError(
            self._msg(
                f"no camera with serial {serial!r} answered discovery (found: {', '.join(seen) or 'none'}); "
                "check power and the cable, or set the camera's address instead"
            )
        )

    def _connect(self) -> CameraInfo:
        aravis, glib, cfg = self._aravis, self._glib, self.config
        target = cfg.address if cfg.address is not None else self._id_of_serial(str(cfg.serial))
        try:
            camera = aravis.Camera.new(target)
        except glib.Error as exc:
            raise CameraError(
                self._msg(
                    f"cannot connect ({exc.message}); check power, the cable and that the camera's "
                    "IP address is in this host's subnet"
                )
            ) from exc
        self._camera = camera
        self._lost.clear()
        self._device = camera.get_device()
        self._control_lost_id = self._device.connect("control-lost", self._on_control_lost)
        try:
            self._configure(camera)
            if camera.is_gv_device() and self._own_port_socket:
                self._disable_packet_socket()
            stream = camera.create_stream(None, None)
            if stream is None:
                raise CameraError(
                    self._msg("could not create a stream; check the camera's streaming channel")
                )
            if camera.is_gv_device():
                stream.set_property(
                    "packet-resend",
                    aravis.GvStreamPacketResend.ALWAYS
                    if cfg.packet_resend
                    else aravis.GvStreamPacketResend.NEVER,
                )
            self._stream = stream
            self._fresh_stream = True
            _x, _y, width, height = camera.get_region()
            pixel_format = camera.get_pixel_format_as_string()
            vendor = camera.get_vendor_name() or ""
            model = camera.get_model_name() or ""
            serial = camera.get_device_serial_number() or ""
        except glib.Error as exc:
            raise CameraError(
                self._msg(f"configuration failed ({exc.message}); check the camera's settings")
            ) from exc
        if pixel_format not in _PIXEL_DTYPES:
            raise CameraError(
                self._msg(f"camera reports pixel format {pixel_format}, not {cfg.pixel_format}")
            )
        self.info = CameraInfo(
            self.name, "aravis", f"{vendor} {model}".strip(), serial, width, height, pixel_format
        )
        self._buffers, self._buffer_size = [], 0
        self._last_frame_id = None
        log.info(
            "%s", self._msg(f"connected: {self.info.model} serial {serial}, {width}x{height} {pixel_format}")
        )
        return self.info

    def _configure(self, camera: Any) -> None:
        aravis, glib, cfg = self._aravis, self._glib, self.config
        try:
            camera.set_pixel_format_from_string(cfg.pixel_format)
        except glib.Error as exc:
            offered = camera.dup_available_pixel_formats_as_strings()
            raise CameraError(
                self._msg(
                    f"pixel_format = {cfg.pixel_format} was refused ({exc.message}); the camera "
                    f"offers {offered}"
                )
            ) from exc
        camera.set_acquisition_mode(aravis.AcquisitionMode.CONTINUOUS)
        if camera.is_feature_available("ExposureMode"):
            camera.set_string("ExposureMode", "Timed")
        if camera.is_exposure_auto_available():
            camera.set_exposure_time_auto(aravis.Auto.OFF)
        camera.set_exposure_time(self._exposure_us)
        if camera.is_gain_available():
            if camera.is_gain_auto_available():
                camera.set_gain_auto(aravis.Auto.OFF)
            camera.set_gain(cfg.gain_db)
        elif cfg.gain_db:
            raise CameraError(
                self._msg(f"gain_db = {cfg.gain_db}: this camera has no gain control; set it to 0")
            )
        self._set_trigger(self._trigger_now)
        if camera.is_gv_device():
            if cfg.packet_size is not None:
                camera.gv_set_packet_size(cfg.packet_size)
            if cfg.packet_delay_ns:
                camera.gv_set_packet_delay(cfg.packet_delay_ns)

    def _set_trigger(self, source: str) -> None:
        camera = self._camera
        offered = camera.dup_available_trigger_sources()
        if source not in offered:
            raise CameraError(
                self._msg(
                    f"trigger = {source}: the camera's TriggerSource offers {offered}; choose one of those"
                )
            )
        if camera.get_trigger_source() != source or camera.get_string("TriggerMode") != "On":
            camera.set_trigger(source)

    def _fill_pool(self, count: int) -> None:
        aravis, camera, stream = self._aravis, self._camera, self._stream
        payload = camera.get_payload()
        self._drain()
        if payload != self._buffer_size:
            self._buffers, self._buffer_size = [], payload
        while len(self._buffers) < count:
            buf = aravis.Buffer.new_allocate(payload)
            self._buffers.append(buf)
            stream.push_buffer(buf)

    def _drain(self) -> None:
        """Pop every buffer left in the output queue and give it back to the stream."""
        stream = self._stream
        while True:
            buf = stream.try_pop_buffer()
            if buf is None:
                return
            stream.push_buffer(buf)

    def _on_control_lost(self, *_args: Any) -> None:
        if not self._lost.is_set():
            log.warning("%s", self._msg("control lost (no heartbeat answer)"))
        self._lost.set()

    def _mark_lost(self, why: str) -> None:
        if not self._lost.is_set():
            log.warning("%s", self._msg(f"marked disconnected: {why}"))
        self._lost.set()

    def _alive(self) -> bool:
        if self._lost.is_set() or self._device is None:
            return False
        try:
            privilege = self._device.read_register(_GEV_CCP)
        except self._glib.Error as exc:
            self._mark_lost(f"register read failed ({exc.message})")
            return False
        if self._camera.is_gv_device() and not privilege & 0x3:
            self._mark_lost("the camera no longer grants us control (it restarted?)")
            return False
        return True

    def _teardown(self) -> None:
        # Stream before camera: Aravis aborts at exit otherwise.
        stream, camera, device = self._stream, self._camera, self._device
        self._stream = self._camera = self._device = None
        self._buffers, self._buffer_size = [], 0
        if camera is not None and not self._lost.is_set():
            try:
                camera.stop_acquisition()
            except self._glib.Error:
                pass
        if device is not None and self._control_lost_id:
            device.disconnect(self._control_lost_id)
            self._control_lost_id = 0
        del stream, camera, device

    # --- acquisition (worker thread) ---------------------------------------------------------------------

    def _acquire(self, job: _Job) -> None:
        try:
            self._acquire_frames(job)
        except CameraError as exc:
            self.stats.scans_failed += 1
            job.future.set_exception(_without_locals(exc))
        except _Aborted:
            job.future.set_exception(
                CameraError(
                    self._msg(
                        f"acquisition aborted after {job.received} of {job.n_frames} frames (camera closed)"
                    )
                )
            )
        except BaseException as exc:  # never leave the scan waiting forever
            job.future.set_exception(_without_locals(exc))
        else:
            self.stats.scans_ok += 1
            job.future.set_result(None)

    def _acquire_frames(self, job: _Job) -> None:
        camera, glib = self._camera, self._glib
        frame_nbytes = job.out[0].nbytes
        base = job.out.ctypes.data
        t_start_ns = time.time_ns()
        try:
            camera.start_acquisition()
        except glib.Error as exc:
            self._mark_lost(f"AcquisitionStart failed ({exc.message})")
            raise self._lost_error(job, 0, "AcquisitionStart failed") from exc
        try:
            for i in range(job.n_frames):
                if job.software:
                    self._fire(job, i)
                buf = self._pop(job, i, t_start_ns)
                self._check_buffer(job, i, buf)
                self._copy(buf, base + i * frame_nbytes, frame_nbytes, job, i)
                job.received = i + 1
                self.stats.frames_ok += 1
                if job.on_frame is not None:
                    job.on_frame(i, job.out[i])
        finally:
            if not self._lost.is_set():
                try:
                    camera.stop_acquisition()
                    self._drain()
                except glib.Error as exc:
                    self._mark_lost(f"AcquisitionStop failed ({exc.message})")

    def _fire(self, job: _Job, i: int) -> None:
        if not job.auto_trigger:
            while True:
                if self._abort.is_set():
                    raise _Aborted
                try:
                    index = job.triggers.get(timeout=POP_SLICE_S)
                except queue.Empty:
                    continue
                if index == i:
                    break
                log.warning("%s", self._msg(f"trigger({index}) while frame {i} was expected; ignored"))
        try:
            self._camera.software_trigger()
        except self._glib.Error as exc:
            self._mark_lost(f"TriggerSoftware failed ({exc.message})")
            raise self._lost_error(job, i, f"the software trigger failed ({exc.message})") from exc

    def _pop(self, job: _Job, i: int, t_start_ns: int) -> Any:
        stream = self._stream
        first_hw = i == 0 and not job.software
        timeout_s = self.config.frame_timeout_ms / 1000
        deadline = None if first_hw else time.monotonic() + timeout_s
        while True:
            if self._abort.is_set():
                raise _Aborted
            left = POP_SLICE_S if deadline is None else min(POP_SLICE_S, deadline - time.monotonic())
            buf = stream.timeout_pop_buffer(max(int(left * 1e6), 1000)) if left > 0 else None
            if buf is not None:
                if buf.get_system_timestamp() < t_start_ns:
                    stream.push_buffer(buf)  # a leftover of an earlier, aborted acquisition
                    continue
                return buf
            if self._lost.is_set():
                raise self._lost_error(job, i, "the camera stopped answering")
            if deadline is not None and time.monotonic() >= deadline:
                self.stats.frames_lost += 1
                self.stats.statuses["NO_FRAME"] += 1
                if not self._alive():
                    raise self._lost_error(job, i, "no frame and the camera does not answer")
                what = "software trigger" if job.software else "trigger"
                raise FrameLostError(
                    self._msg(
                        f"frame {i} of {job.n_frames} (counting from 0): no frame within "
                        f"{self.config.frame_timeout_ms:.0f} ms of its {what}; "
                        f"{self._no_frame_hint(job.software)}"
                    ),
                    i,
                    "NO_FRAME",
                )

    def _check_buffer(self, job: _Job, i: int, buf: Any) -> None:
        status = buf.get_status()
        name = status.value_nick.upper().replace("-", "_")
        self.stats.statuses[name] += 1
        frame_id = buf.get_frame_id()
        previous, self._last_frame_id = self._last_frame_id, frame_id
        if status != self._aravis.BufferStatus.SUCCESS:
            self._stream.push_buffer(buf)
            self.stats.frames_lost += 1
            detail = ""
            if name == "MISSING_PACKETS" and hasattr(self._stream, "get_statistics"):
                try:
                    resent, missing = self._stream.get_statistics()
                    detail = f" ({missing} packets missing, {resent} resent so far on this stream)"
                except (TypeError, ValueError):
                    detail = ""
            raise FrameLostError(
                self._msg(
                    f"frame {i} of {job.n_frames} (counting from 0, camera frame id {frame_id}) "
                    f"arrived with status {name}{detail}; "
                    f"{_STATUS_HINTS.get(name, _STATUS_HINTS['UNKNOWN'])}"
                ),
                i,
                name,
            )
        if previous is not None and i > 0 and 1 < frame_id - previous < 1000:
            self._stream.push_buffer(buf)
            lost = frame_id - previous - 1
            self.stats.frames_lost += lost
            self.stats.statuses["SKIPPED"] += lost
            raise FrameLostError(
                self._msg(
                    f"frame {i} of {job.n_frames} (counting from 0) is missing: the camera's frame "
                    f"id jumped from {previous} to {frame_id} ({lost} frame(s) lost whole); "
                    f"{_STATUS_HINTS['MISSING_PACKETS']}"
                ),
                i,
                "SKIPPED",
            )

    def _copy(self, buf: Any, dest: int, nbytes: int, job: _Job, i: int) -> None:
        size = ctypes.c_size_t(0)
        src = self._lib.arv_buffer_get_image_data(gobject_pointer(buf), ctypes.byref(size))
        try:
            if not src or size.value < nbytes:
                self.stats.frames_lost += 1
                raise FrameLostError(
                    self._msg(
                        f"frame {i} of {job.n_frames} (counting from 0) holds {size.value} bytes, "
                        f"expected {nbytes}; " + _STATUS_HINTS["SIZE_MISMATCH"]
                    ),
                    i,
                    "SIZE_MISMATCH",
                )
            ctypes.memmove(dest, src, nbytes)
        finally:
            self._stream.push_buffer(buf)

    def _lost_error(self, job: _Job, i: int, why: str) -> FrameLostError:
        self.stats.frames_lost += 1
        self.stats.statuses["DISCONNECTED"] += 1
        return FrameLostError(
            self._msg(
                f"disconnected at frame {i} of {job.n_frames} (counting from 0): {why}; check the "
                "cable and the "
                "camera's power (the next scan reconnects by itself)"
            ),
            i,
            "DISCONNECTED",
        )

    def _no_frame_hint(self, software: bool) -> str:
        if software:
            return "check the network link and that the camera accepts TriggerSoftware"
        return "check the trigger cable to Line1 and the trigger controller"


def _without_locals(exc: BaseException) -> BaseException:
    """``exc`` with the locals of its finished frames (and its causes') dropped.

    The job's future keeps the exception, whose traceback keeps the acquisition frame, whose locals keep the job
    (so the future) and the Aravis camera: a reference cycle. Left to the garbage collector, the camera was
    released in whatever thread collected next, often the event loop's, where releasing a vanished GigE camera
    blocked for up to 15 s (its control channel's timeouts). Cleared here, the camera goes in ``_teardown``.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        traceback.clear_frames(e.__traceback__)
        e = e.__cause__ or e.__context__
    return exc
