"""A fake GigE Vision camera served from Python, for tests through the real Aravis stack.

:func:`start_fake_camera` runs ``Aravis.GvFakeCamera`` in its own process (a ``GLib.MainLoop``) on an
explicit loopback address. Each frame it sends comes from a provider, ``frame_provider(index) -> (H, W)
array``, where ``index`` counts the frames of the current acquisition from 0; the pixels are written into
the fake's buffer by a ctypes fill-pattern callback (a Python callback through PyGObject crashes).

The camera's GenICam description is Aravis' own fake camera with two additions: ``Line1`` in
``TriggerSource`` (the fake then fires its own "hardware" pulses, ``line_pulses`` per acquisition at
``line_rate_hz``) and ``Mono12`` in ``PixelFormat``.

Fault injection: packet loss (``packet_loss``), frames whose every packet is dropped (``skip_frames``), and
the camera disappearing (:meth:`FakeGigECamera.kill`).

Only one camera can listen on one address's port 3956, and the address must belong to a network
interface. :class:`LoopbackLab` gives a private network namespace (when the OS allows) in which
127.0.0.2, 127.0.0.3, ... exist and nothing can leak onto a real network.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import multiprocessing.connection
import os
import queue
import re
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from appliance.errors import CameraError

FrameProvider = Callable[[int], npt.NDArray[Any]]
T = TypeVar("T")

READY_TIMEOUT_S = 15.0
"""How long :func:`start_fake_camera` waits for the fake's process to listen (s)."""
POLL_MS = 1
"""Period of the fake's acquisition-state poll (ms)."""

_MONO12 = 0x01100005
_MONO16 = 0x01100007
_CLONE_NEWNET = 0x40000000
_TAG = b"scan3d-served"


# --- the served camera (runs in the fake's own process) ------------------------------------------------


class FrameSource(Protocol):
    """What ``scan3d simulate-camera`` serves: ``frame_count`` frames of ``frame_size`` (width, height) px.

    The command hands the tool one (a manifest's stack, or the virtual rig's rendering of the configured
    sequence, see :func:`appliance.commands.simulate_camera_command`); the tool knows nothing about
    configurations, rigs or scans.
    """

    @property
    def frame_count(self) -> int:
        """Frames per acquisition."""
        ...

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) of every frame (px)."""
        ...

    def render(self, frame_index: int) -> npt.NDArray[Any]:
        """Frame ``frame_index`` (0 <= index < frame_count), shape (height, width), uint8 or uint16."""
        ...


class StackProvider:
    """Serves the frames of a (F, H, W) stack in order, cycling after the last one (a :class:`FrameSource`)."""

    def __init__(self, frames: npt.NDArray[Any]) -> None:
        if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
            raise CameraError(
                f"fake camera: frames must be (F, H, W) uint8 or uint16, got {frames.shape} {frames.dtype}"
            )
        self.frames = np.ascontiguousarray(frames)

    @property
    def frame_count(self) -> int:
        return int(self.frames.shape[0])

    @property
    def frame_size(self) -> tuple[int, int]:
        return int(self.frames.shape[2]), int(self.frames.shape[1])

    def render(self, frame_index: int) -> npt.NDArray[Any]:
        return self.frames[frame_index % len(self.frames)]  # type: ignore[no-any-return]

    def __call__(self, index: int) -> npt.NDArray[Any]:
        return self.render(index)


@dataclass
class _Spec:
    address: str
    serial: str
    provider: FrameProvider
    width: int
    height: int
    packet_loss: float = 0.0
    skip_frames: frozenset[int] = frozenset()
    line_pulses: int | None = None
    line_rate_hz: float = 50.0
    trigger_tick_hz: float = 200.0
    exposure_reference_us: float | None = None


def _patched_genicam(xml: str) -> str:
    """Aravis' fake camera description plus Line1 (trigger) and Mono12 (pixel format)."""
    xml = xml.replace(
        '<EnumEntry Name="Software" NameSpace="Standard">',
        '<EnumEntry Name="Line1" NameSpace="Standard">\n\t\t\t<Value>2</Value>\n\t\t</EnumEntry>\n'
        '\t\t<EnumEntry Name="Software" NameSpace="Standard">',
        1,
    )
    return xml.replace(
        '<EnumEntry Name="Mono16" NameSpace="Standard">',
        f'<EnumEntry Name="Mono12" NameSpace="Standard">\n\t\t\t<Value>{_MONO12}</Value>\n\t\t</EnumEntry>\n'
        '\t\t<EnumEntry Name="Mono16" NameSpace="Standard">',
        1,
    )


def _register(xml: str, name: str) -> int:
    match = re.search(rf'<IntReg Name="{name}"[^>]*>\s*<Address>(0x[0-9a-fA-F]+)</Address>', xml)
    if match is None:
        raise CameraError(f"fake camera: register {name} not found in Aravis' fake GenICam description")
    return int(match.group(1), 16)


class _Server:
    """The fake camera inside its process: GLib main loop, fill callback, fault injection."""

    def __init__(self, spec: _Spec, conn: multiprocessing.connection.Connection | None) -> None:
        from appliance.hardware.aravis import gobject_pointer, libaravis, load_aravis

        self.aravis, self.glib = load_aravis()
        self.spec, self.conn = spec, conn
        self.lock = threading.Lock()
        self.index = 0
        self.served = 0
        self.acquisitions = 0
        self.exposures: list[int] = []
        self.active = False
        self.pulses_left = 0
        self.pulsing = False
        self.loss = spec.packet_loss
        self.applied_loss = -1.0
        self.skip = set(spec.skip_frames)
        base = self.aravis.FakeCamera.new("base").get_genicam_xml()
        base_xml = base[0] if isinstance(base, tuple) else base
        xml = _patched_genicam(base_xml)
        self.xml_file = tempfile.NamedTemporaryFile("w", suffix=".xml", prefix="scan3d-fake-", delete=False)
        self.xml_file.write(xml)
        self.xml_file.close()
        self.reg_mode = _register(xml, "TriggerModeRegister")
        self.reg_source = _register(xml, "TriggerSourceRegister")
        self.reg_software = _register(xml, "TriggerSoftwareCommandRegister")
        self.gv = self.aravis.GvFakeCamera.new_full(spec.address, spec.serial, self.xml_file.name)
        if not self.gv.is_running():
            raise CameraError(
                f"fake camera: cannot listen on {spec.address}:3956; the address must belong to a network "
                f"interface (e.g. `ip addr add {spec.address}/8 dev lo`, or use a LoopbackLab) and no other "
                "camera may listen there"
            )
        self.fake = self.gv.get_fake_camera()
        self.fake.write_register(_register(xml, "WidthRegister"), spec.width)
        self.fake.write_register(_register(xml, "HeightRegister"), spec.height)
        self.fake.set_trigger_frequency(spec.trigger_tick_hz)
        self.lib = libaravis()
        self.lib.arv_buffer_get_image_width.restype = ctypes.c_int
        self.lib.arv_buffer_get_image_width.argtypes = [ctypes.c_void_p]
        self.lib.arv_buffer_get_image_height.restype = ctypes.c_int
        self.lib.arv_buffer_get_image_height.argtypes = [ctypes.c_void_p]
        self.lib.arv_fake_camera_set_fill_pattern.argtypes = [
            ctypes.c_void_p,
            ctypes.c_void_p,
            ctypes.c_void_p,
        ]
        fill_type = ctypes.CFUNCTYPE(
            None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
        )
        self.fill_cb = fill_type(self._fill)  # kept alive as long as the server
        self.lib.arv_fake_camera_set_fill_pattern(gobject_pointer(self.fake), self.fill_cb, None)
        self.gobject = ctypes.CDLL("libgobject-2.0.so.0")
        self.gobject.g_object_get_data.restype = ctypes.c_void_p
        self.gobject.g_object_get_data.argtypes = [ctypes.c_void_p, ctypes.c_char_p]
        self.gobject.g_object_set_data.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
        self.loop = self.glib.MainLoop()

    def run(self) -> None:
        self.glib.timeout_add(POLL_MS, self._poll)
        if self.spec.line_rate_hz > 0:
            self.glib.timeout_add(max(1, int(1000 / self.spec.line_rate_hz)), self._pulse)
        self.glib.unix_signal_add(self.glib.PRIORITY_DEFAULT, signal.SIGTERM, self._quit)
        self.glib.unix_signal_add(self.glib.PRIORITY_DEFAULT, signal.SIGINT, self._quit)
        if self.conn is not None:
            self.conn.send(("ready", self.spec.width, self.spec.height))
        try:
            self.loop.run()
        finally:
            os.unlink(self.xml_file.name)

    def _quit(self) -> bool:
        self.loop.quit()
        return False

    def _poll(self) -> bool:
        if self.fake.get_acquisition_status() == 0:
            with self.lock:
                self.active = False
        if self.conn is not None:
            while self.conn.poll():
                self._command(self.conn.recv())
        return True

    def _command(self, cmd: tuple[Any, ...]) -> None:
        op = cmd[0]
        with self.lock:
            if op == "loss":
                self.loss = float(cmd[1])
            elif op == "skip":
                self.skip = set(cmd[1])
            elif op == "stats":
                assert self.conn is not None
                self.conn.send(("stats", {"served": self.served, "acquisitions": self.acquisitions}))
            elif op == "exposures":
                assert self.conn is not None
                self.conn.send(("exposures", list(self.exposures)))
            elif op == "stop":
                self.loop.quit()

    def _line1_mode(self) -> bool:
        return bool(
            self.fake.read_register(self.reg_mode)[1] == 1
            and self.fake.read_register(self.reg_source)[1] == 2
        )

    def _pulse(self) -> bool:
        """Line1 mode: a simulated trigger controller pulses ``line_pulses`` times per acquisition."""
        if self.fake.get_acquisition_status() == 0 or not self._line1_mode():
            return True
        with self.lock:
            if not self.active:
                self._new_acquisition()
            if self.pulses_left <= 0:
                return True
            self.pulses_left -= 1
            # The fake emits frames only in its software-trigger mode: switch over for the pulse's frame.
            self.pulsing = True
        self.fake.write_register(self.reg_source, 1)
        self.fake.write_register(self.reg_software, 1)
        return True

    def _new_acquisition(self) -> None:
        self.active = True
        self.pulses_left = self.spec.line_pulses if self.spec.line_pulses is not None else 1 << 30

    def _fill(self, buffer: int, _data: int, exposure_us: int, _gain: int, pixel_format: int) -> None:
        try:
            self._fill_frame(buffer, pixel_format, exposure_us)
        except Exception as exc:  # an exception must not cross the C callback
            print(f"fake camera {self.spec.address}: fill failed: {exc!r}", file=sys.stderr, flush=True)

    def _fill_frame(self, buffer: int, pixel_format: int, exposure_us: int) -> None:
        # The fake allocates a new buffer at each AcquisitionStart: an untagged buffer starts frame 0.
        if not self.gobject.g_object_get_data(buffer, _TAG):
            self.gobject.g_object_set_data(buffer, _TAG, 1)
            with self.lock:
                self.index = 0
                self.acquisitions += 1
                self.exposures.append(int(exposure_us))
        with self.lock:
            index = self.index
            self.index += 1
            self.served += 1
            loss = 1.0 if index in self.skip else self.loss
            pulsed, self.pulsing = self.pulsing, False
        if pulsed:
            self.fake.write_register(self.reg_source, 2)  # back to Line1 after a simulated pulse
        if loss != self.applied_loss:
            self.gv.set_property("gvsp-lost-ratio", loss)
            self.applied_loss = loss
        width = self.lib.arv_buffer_get_image_width(buffer)
        height = self.lib.arv_buffer_get_image_height(buffer)
        frame = np.asarray(self.spec.provider(index))
        if frame.shape != (height, width):
            raise CameraError(f"frame {index} has shape {frame.shape}, the camera is {width}x{height}")
        wide = pixel_format in (_MONO12, _MONO16)
        if wide:
            data = frame.astype("<u2", copy=False) if frame.dtype == np.uint16 else frame.astype("<u2") << 8
        else:
            data = frame if frame.dtype == np.uint8 else (frame >> 8).astype(np.uint8)
        ref = self.spec.exposure_reference_us
        if ref is not None and exposure_us != ref:  # light scales with the exposure, clipped at full scale
            full = {_MONO12: 4095, _MONO16: 65535}.get(pixel_format, 255)
            data = np.minimum(np.rint(data * (exposure_us / ref)), full).astype(data.dtype)
        data = np.ascontiguousarray(data)
        size = ctypes.c_size_t(0)
        dest = self.lib.arv_buffer_get_image_data(buffer, ctypes.byref(size))
        ctypes.memmove(dest, data.ctypes.data, data.nbytes)


def _serve(spec: _Spec, conn: multiprocessing.connection.Connection | None) -> None:
    try:
        server = _Server(spec, conn)
    except Exception as exc:
        if conn is not None:
            conn.send(("error", str(exc)))
            return
        raise
    server.run()


# --- the handle (test side) ----------------------------------------------------------------------------


@dataclass
class FakeGigECamera:
    """A running fake camera process; stop it with :meth:`stop` (or :meth:`kill` to make it vanish)."""

    address: str
    serial: str
    width: int
    height: int
    process: multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def alive(self) -> bool:
        """True while the fake's process runs."""
        return self.process.is_alive()

    def set_packet_loss(self, ratio: float) -> None:
        """Drop this fraction (0..1) of every frame's GVSP packets from now on."""
        self._send(("loss", ratio))

    def skip_frames(self, indices: Iterable[int]) -> None:
        """Drop every packet of these frames (indices within each acquisition, from 0)."""
        self._send(("skip", sorted(indices)))

    def stats(self, timeout_s: float = 2.0) -> dict[str, int]:
        """Frames served and acquisitions seen by the fake."""
        with self._lock:
            self.conn.send(("stats",))
            if not self.conn.poll(timeout_s):
                raise CameraError(f"fake camera {self.address}: no answer to a stats request")
            reply = self.conn.recv()
        return dict(reply[1])

    def acquisition_exposures(self, timeout_s: float = 2.0) -> list[int]:
        """The ``ExposureTime`` (µs) each acquisition so far started with, in order."""
        with self._lock:
            self.conn.send(("exposures",))
            if not self.conn.poll(timeout_s):
                raise CameraError(f"fake camera {self.address}: no answer to an exposures request")
            reply = self.conn.recv()
        return [int(e) for e in reply[1]]

    def kill(self) -> None:
        """Make the camera vanish at once (SIGKILL), like a pulled cable."""
        if self.process.is_alive():
            self.process.kill()
        self.process.join(5)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the fake cleanly (SIGTERM, then SIGKILL after ``timeout_s``); idempotent."""
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout_s)
        if self.process.is_alive():
            self.kill()
        self.conn.close()

    def _send(self, cmd: tuple[Any, ...]) -> None:
        with self._lock:
            self.conn.send(cmd)

    def __enter__(self) -> FakeGigECamera:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


def start_fake_camera(
    address: str,
    serial: str,
    frames: npt.NDArray[Any] | FrameProvider,
    *,
    size: tuple[int, int] | None = None,
    packet_loss: float = 0.0,
    skip_frames: Iterable[int] = (),
    line_pulses: int | None = None,
    line_rate_hz: float = 50.0,
    trigger_tick_hz: float = 200.0,
    ready_timeout_s: float = READY_TIMEOUT_S,
    exposure_reference_us: float | None = None,
) -> FakeGigECamera:
    """Start a fake GigE Vision camera in its own process, listening on ``address`` port 3956.

    Parameters
    ----------
    address : str
        A loopback address that belongs to an interface (127.0.0.1, or 127.0.0.2+ inside a
        :class:`LoopbackLab`).
    serial : str
        The camera's serial number (at most 15 characters).
    frames : ndarray, shape (F, H, W), uint8 or uint16, or callable
        The frames to serve, frame ``i`` of each acquisition being ``frames[i % F]``; or a picklable
        ``frame_provider(index) -> (H, W) array`` (then ``size`` = (width, height) in px is required).
    packet_loss : float
        Fraction (0..1) of GVSP packets dropped (the fake does not resend).
    skip_frames : iterable of int
        Frames (indices within an acquisition) whose packets are all dropped.
    line_pulses, line_rate_hz : int or None, float
        In ``TriggerSource=Line1``: how many pulses the simulated trigger controller fires per acquisition
        (all of ``frames`` when None) and how fast (Hz).
    trigger_tick_hz : float
        How often the fake checks for triggers (Hz); its frame latency is up to one tick.
    exposure_reference_us : float, optional
        The ``ExposureTime`` (µs) at which ``frames`` hold: at another exposure each frame's values scale with
        ``ExposureTime / exposure_reference_us`` (rounded, clipped at the pixel format's full scale). None:
        served as they are, whatever the exposure.

    Returns
    -------
    FakeGigECamera
        The running camera; :meth:`FakeGigECamera.stop` ends it.
    """
    if isinstance(frames, np.ndarray):
        provider: FrameProvider = StackProvider(frames)
        height, width = frames.shape[1:]
        if line_pulses is None:
            line_pulses = len(frames)
    else:
        if size is None:
            raise CameraError("fake camera: a frame provider needs size=(width, height)")
        provider = frames
        width, height = size
    spec = _Spec(
        address,
        serial,
        provider,
        width,
        height,
        packet_loss,
        frozenset(skip_frames),
        line_pulses,
        line_rate_hz,
        trigger_tick_hz,
        exposure_reference_us,
    )
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_serve, args=(spec, child), name=f"fake-gige-{address}", daemon=True)
    process.start()
    child.close()
    handle = FakeGigECamera(address, serial, width, height, process, parent)
    if not parent.poll(ready_timeout_s):
        handle.stop()
        raise CameraError(f"fake camera {address}: did not start within {ready_timeout_s:.0f} s")
    try:
        reply = parent.recv()
    except EOFError:
        reply = ("error", f"process exited with code {process.exitcode}")
    if reply[0] != "ready":
        handle.stop()
        raise CameraError(f"fake camera {address}: {reply[1]}")
    return handle


# --- a private network namespace -------------------------------------------------------------------------


class LoopbackLab:
    """A thread in a private network namespace with loopback addresses 127.0.0.2, 127.0.0.3, ...

    Work handed to :meth:`call` runs in that thread; sockets, threads and processes it creates live in the
    namespace, so fake cameras get their own addresses and nothing (not even a discovery broadcast) can
    reach a real network. Without the privilege to create a namespace (``CAP_SYS_ADMIN``), the lab runs in
    the host's namespace and offers only 127.0.0.1 (:attr:`isolated` is False).

    Parameters
    ----------
    n_addresses : int
        How many extra loopback addresses to create (127.0.0.2 onwards).
    isolate : bool
        False runs in the host's namespace (only 127.0.0.1), as when the privilege is missing.
    """

    def __init__(self, n_addresses: int = 4, *, isolate: bool = True) -> None:
        self.n_addresses = n_addresses
        self.isolate = isolate
        self.isolated = False
        self.addresses: list[str] = ["127.0.0.1"]
        self.setup_error = ""
        self._jobs: queue.Queue[tuple[Callable[[], Any], Future[Any]] | None] = queue.Queue()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> LoopbackLab:
        ready = threading.Event()
        self._thread = threading.Thread(target=self._main, args=(ready,), name="loopback-lab", daemon=True)
        self._thread.start()
        ready.wait()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._jobs.put(None)
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run ``fn(*args, **kwargs)`` in the lab's thread and return its result (or raise its exception)."""
        done: Future[T] = Future()
        self._jobs.put((lambda: fn(*args, **kwargs), done))
        return done.result()

    def _main(self, ready: threading.Event) -> None:
        try:
            self._enter_namespace()
        finally:
            ready.set()
        while True:
            job = self._jobs.get()
            if job is None:
                return
            fn, done = job
            try:
                done.set_result(fn())
            except BaseException as exc:
                done.set_exception(exc)

    def _enter_namespace(self) -> None:
        if not self.isolate:
            self.setup_error = "isolation not requested"
            return
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.unshare(_CLONE_NEWNET) != 0:
            self.setup_error = f"unshare(CLONE_NEWNET): {os.strerror(ctypes.get_errno())}"
            return
        extra = [f"127.0.0.{k}" for k in range(2, 2 + self.n_addresses)]
        commands = [["ip", "link", "set", "lo", "up"]] + [
            ["ip", "addr", "add", f"{a}/8", "dev", "lo"] for a in extra
        ]
        for cmd in commands:
            result = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if result.returncode != 0:
                self.setup_error = f"{' '.join(cmd)}: {result.stderr.strip()}"
                return
        self.isolated = True
        self.addresses = extra


# --- scan3d simulate-camera ----------------------------------------------------------------------------


def serve_fake_camera(source: FrameSource, address: str, serial: str, *, packet_loss: float = 0.0) -> int:
    """``scan3d simulate-camera``: serve ``source``'s frames as a GigE Vision camera on ``address`` port 3956.

    Runs in the foreground (this process) until Ctrl-C or SIGTERM.

    Parameters
    ----------
    source : FrameSource
        The frames; frame ``i`` of each acquisition is ``source.render(i % source.frame_count)``.
    address : str
        A loopback address that belongs to an interface.
    serial : str
        The serial number the camera reports (at most 15 characters).
    packet_loss : float
        Fraction (0..1) of GVSP packets to drop.

    Returns
    -------
    int
        The exit status: 0 after Ctrl-C, 1 (with one line on stderr) when the camera cannot start.
    """
    width, height = source.frame_size
    count = source.frame_count
    try:
        dtype = np.asarray(source.render(0)).dtype
        spec = _Spec(address, serial, lambda i: source.render(i % count), width, height, packet_loss,
                     frozenset(), count)
        server = _Server(spec, None)
    except Exception as exc:  # the CLI reports every failure in one line
        print(f"scan3d simulate-camera: {exc}", file=sys.stderr)
        return 1
    print(f"serving {count} frames of {width}x{height} {dtype} as GigE Vision camera {serial} on {address}; "
          "Ctrl-C stops", flush=True)
    with contextlib.suppress(KeyboardInterrupt):
        server.run()
    return 0
