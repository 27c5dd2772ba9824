"""The ``lightcrafter4500`` projector backend: a TI DLP LightCrafter 4500 (DLPC350) over USB HID.

The device is found by its USB ids 0x0451:0x6401 (optionally by serial number) with pyusb; the kernel's
HID driver is detached, the configuration set, and 64-byte reports are written to endpoint 0x01 and read
from 0x81 (:mod:`appliance.hardware.dlpc350` encodes them). Every request asks for a reply, so a NACK
surfaces at once as a :class:`~appliance.errors.ProjectorError` naming the command. Every write passes
:func:`~appliance.hardware.dlpc350.check_not_flash` first: the flash is never touched.

How a scan3d :class:`~appliance.patterns.sequence.Sequence` maps onto the DLPC350 (:func:`pack_video_frames`):

- Each 24-bit RGB image carries up to 24 one-bit patterns in bit planes G0..G7, R0..R7, B0..B7 (pattern
  numbers 0..23, filled in this order); an 8-bit frame (phase) takes a whole free channel (pattern 0 = G,
  1 = R, 2 = B at bit depth 8). Gray, white and black frames are 1-bit planes; phase frames are 8-bit.
- At most ``patterns_per_image`` patterns share one image: for the video source that is
  ``video_frame_period_us // period_us`` (the patterns of one video frame must fit between two VSYNCs).
- One LUT entry per frame, in sequence order, LED white. The first entry of every image sets *buffer
  swap* (next video frame / next flash image); for the video source it is triggered by the VSYNC
  (trigger type external-positive in trigger mode 0) and the others continue from the previous pattern,
  and the last entry of every image sets *insert black* (the post-vector the DLPC350 wants before an
  externally triggered pattern). For the flash source every entry is internally triggered.
- So frame ``i`` of the sequence is LUT entry ``i`` and TRIG_OUT1 pulse ``i``: the cameras capture the
  sequence in order.

TRIG_OUT1/TRIG_OUT2 delays (``trigger_out1_delay_steps``) are written as raw register values, 107.2 ns per
step; on the DLPC350 the register's zero-delay point is not 0 (check the programmer's guide for your
firmware; 0xBB is documented as 0 µs) and the fake accepts 0..0xD5.

Video source: the backend shows the packed images itself, one per frame, on the display wired to the
projector's HDMI input (``video_output``; a :class:`~appliance.hardware.display.Screen`, pygame by default).
Flash source: the same packed images must already be in flash at indices ``flash_first_image`` onwards
(program them with TI's GUI on a bench; the appliance never writes flash); no display is opened.

Video timing (:func:`video_flip_plan`, :meth:`LightCrafter4500.start`). Flip ``k`` presents the back buffer
and returns at vsync ``V_k`` (the pygame screen makes SDL's kmsdrm driver wait for the page flip); the frame
then crosses HDMI during ``[V_k, V_k+1)``. The DLPC350 displays at ``V_m`` the frame that arrived
``L = video_latency_frames`` frames earlier, and a started sequencer begins at the first VSYNC after the start
command. So, after a few black flips that locate the vsyncs (:data:`SYNC_FLIPS`) and counting flips from there,
with ``s = max(L - 1, 0)``: image ``j`` goes out on flip ``s + 1 - L + j``; the start command (0x1A24 = 2) is sent
right after flip ``s`` returns, from the flip thread (the backend's one worker thread, which owns the USB link),
and must complete within half a frame; the sequencer then shows image ``j`` at ``V_(s+1+j)``. ``L + 1`` black
flips end the sequence, so start() returns when the last image has been displayed. For L = 1: image ``j`` on
flip ``j``, start after flip 0. A missed vsync (a flip interval over 1.5 frames), a flip under half a frame
(no vsync) or a late start command puts the patterns out of step: start() stops the sequencer, shows black and
raises.

The one-frame latency is TI's documented video-input-to-display delay, not measured on this appliance: confirm
it on a real unit (camera frames captured on TRIG_OUT1 against the expected patterns) and set
``video_latency_frames`` if it differs.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import importlib.util
import logging
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from appliance.config.backends import LightCrafter4500Config, VideoOutputConfig
from appliance.errors import BackendUnavailableError, PatternError, ProjectorError
from appliance.hardware import dlpc350 as proto
from appliance.hardware.display import DisplayTiming, PygameScreen, Screen, show_black
from appliance.hardware.dlpc350 import Cmd, Led, LutEntry, Trigger
from appliance.patterns.render import render_frame
from appliance.patterns.sequence import BlackFrame, GrayFrame, PhaseFrame, Sequence, WhiteFrame

try:
    import usb.core
    import usb.util
except ImportError:  # pragma: no cover - pyusb is a core dependency
    usb = None

_log = logging.getLogger(__name__)
_T = TypeVar("_T")

# Module-level so tests can shorten them.
USB_TIMEOUT_MS = 1000
WAKE_S = 2.0
VALIDATE_POLL_S = 0.01
VALIDATE_TIMEOUT_S = 2.0
VIDEO_LOCKED_BIT = 1 << 3
"""0x1A0C main status: external video locked (the DLPC350 sees a stable HDMI input)."""
SYNC_FLIPS = 3
"""Video source: black flips before the sequence's own, to locate the vsyncs (the start command is timed from them)."""
flip_clock_ns: Callable[[], int] = time.monotonic_ns
"""Clock of the flip and start-command times (CLOCK_MONOTONIC, ns); tests drive it from a virtual display."""

_UDEV_HINT = (
    'add a udev rule: SUBSYSTEM=="usb", ATTR{idVendor}=="0451", ATTR{idProduct}=="6401", '
    'MODE="0660", GROUP="plugdev" and put the service user in plugdev'
)
_CHANNEL_RGB_INDEX = (1, 0, 2)  # DLPC350 plane order G, R, B -> index in an RGB image


# --- sequence -> images + LUT -------------------------------------------------------------------------


@dataclass
class VideoPacking:
    """Packed 24-bit images and the pattern LUT that shows a sequence on the DLPC350.

    Attributes
    ----------
    images : list of ndarray, shape (H, W, 3), uint8
        RGB images (channel 0 = red); bit planes as described in the module docstring.
    entries : list of LutEntry
        One LUT entry per sequence frame, in order.
    image_of_frame : list of int
        Index into ``images`` of each sequence frame.
    """

    images: list[npt.NDArray[np.uint8]] = field(default_factory=list)
    entries: list[LutEntry] = field(default_factory=list)
    image_of_frame: list[int] = field(default_factory=list)

    @property
    def bit_depths(self) -> frozenset[int]:
        """The bit depths used by the LUT."""
        return frozenset(e.bit_depth for e in self.entries)


def _frame_bit_depth(frame: object) -> int:
    if isinstance(frame, GrayFrame | WhiteFrame | BlackFrame):
        return 1
    if isinstance(frame, PhaseFrame):
        return 8
    raise PatternError(f"lightcrafter4500: frame {frame!r} cannot be shown: only gray, phase, white, black")


def _free_slot(fill: list[int], depth: int) -> int | None:
    """Channel (0 G, 1 R, 2 B) with room for a pattern of ``depth`` bits, or None."""
    for c in range(3):
        if (depth == 1 and fill[c] < 8) or (depth == 8 and fill[c] == 0):
            return c
    return None


def pack_video_frames(
    sequence: Sequence, *, patterns_per_image: int = 24, video_source: bool = True, led: Led = Led.WHITE
) -> VideoPacking:
    """Pack a sequence into 24-bit images and the matching DLPC350 pattern LUT.

    Parameters
    ----------
    sequence : Sequence
        Gray, white, black (1-bit) and phase (8-bit) frames; the images have the sequence's size.
    patterns_per_image : int
        Most patterns shown from one image (video: ``video_frame_period_us // period_us``), 1..24.
    video_source : bool
        LUT triggers for the video port (VSYNC-triggered first pattern per image, the rest continue)
        rather than the flash (every pattern internally triggered).
    led : Led
        LED select of every entry.

    Returns
    -------
    VideoPacking
        ``images`` (list of (H, W, 3) uint8 RGB) and one ``LutEntry`` per frame.
    """
    if not 1 <= patterns_per_image <= 24:
        raise PatternError(f"pack_video_frames: patterns_per_image = {patterns_per_image}: must be 1..24")
    out = VideoPacking()
    fill = [8, 8, 8]
    count = patterns_per_image
    first_trigger = Trigger.EXTERNAL_POSITIVE if video_source else Trigger.INTERNAL
    for frame in sequence:
        depth = _frame_bit_depth(frame)
        channel = _free_slot(fill, depth) if count < patterns_per_image else None
        new_image = channel is None
        if channel is None:
            if out.entries and video_source:
                out.entries[-1] = _with_insert_black(out.entries[-1])
            out.images.append(np.zeros((sequence.height, sequence.width, 3), np.uint8))
            fill, count = [0, 0, 0], 0
            channel = _free_slot(fill, depth)
            assert channel is not None
        plane_img = out.images[-1][:, :, _CHANNEL_RGB_INDEX[channel]]
        rendered = render_frame(frame, sequence.width, sequence.height)
        if depth == 1:
            plane_img |= (rendered > 127).astype(np.uint8) << np.uint8(fill[channel])
            pattern = channel * 8 + fill[channel]
            fill[channel] += 1
        else:
            plane_img[...] = rendered
            pattern = channel
            fill[channel] = 8
        count += 1
        trigger = first_trigger if new_image or not video_source else Trigger.CONTINUE
        out.entries.append(LutEntry(pattern, depth, led, trigger, buffer_swap=new_image))
        out.image_of_frame.append(len(out.images) - 1)
    if out.entries and video_source:
        out.entries[-1] = _with_insert_black(out.entries[-1])
    return out


def _with_insert_black(e: LutEntry) -> LutEntry:
    return LutEntry(e.pattern, e.bit_depth, e.led, e.trigger, e.invert, True, e.buffer_swap, e.trig_out_prev)


@dataclass(frozen=True)
class VideoFlipPlan:
    """What each flip of a video-source sequence presents, and when the sequencer is started.

    Attributes
    ----------
    images : list of int
        Index of the packed image drawn before each flip (-1 = black).
    start_after_flip : int
        The start command is sent right after this flip returns.
    in_step_until : int
        Every flip up to this one (the last image's flip, or the start flip if later) must follow the previous
        one by exactly one frame.
    """

    images: list[int]
    start_after_flip: int
    in_step_until: int


def video_flip_plan(n_images: int, latency_frames: int, sync_flips: int = 0) -> VideoFlipPlan:
    """The flips that show ``n_images`` packed images to a DLPC350 with ``latency_frames`` of input latency.

    After ``sync_flips`` black flips, and counting flips from there: image ``j`` goes out on flip
    ``s + 1 - L + j`` with ``s = max(L - 1, 0)``, the start command right after flip ``s``, then ``L + 1``
    black frames (see the module docstring).

    Parameters
    ----------
    n_images : int
        Packed images of the sequence (>= 1).
    latency_frames : int
        Frames from an HDMI frame's arrival to the sequencer showing it (>= 0).
    sync_flips : int
        Black flips first (>= 0).

    Returns
    -------
    VideoFlipPlan
        Flip indices count every flip, the black ones first included.
    """
    if n_images < 1 or latency_frames < 0 or sync_flips < 0:
        raise ProjectorError(
            f"video_flip_plan: n_images = {n_images}, latency_frames = {latency_frames}, sync_flips = "
            f"{sync_flips}: need >= 1, >= 0, >= 0"
        )
    start = sync_flips + max(latency_frames - 1, 0)
    first = start + 1 - latency_frames  # the flip that presents image 0
    images = [-1] * first + list(range(n_images)) + [-1] * (latency_frames + 1)
    return VideoFlipPlan(images, start, max(first + n_images - 1, start))


# --- USB ----------------------------------------------------------------------------------------------


def _require_pyusb() -> None:
    if usb is None:
        raise BackendUnavailableError(
            "lightcrafter4500: pyusb is not installed; install it with: pip install pyusb "
            "(and apt-get install libusb-1.0-0)"
        )


def find_devices(usb_backend: Any = None) -> list[Any]:
    """Every LightCrafter 4500 (USB 0451:6401) on the bus, as pyusb devices."""
    _require_pyusb()
    try:
        return list(
            usb.core.find(
                find_all=True, idVendor=proto.VENDOR_ID, idProduct=proto.PRODUCT_ID, backend=usb_backend
            )
        )
    except usb.core.NoBackendError as exc:
        raise BackendUnavailableError(
            f"lightcrafter4500: no libusb backend for pyusb ({exc}); apt-get install libusb-1.0-0"
        ) from exc


def _serial_of(dev: Any) -> str:
    try:
        return str(dev.serial_number)
    except (ValueError, usb.core.USBError):
        return "?"


def _describe(dev: Any) -> str:
    return f"bus {getattr(dev, 'bus', '?')} address {getattr(dev, 'address', '?')}"


def find_device(serial: str | None = None, usb_backend: Any = None) -> Any:
    """The LightCrafter 4500 to use: the only one, or the one with USB serial ``serial``."""
    devices = find_devices(usb_backend)
    if not devices:
        raise ProjectorError(
            "lightcrafter4500: no LightCrafter 4500 (USB 0451:6401) found; check its USB cable and power "
            "(lsusb should list 0451:6401)"
        )
    if serial is None:
        if len(devices) > 1:
            serials = ", ".join(_serial_of(d) for d in devices)
            raise ProjectorError(
                f"lightcrafter4500: {len(devices)} LightCrafter 4500 units found (serials {serials}); "
                "set projector.usb_serial to pick one"
            )
        return devices[0]
    for dev in devices:
        if _serial_of(dev) == serial:
            return dev
    serials = ", ".join(_serial_of(d) for d in devices)
    raise ProjectorError(
        f"lightcrafter4500: usb_serial = {serial!r}: no such unit (found {serials}); fix projector.usb_serial"
    )


class _Link:
    """Blocking request/reply over the HID endpoints (runs only in the backend's executor thread)."""

    def __init__(self, dev: Any, where: str) -> None:
        self.dev = dev
        self.where = where
        self.seq = 0

    def setup(self) -> None:
        try:
            for intf in self._interfaces():
                if self.dev.is_kernel_driver_active(intf):
                    self.dev.detach_kernel_driver(intf)
            if not self._configured():
                self.dev.set_configuration()
        except usb.core.USBError as exc:
            hint = _UDEV_HINT if exc.errno == errno.EACCES else "unplug and replug the projector's USB cable"
            raise ProjectorError(f"{self.where}: cannot claim the USB device: {exc}; {hint}") from exc

    def _configured(self) -> bool:
        # Setting the configuration again would reset a device another process is using.
        try:
            self.dev.get_active_configuration()
        except (usb.core.USBError, AttributeError):
            return False
        return True

    def _interfaces(self) -> Iterator[int]:
        try:
            numbers = {intf.bInterfaceNumber for cfg in self.dev for intf in cfg}
        except (TypeError, AttributeError):  # a device object that does not list its descriptors
            numbers = {0}
        return iter(sorted(numbers))

    def release(self) -> None:
        if usb is not None and isinstance(self.dev, usb.core.Device):
            usb.util.dispose_resources(self.dev)

    def transact(self, code: int, data: bytes = b"", *, read: bool = False) -> bytes:
        """Send one request and return the reply's data; NACK or a bad reply raises ProjectorError."""
        proto.check_not_flash(code)  # the flash guard: before anything reaches the wire
        self.seq = (self.seq + 1) & 0xFF
        name = proto.command_name(code)
        try:
            for report in proto.encode_request(code, data, read=read, seq=self.seq):
                self.dev.write(proto.EP_OUT, report, USB_TIMEOUT_MS)
            first = bytes(self.dev.read(proto.EP_IN, proto.REPORT_SIZE, USB_TIMEOUT_MS))
            reports = [first]
            for _ in range(proto.reports_needed(proto.message_length(first)) - 1):
                reports.append(bytes(self.dev.read(proto.EP_IN, proto.REPORT_SIZE, USB_TIMEOUT_MS)))
        except usb.core.USBTimeoutError as exc:
            raise ProjectorError(
                f"{self.where}: no reply to {name} within {USB_TIMEOUT_MS} ms; check the USB cable and "
                "that the projector is powered"
            ) from exc
        except usb.core.USBError as exc:
            raise ProjectorError(f"{self.where}: USB error on {name}: {exc}; replug the projector") from exc
        try:
            reply = proto.decode_reply(reports)
        except ValueError as exc:
            raise ProjectorError(f"{self.where}: malformed reply to {name}: {exc}") from exc
        if reply.seq != self.seq:
            raise ProjectorError(
                f"{self.where}: reply to {name} has sequence {reply.seq}, expected {self.seq}"
            )
        if reply.nack:
            raise ProjectorError(
                f"{self.where}: the DLPC350 refused {name} (NACK) with data {data.hex(' ') or 'none'}; "
                "check the command, its length and the projector's state (standby? sequence running?)"
            )
        return reply.data

    def read1(self, code: int) -> int:
        data = self.transact(code, read=True)
        if not data:
            raise ProjectorError(f"{self.where}: empty reply to {proto.command_name(code)}")
        return data[0]


@dataclass(frozen=True)
class LightCrafterStatus:
    """Decoded status of the DLPC350: hardware problems (empty = healthy) and main states."""

    hardware_byte: int
    main_byte: int
    problems: list[str]
    states: list[str]

    def describe(self) -> str:
        """One line, e.g. ``'healthy; sequencer running, external video locked'``."""
        head = "healthy" if not self.problems else "PROBLEMS: " + ", ".join(self.problems)
        return f"{head}; {', '.join(self.states) or 'idle'}"


class LightCrafter4500:
    """The ``lightcrafter4500`` :class:`~appliance.hardware.base.Projector`.

    Parameters
    ----------
    config : LightCrafter4500Config
        Backend options.
    name : str
        Name used in messages.
    device : object, optional
        A pyusb ``usb.core.Device`` (or an object with its ``write``/``read``/``set_configuration``/
        kernel-driver methods) to use instead of searching the bus.
    usb_backend : object, optional
        A pyusb backend for the search (tests: :class:`~appliance.fakes.dlpc350.FakeUsbBackend`).
    screen_factory : callable, optional
        Video source: makes the :class:`~appliance.hardware.display.Screen` on the projector's HDMI input from
        ``config.video_output`` (default: pygame); tests pass a fake. Never called for the flash source.

    Attributes
    ----------
    flip_times_ns : list of int
        Video source: CLOCK_MONOTONIC time at which each flip of the last start() returned (ns).
    start_flip : int
        Video source: index in ``flip_times_ns`` of the flip after which the start command was sent (-1 = not
        sent).
    start_delay_us : float or None
        Video source: time from that flip's vsync (estimated from all flips before it) to the start command's
        reply (µs).
    """

    def __init__(
        self,
        config: LightCrafter4500Config,
        *,
        name: str = "projector",
        device: Any = None,
        usb_backend: Any = None,
        screen_factory: Callable[[VideoOutputConfig], Screen] | None = None,
    ) -> None:
        _require_pyusb()
        self.name = name
        self.config = config
        self._device = device
        self._usb_backend = usb_backend
        self._screen_factory = screen_factory
        self._link: _Link | None = None
        self._screen: Screen | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._prepared_images = 0
        self._stopping = threading.Event()
        self.packing: VideoPacking | None = None
        self.last_status: LightCrafterStatus | None = None
        self.flip_times_ns: list[int] = []
        self.start_flip = -1
        self.start_delay_us: float | None = None

    @property
    def where(self) -> str:
        """``projector 'name' (lightcrafter4500, bus 1 address 7)``."""
        dev = self._link.dev if self._link else self._device
        return f"projector {self.name!r} (lightcrafter4500{', ' + _describe(dev) if dev is not None else ''})"

    @property
    def video_frames(self) -> list[npt.NDArray[np.uint8]]:
        """Images to show on the HDMI input for the loaded sequence (video source), (H, W, 3) uint8 RGB."""
        return self.packing.images if self.packing else []

    async def _run(self, fn: Callable[..., _T], *args: Any) -> _T:
        if self._executor is None:
            raise ProjectorError(f"{self.where}: not open; call open() first")
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

    # --- Projector protocol -------------------------------------------------------------------------

    async def open(self) -> None:
        """Find the device, claim it, wake it from standby, check its health and stop any sequence.

        With the video source, also open the display on the projector's HDMI input and show black. Every
        USB and display call runs in the backend's one worker thread (SDL wants its window used from one
        thread; the USB link is never used concurrently).
        """
        if self._link is not None:
            return
        factory = self._screen_factory
        if self.config.source == "video" and factory is None:
            if importlib.util.find_spec("pygame") is None:
                raise BackendUnavailableError(
                    f"{self.where}: source: video shows the patterns on the projector's HDMI input with pygame "
                    "(SDL2), which is not installed: install it with: pip install pygame (or use source: flash)"
                )
            factory = _pygame_screen
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"lcr4500-{self.name}")
        try:
            await self._run(self._open_sync)
            if self.config.source == "video":
                assert factory is not None
                await self._run(self._open_screen_sync, factory)
        except BaseException:
            try:
                await self._run(self._abandon_sync)
            finally:
                await self._shutdown_executor()
            raise

    def _open_screen_sync(self, factory: Callable[[VideoOutputConfig], Screen]) -> None:
        self._screen = factory(self.config.video_output)
        show_black(self._screen)

    def _abandon_sync(self) -> None:
        """Undo a partial open: close the display, release the USB device."""
        try:
            self._close_screen_sync()
        finally:
            if self._link is not None:
                self._link.release()

    def _open_sync(self) -> None:
        dev = (
            self._device
            if self._device is not None
            else find_device(self.config.usb_serial, self._usb_backend)
        )
        link = _Link(dev, f"projector {self.name!r} (lightcrafter4500, {_describe(dev)})")
        link.setup()
        self._link = link
        try:
            if link.read1(Cmd.POWER_CONTROL):
                _log.info("%s: waking from standby", link.where)
                link.transact(Cmd.POWER_CONTROL, b"\x00")
                time.sleep(WAKE_S)
            status = self._status_sync()
            if status.problems:
                raise ProjectorError(
                    f"{link.where}: unhealthy after open: {status.describe()}; power-cycle it"
                )
            link.transact(Cmd.SEQUENCE_CONTROL, b"\x00")
        except BaseException:
            link.release()
            raise

    async def load(self, sequence: Sequence) -> None:
        """Configure the pattern sequence (documented DLPC350 order) and validate it on the device.

        With the video source, the packed images are then converted for the display; their size must be the
        display's mode exactly (each colour bit is a pattern bit plane: nothing may rescale them).
        """
        packing = await asyncio.to_thread(self._plan, sequence)  # renders every pattern: not on the loop
        screen = self._screen
        if screen is not None and packing.images:
            height, width = packing.images[0].shape[:2]
            if (width, height) != tuple(screen.size):
                raise ProjectorError(
                    f"{self.where}: the packed images are {width}x{height} but the display on the HDMI input "
                    f"(video_output.display_index = {self.config.video_output.display_index}) is "
                    f"{screen.size[0]}x{screen.size[1]}: generate the sequence at the display's size and set the "
                    "display mode to the projector's native size (nothing was sent to the projector)"
                )
        self._prepared_images = 0
        self.packing = packing
        await self._run(self._load_sync, packing)
        if screen is not None:
            await self._run(screen.prepare, packing.images)
            self._prepared_images = len(packing.images)

    def _plan(self, sequence: Sequence) -> VideoPacking:
        cfg = self.config
        video = cfg.source == "video"
        per_image = 24
        if video:
            per_image = min(24, cfg.video_frame_period_us // cfg.period_us)
            if per_image < 1:
                raise ProjectorError(
                    f"{self.where}: period_us = {cfg.period_us} is longer than video_frame_period_us = "
                    f"{cfg.video_frame_period_us}: with the video source every pattern must fit in one "
                    "video frame; lower period_us"
                )
        packing = pack_video_frames(sequence, patterns_per_image=per_image, video_source=video)
        problems = proto.check_exposure_period(cfg.exposure_us, cfg.period_us, packing.bit_depths)
        if problems:
            raise ProjectorError(
                f"{self.where}: exposure_us = {cfg.exposure_us}, period_us = {cfg.period_us}: "
                + "; ".join(problems)
                + "; fix projector.exposure_us / period_us (nothing was sent to the projector)"
            )
        if len(packing.entries) > proto.MAX_LUT_ENTRIES or len(packing.images) > proto.MAX_IMAGE_LUT_ENTRIES:
            raise ProjectorError(
                f"{self.where}: the sequence needs {len(packing.entries)} LUT entries and "
                f"{len(packing.images)} images: the DLPC350 holds at most {proto.MAX_LUT_ENTRIES} and "
                f"{proto.MAX_IMAGE_LUT_ENTRIES}; use fewer frames"
            )
        if not video and cfg.flash_first_image + len(packing.images) > 256:
            raise ProjectorError(
                f"{self.where}: flash_first_image = {cfg.flash_first_image} + {len(packing.images)} images "
                "exceeds flash image index 255"
            )
        for value in (*cfg.led_current, *cfg.trigger_out1_delay_steps):
            if not 0 <= value <= 255:
                raise ProjectorError(
                    f"{self.where}: LED current / trigger delay value {value}: must be 0..255"
                )
        return packing

    def _load_sync(self, packing: VideoPacking) -> None:
        cfg = self.config
        link = self._require_link()
        video = cfg.source == "video"
        n = len(packing.entries)
        link.transact(Cmd.SEQUENCE_CONTROL, b"\x00")
        link.transact(Cmd.DISPLAY_MODE, b"\x01")
        link.transact(Cmd.PATTERN_SOURCE, b"\x00" if video else b"\x03")
        link.transact(Cmd.LUT_CONTROL, proto.lut_control_data(n, False, n, len(packing.images)))
        link.transact(Cmd.EXPOSURE_PERIOD, proto.exposure_period_data(cfg.exposure_us, cfg.period_us))
        link.transact(Cmd.TRIGGER_MODE, b"\x00" if video else b"\x01")
        self._mailbox(link, 2, proto.encode_lut(packing.entries))
        if not video:
            first = cfg.flash_first_image
            self._mailbox(link, 1, bytes(range(first, first + len(packing.images))))
        rising, falling = cfg.trigger_out1_delay_steps
        link.transact(Cmd.TRIG_OUT1, bytes([0, rising, falling]))
        link.transact(Cmd.TRIG_OUT2, bytes([0, rising]))
        link.transact(Cmd.LED_ENABLE, b"\x08")
        link.transact(Cmd.LED_CURRENT, bytes(255 - x for x in cfg.led_current))
        self._validate_sync(link)

    @staticmethod
    def _mailbox(link: _Link, which: int, payload: bytes) -> None:
        link.transact(Cmd.MAILBOX_CONTROL, bytes([which]))
        link.transact(Cmd.MAILBOX_ADDRESS, b"\x00")
        link.transact(Cmd.MAILBOX_DATA, payload)
        link.transact(Cmd.MAILBOX_CONTROL, b"\x00")

    def _validate_sync(self, link: _Link) -> None:
        link.transact(Cmd.LUT_VALIDATE, b"\x00")
        deadline = time.monotonic() + VALIDATE_TIMEOUT_S
        while (status := link.read1(Cmd.LUT_VALIDATE)) & proto.VALIDATION_BUSY:
            if time.monotonic() > deadline:
                raise ProjectorError(
                    f"{link.where}: sequence validation still busy after {VALIDATE_TIMEOUT_S} s"
                )
            time.sleep(VALIDATE_POLL_S)
        errors = proto.decode_validation(status)
        if errors:
            raise ProjectorError(
                f"{link.where}: the DLPC350 rejected the sequence (validation 0x{status:02X}): "
                + "; ".join(errors)
            )

    async def start(self) -> None:
        """Start the validated sequence and check that the sequencer runs without errors.

        Flash source: start and return. Video source: show the packed images frame by frame in step with the
        sequencer (module docstring) and return when the last one has been displayed.

        Raises
        ------
        ProjectorError
            Video source: a missed vsync or a late start command put the patterns out of step (the sequencer
            is stopped and the display shows black), or the DLPC350 reports a problem after the sequence.
        """
        if self.config.source != "video":
            self.last_status = await self._run(self._start_sync)
            return
        screen = self._screen
        if screen is None or self._executor is None:
            raise ProjectorError(f"{self.where}: not open; call open() first")
        if not self._prepared_images:
            raise ProjectorError(f"{self.where}: no sequence loaded (load() not called or it failed); load one")
        self._stopping.clear()
        self.last_status = await self._run(self._present_sync, screen, self._prepared_images)

    def _present_sync(self, screen: Screen, n_images: int) -> LightCrafterStatus:
        link = self._require_link()
        cfg = self.config
        timing = DisplayTiming(cfg.video_output.refresh_hz, cfg.video_latency_frames, 1)
        plan = video_flip_plan(n_images, cfg.video_latency_frames, SYNC_FLIPS)
        self.flip_times_ns, self.start_flip, self.start_delay_us = [], -1, None
        try:
            link.transact(Cmd.SEQUENCE_CONTROL, b"\x00")  # stopped (not paused): the start begins at entry 0
            if not link.read1(Cmd.MAIN_STATUS) & VIDEO_LOCKED_BIT:
                raise ProjectorError(
                    f"{link.where}: no video signal is locked on the projector's HDMI input, so the packed "
                    f"patterns cannot reach it; check the cable and that video_output.display_index = "
                    f"{cfg.video_output.display_index} is the output wired to the projector, running at "
                    f"{cfg.video_output.refresh_hz:g} Hz"
                )
            problem = self._flip_sequence(screen, link, plan, timing)
        except BaseException:
            self._stop_and_black(link, screen)
            raise
        if problem is not None:
            self._stop_and_black(link, screen)
            raise ProjectorError(
                f"{link.where}: {problem}: the patterns went out of step with the projector's sequencer, so "
                "this scan's frames are not the expected patterns; the sequence was stopped. Scan again; if it "
                "recurs, reduce the system load (other processes, CPU frequency scaling) or check the display's "
                f"refresh rate (video_output.refresh_hz = {cfg.video_output.refresh_hz:g})"
            )
        status = self._status_sync()
        if status.problems:
            raise ProjectorError(f"{link.where}: after the sequence: {status.describe()}; reload the sequence")
        return status

    def _flip_sequence(
        self, screen: Screen, link: _Link, plan: VideoFlipPlan, timing: DisplayTiming
    ) -> str | None:
        """Run the flips of ``plan``; the first timing problem found, or None."""
        frame_ns = timing.frame_period_us * 1e3
        times = self.flip_times_ns
        for k, image in enumerate(plan.images):
            if self._stopping.is_set():
                return None
            screen.show(image)
            screen.flip()
            times.append(flip_clock_ns())
            if 0 < k <= plan.in_step_until:
                interval_ns = times[-1] - times[-2]
                if timing.dropped_flips(times[-2:]):
                    return (
                        f"missed vsync: flip {k} came {interval_ns / 1e3:.0f} µs after the previous one "
                        f"(frames of {frame_ns / 1e3:.0f} µs)"
                    )
                if interval_ns < frame_ns / 2:
                    return (
                        f"flip {k} came {interval_ns / 1e3:.0f} µs after the previous one, under half a frame "
                        f"({frame_ns / 1e3:.0f} µs): the display does not wait for vsync or runs faster than "
                        "refresh_hz"
                    )
            if k == plan.start_after_flip:
                link.transact(Cmd.SEQUENCE_CONTROL, b"\x02")
                done_ns = flip_clock_ns()
                # This flip's vsync: the earliest estimate from all flips so far (a thread can wake late after
                # a vsync, never early), so a late wake-up counts against the half-frame budget.
                vsync_ns = min(t + (k - i) * frame_ns for i, t in enumerate(times))
                self.start_flip = k
                self.start_delay_us = (done_ns - vsync_ns) / 1e3
                if done_ns - vsync_ns > frame_ns / 2:
                    return (
                        f"the start command completed {self.start_delay_us:.0f} µs after the vsync, over half a "
                        f"frame ({frame_ns / 2e3:.0f} µs), so the sequencer may have started a frame late"
                    )
        return None

    def _stop_and_black(self, link: _Link, screen: Screen) -> None:
        with contextlib.suppress(ProjectorError):
            link.transact(Cmd.SEQUENCE_CONTROL, b"\x00")
        show_black(screen)

    def _start_sync(self) -> LightCrafterStatus:
        link = self._require_link()
        link.transact(Cmd.SEQUENCE_CONTROL, b"\x02")
        status = self._status_sync()
        if status.problems:
            raise ProjectorError(f"{link.where}: after start: {status.describe()}; reload the sequence")
        return status

    async def set_intensity(self, intensity: float) -> None:
        """Dim the LEDs for the next pass of a multi-pass (HDR) capture: each LED's PWM value becomes
        ``round(intensity x led_current)`` of the configured one (the evaluation module takes 255 - x).

        Call it between passes, with the sequence stopped; ``load`` sets the configured (full) currents again.
        Light follows the PWM value about linearly; the decoder picks one pass per pixel, so a departure from
        that changes which pass a pixel takes, not its code.

        Raises
        ------
        ProjectorError
            ``intensity`` not in (0, 1], a dimmed LED whose PWM value would round to 0, or the device refusing.
        """
        if not (0.0 < intensity <= 1.0):
            raise ProjectorError(f"{self.where}: intensity {intensity}: must be in (0, 1] of the configured "
                                 "LED currents")  # fmt: skip
        pwm = [round(x * intensity) for x in self.config.led_current]
        if any(p == 0 < x for p, x in zip(pwm, self.config.led_current, strict=True)):
            least = 0.5 / max(1, min(x for x in self.config.led_current if x))
            raise ProjectorError(
                f"{self.where}: intensity {intensity:g} of led_current {list(self.config.led_current)} rounds an "
                f"LED to 0 (off); use an intensity above {least:.3g}"
            )
        await self._run(self._set_leds_sync, bytes(255 - p for p in pwm))

    def _set_leds_sync(self, data: bytes) -> None:
        self._require_link().transact(Cmd.LED_CURRENT, data)

    async def stop(self) -> None:
        """Stop the sequence and, with the video source, show black (the projector stays awake)."""
        self._stopping.set()  # ends a running video presentation at its next frame
        if self._link is not None:
            await self._run(self._stop_sync)

    def _stop_sync(self) -> None:
        try:
            self._require_link().transact(Cmd.SEQUENCE_CONTROL, b"\x00")
        finally:
            if self._screen is not None:
                show_black(self._screen)

    async def close(self) -> None:
        """Stop, put the projector in standby, release the USB device and the display; idempotent."""
        if self._executor is None:
            return
        self._stopping.set()
        try:
            if self._link is not None:
                await self._run(self._close_sync)
        finally:
            try:
                await self._run(self._close_screen_sync)
            finally:
                await self._shutdown_executor()

    def _close_screen_sync(self) -> None:
        screen, self._screen, self._prepared_images = self._screen, None, 0
        if screen is not None:
            screen.close()

    async def _shutdown_executor(self) -> None:
        executor, self._executor, self._link = self._executor, None, None
        if executor is not None:
            await asyncio.to_thread(executor.shutdown, True)  # joins the idle USB thread off the loop

    def _close_sync(self) -> None:
        link = self._require_link()
        try:
            link.transact(Cmd.SEQUENCE_CONTROL, b"\x00")
            link.transact(Cmd.POWER_CONTROL, b"\x01")
        finally:
            link.release()

    # --- extras -------------------------------------------------------------------------------------

    async def status(self) -> LightCrafterStatus:
        """Read and decode the hardware (0x1A0A) and main (0x1A0C) status."""
        self.last_status = await self._run(self._status_sync)
        return self.last_status

    def _status_sync(self) -> LightCrafterStatus:
        link = self._require_link()
        hw = link.read1(Cmd.HW_STATUS)
        main = link.read1(Cmd.MAIN_STATUS)
        return LightCrafterStatus(hw, main, proto.decode_hardware_status(hw), proto.decode_main_status(main))

    async def command(self, code: int, data: bytes = b"", *, read: bool = False) -> bytes:
        """Send one raw command (maintenance); flash commands are refused before reaching the wire."""
        proto.check_not_flash(code)
        return await self._run(functools.partial(self._require_link().transact, code, data, read=read))

    def _require_link(self) -> _Link:
        if self._link is None:
            raise ProjectorError(f"{self.where}: not open; call open() first")
        return self._link


def _pygame_screen(cfg: VideoOutputConfig) -> Screen:
    return PygameScreen(cfg.output, cfg.display_index, flip_at_scanout=True)


def probe_lightcrafter(usb_backend: Any = None) -> str:
    """One line for ``scan3d devices``: the LightCrafter 4500 units on USB and their status.

    Reads only the status registers (no configuration change); never raises.
    """
    if usb is None:
        return "lightcrafter4500: pyusb not installed (pip install pyusb)"
    try:
        devices = find_devices(usb_backend)
    except BackendUnavailableError as exc:
        return str(exc)
    if not devices:
        return "lightcrafter4500: no LightCrafter 4500 (USB 0451:6401) found"
    parts = []
    for dev in devices:
        link = _Link(dev, f"LightCrafter 4500 at {_describe(dev)}")
        try:
            link.setup()
            hw, main = link.read1(Cmd.HW_STATUS), link.read1(Cmd.MAIN_STATUS)
            st = LightCrafterStatus(
                hw, main, proto.decode_hardware_status(hw), proto.decode_main_status(main)
            )
            parts.append(f"{_describe(dev)} serial {_serial_of(dev)}: {st.describe()}")
        except ProjectorError as exc:
            parts.append(f"{_describe(dev)}: {exc}")
        finally:
            link.release()
    return f"lightcrafter4500: {len(devices)} found: " + " | ".join(parts)
