"""A fake TI DLP LightCrafter 4500 (DLPC350) behind a pyusb backend, for tests without the projector.

:class:`FakeDLPC350` is the device: it parses every 64-byte HID report the host writes, keeps the
controller's state (standby, display mode, pattern source, trigger mode, exposure/period, LUT control,
mailbox, pattern and image LUTs, validation result, sequencer, LEDs, trigger outputs), answers reads,
NACKs what the device would refuse (unknown command, wrong length, value out of range, a write in the
wrong state) and validates sequences with its own implementation of the device's rules, setting the
0x1A1A error bits. Every request is recorded in :attr:`FakeDLPC350.log`. A flash-programming command
is a test failure: it is recorded in :attr:`FakeDLPC350.flash_violations` and raises
:class:`FlashCommandError` (an ``AssertionError``) into the host.

:class:`FakeUsbBackend` is a pyusb ``IBackend`` that enumerates fake devices, so the real
``usb.core.find(..., backend=FakeUsbBackend(fake))`` and ``usb.core.Device`` code paths (descriptors,
configuration, kernel-driver detach, interface claim, interrupt transfers, string descriptors) run
unchanged in tests.
"""

from __future__ import annotations

import errno
import struct
from collections import deque
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import usb.backend
import usb.core

from appliance.hardware import dlpc350 as proto
from appliance.hardware.dlpc350 import Cmd

_HID_CLASS = 3
_STRINGS = {1: "Texas Instruments", 2: "DLPC350"}
_SERIAL_INDEX = 3
_MAX_TRIGGER_DELAY = 0xD5

_CONFIG_COMMANDS = frozenset(
    {
        Cmd.DISPLAY_MODE,
        Cmd.PATTERN_SOURCE,
        Cmd.TRIGGER_MODE,
        Cmd.EXPOSURE_PERIOD,
        Cmd.LUT_CONTROL,
        Cmd.MAILBOX_CONTROL,
        Cmd.MAILBOX_ADDRESS,
        Cmd.MAILBOX_DATA,
        Cmd.LUT_VALIDATE,
        Cmd.TRIG_OUT1,
        Cmd.TRIG_OUT2,
        Cmd.TRIG_IN1_DELAY,
    }
)
_VALUE_LIMITS = {
    Cmd.POWER_CONTROL: 1,
    Cmd.DISPLAY_MODE: 1,
    Cmd.PATTERN_SOURCE: 3,
    Cmd.TRIGGER_MODE: 4,
    Cmd.SEQUENCE_CONTROL: 2,
    Cmd.MAILBOX_CONTROL: 2,
}


class FlashCommandError(AssertionError):
    """The host sent a flash-programming command to the fake projector (a test failure)."""


@dataclass
class LoggedRequest:
    """One host request as the fake received it."""

    request: proto.Request
    reports: list[bytes]
    nack: str | None = None

    @property
    def code(self) -> int:
        """Command code."""
        return self.request.code


@dataclass(eq=False)
class FakeDLPC350:
    """The device model; see the module docstring.

    Parameters
    ----------
    serial : str
        USB serial number string.
    busy_polls : int
        How many 0x1A1A reads after a validation still report busy (bit 7).
    """

    serial: str = "FAKE4500"
    busy_polls: int = 1
    bus: int = 1
    address: int = 7
    standby: bool = False
    display_mode: int = 0
    source: int = 0
    trigger_mode: int = 0
    exposure_us: int = 16667
    period_us: int = 16667
    lut_control: bytes = b"\x00\x00\x00\x00"
    mailbox: int = 0
    mailbox_address: int = 0
    pattern_lut: list[int] = field(default_factory=lambda: [0] * proto.MAX_LUT_ENTRIES)
    pattern_written: set[int] = field(default_factory=set)
    image_lut: list[int] = field(default_factory=lambda: [0] * proto.MAX_IMAGE_LUT_ENTRIES)
    image_written: set[int] = field(default_factory=set)
    validation: int = 0
    validated: bool = False
    sequencer: int = 0  # 0 stopped, 1 paused, 2 running
    led_current: bytes = b"\x97\x78\x7d"
    led_enable: int = 0x08
    trig_out1: bytes = b"\x00\xbb\xbb"
    trig_out2: bytes = b"\x00\xbb"
    trig_in1_delay: bytes = b"\x00\x00\x00\x00"
    hw_status_faults: int = 0
    """Extra 0x1A0A bits to report (fault injection), e.g. 0x04 for a DRC error."""
    video_locked: bool = True
    log: list[LoggedRequest] = field(default_factory=list)
    flash_violations: list[int] = field(default_factory=list)
    kernel_driver: dict[int, bool] = field(default_factory=lambda: {0: True})
    configuration: int = 0
    _partial: list[bytes] = field(default_factory=list)
    _out: deque[bytes] = field(default_factory=deque)
    _busy_left: int = 0

    # --- transport ----------------------------------------------------------------------------------

    def receive(self, report: bytes) -> None:
        """Take one 64-byte report from the host (OUT endpoint 0x01)."""
        self._partial.append(bytes(report))
        if proto.reports_needed(proto.message_length(self._partial[0])) > len(self._partial):
            return
        reports, self._partial = self._partial, []
        request = proto.decode_request(reports)
        entry = LoggedRequest(request, reports)
        self.log.append(entry)
        if proto.is_flash_command(request.code):
            self.flash_violations.append(request.code)
            raise FlashCommandError(f"the host sent flash command {proto.command_name(request.code)}")
        try:
            data = self._handle(request)
        except _Nack as nack:
            entry.nack = str(nack)
            self._out.extend(proto.encode_reply(request.seq, flags=request.flags, nack=True))
            return
        if request.wants_reply:
            self._out.extend(proto.encode_reply(request.seq, data, flags=request.flags))

    def send(self) -> bytes | None:
        """The next 64-byte report for the host (IN endpoint 0x81), or ``None`` if nothing is pending."""
        return self._out.popleft() if self._out else None

    def writes(self) -> list[tuple[int, bytes]]:
        """``(command, data)`` of every write received, in order."""
        return [(e.code, e.request.data) for e in self.log if not e.request.is_read]

    # --- command handling ---------------------------------------------------------------------------

    def _handle(self, req: proto.Request) -> bytes:
        spec = proto.COMMANDS.get(req.code)
        if spec is None:
            raise _Nack(f"unknown command 0x{req.code:04X}")
        if req.is_read:
            if spec.read_len is None:
                raise _Nack(f"{spec.name} cannot be read")
            return self._read(req.code)
        if spec.write_len is None:
            raise _Nack(f"{spec.name} cannot be written")
        if spec.write_len >= 0 and len(req.data) != spec.write_len:
            raise _Nack(f"{spec.name}: {len(req.data)} data bytes, expected {spec.write_len}")
        if self.standby and req.code != Cmd.POWER_CONTROL:
            raise _Nack("in standby: only power control and reads are accepted")
        if self.sequencer != 0 and req.code in _CONFIG_COMMANDS:
            raise _Nack(f"{spec.name} while the sequence runs: stop it first")
        limit = _VALUE_LIMITS.get(Cmd(req.code))
        if limit is not None and req.data[0] > limit:
            raise _Nack(f"{spec.name}: value {req.data[0]} out of range 0..{limit}")
        self._write(Cmd(req.code), req.data)
        return b""

    def _read(self, code: int) -> bytes:
        if code == Cmd.LUT_VALIDATE:
            if self._busy_left > 0:
                self._busy_left -= 1
                return bytes([proto.VALIDATION_BUSY])
            return bytes([self.validation])
        if code == Cmd.HW_STATUS:
            return bytes([0x01 | self.hw_status_faults])
        if code == Cmd.SYS_STATUS:
            return b"\x01"
        if code == Cmd.MAIN_STATUS:
            locked = self.video_locked and self.source == 0
            return bytes([int(self.standby) | (self.sequencer == 2) << 1 | locked << 3])
        values: dict[int, bytes] = {
            Cmd.POWER_CONTROL: bytes([self.standby]),
            Cmd.LED_CURRENT: self.led_current,
            Cmd.LED_ENABLE: bytes([self.led_enable]),
            Cmd.DISPLAY_MODE: bytes([self.display_mode]),
            Cmd.TRIG_OUT1: self.trig_out1,
            Cmd.TRIG_OUT2: self.trig_out2,
            Cmd.PATTERN_SOURCE: bytes([self.source]),
            Cmd.TRIGGER_MODE: bytes([self.trigger_mode]),
            Cmd.SEQUENCE_CONTROL: bytes([self.sequencer]),
            Cmd.EXPOSURE_PERIOD: proto.exposure_period_data(self.exposure_us, self.period_us),
            Cmd.LUT_CONTROL: self.lut_control,
            Cmd.MAILBOX_ADDRESS: bytes([self.mailbox_address]),
            Cmd.MAILBOX_CONTROL: bytes([self.mailbox]),
            Cmd.TRIG_IN1_DELAY: self.trig_in1_delay,
        }
        return values[code]

    def _write(self, code: Cmd, data: bytes) -> None:
        if code in _CONFIG_COMMANDS and code != Cmd.LUT_VALIDATE:
            self.validated = False
        if code == Cmd.POWER_CONTROL:
            self.standby = bool(data[0])
            if self.standby:
                self.sequencer = 0
        elif code == Cmd.DISPLAY_MODE:
            self.display_mode = data[0]
        elif code == Cmd.PATTERN_SOURCE:
            if data[0] == 2:
                raise _Nack("pattern source 2 is reserved")
            self.source = data[0]
        elif code == Cmd.TRIGGER_MODE:
            self.trigger_mode = data[0]
        elif code == Cmd.EXPOSURE_PERIOD:
            self.exposure_us, self.period_us = struct.unpack("<II", data)
        elif code == Cmd.LUT_CONTROL:
            if data[0] >= proto.MAX_LUT_ENTRIES or data[3] >= proto.MAX_IMAGE_LUT_ENTRIES or data[1] > 1:
                raise _Nack(f"LUT control {data.hex(' ')}: entries <= 128, images <= 64, repeat 0/1")
            self.lut_control = bytes(data)
        elif code == Cmd.MAILBOX_CONTROL:
            self.mailbox, self.mailbox_address = data[0], 0
        elif code == Cmd.MAILBOX_ADDRESS:
            if self.mailbox == 0:
                raise _Nack("mailbox address while the mailbox is closed")
            self.mailbox_address = data[0]
        elif code == Cmd.MAILBOX_DATA:
            self._mailbox_data(data)
        elif code in (Cmd.TRIG_OUT1, Cmd.TRIG_OUT2):
            if any(d > _MAX_TRIGGER_DELAY for d in data[1:]) or data[0] > 1:
                raise _Nack(
                    f"trigger output {data.hex(' ')}: invert 0/1, delays <= 0x{_MAX_TRIGGER_DELAY:02X}"
                )
            if code == Cmd.TRIG_OUT1:
                self.trig_out1 = bytes(data)
            else:
                self.trig_out2 = bytes(data)
        elif code == Cmd.TRIG_IN1_DELAY:
            self.trig_in1_delay = bytes(data)
        elif code == Cmd.LUT_VALIDATE:
            self.validation = self._validate()
            self.validated = self.validation & 0x1F == 0
            self._busy_left = self.busy_polls
        elif code == Cmd.SEQUENCE_CONTROL:
            if data[0] == 2 and (self.display_mode != 1 or not self.validated):
                raise _Nack("start: not in pattern mode or the sequence is not validated")
            self.sequencer = data[0]
        elif code == Cmd.LED_CURRENT:
            self.led_current = bytes(data)
        elif code == Cmd.LED_ENABLE:
            self.led_enable = data[0]

    def _mailbox_data(self, data: bytes) -> None:
        if self.mailbox == 2:
            if len(data) % 3:
                raise _Nack(f"pattern LUT data of {len(data)} bytes: must be 3 per entry")
            words = proto.decode_lut_words(data)
            if self.mailbox_address + len(words) > proto.MAX_LUT_ENTRIES:
                raise _Nack("pattern LUT overflows 128 entries")
            for i, w in enumerate(words, self.mailbox_address):
                self.pattern_lut[i] = w
                self.pattern_written.add(i)
            self.mailbox_address += len(words)
        elif self.mailbox == 1:
            if self.mailbox_address + len(data) > proto.MAX_IMAGE_LUT_ENTRIES:
                raise _Nack("image LUT overflows 64 entries")
            for i, b in enumerate(data, self.mailbox_address):
                self.image_lut[i] = b
                self.image_written.add(i)
            self.mailbox_address += len(data)
        else:
            raise _Nack("LUT data while the mailbox is closed")

    # --- validation (the device's rules, implemented independently of the host's checks) ------------

    def lut_entries(self) -> list[int]:
        """The pattern LUT words that 0x1A31 says are in use."""
        return self.pattern_lut[: self.lut_control[0] + 1]

    def _validate(self) -> int:
        n = self.lut_control[0] + 1
        words = self.lut_entries()
        bits = 0
        if not set(range(n)) <= self.pattern_written:
            bits |= 1 << 1
        depths = set()
        for w in words:
            depth, pattern = (w >> 8) & 0xF, (w >> 2) & 0x3F
            if not 1 <= depth <= 8 or pattern >= 24 // depth:
                bits |= 1 << 1
            else:
                depths.add(depth)
        if self.exposure_us > self.period_us:
            bits |= 1 << 0
        elif (
            self.exposure_us != self.period_us and self.period_us - self.exposure_us < proto.MIN_PERIOD_GAP_US
        ):
            bits |= 1 << 4
        if any(self.exposure_us < proto.MIN_EXPOSURE_US[d] for d in depths):
            bits |= 1 << 0
        if self.source == 3:
            swaps = sum(1 for w in words[1:] if w >> 18 & 1) + 1
            n_images = self.lut_control[3] + 1
            if swaps > n_images or not set(range(n_images)) <= self.image_written:
                bits |= 1 << 1
        if all(w >> 19 & 1 for w in words):
            bits |= 1 << 2
        for i, w in enumerate(words):
            prev = words[i - 1]
            if w >> 19 & 1 and prev >> 17 & 1:
                bits |= 1 << 2
            if (w & 3) in (1, 2) and not prev >> 17 & 1:
                bits |= 1 << 3
        return bits


class _Nack(Exception):
    pass


class FakeUsbBackend(usb.backend.IBackend):  # type: ignore[misc]
    """A pyusb backend serving :class:`FakeDLPC350` devices (one HID interface, endpoints 0x01 / 0x81)."""

    def __init__(self, *devices: FakeDLPC350) -> None:
        super().__init__()
        self.devices = list(devices)

    def enumerate_devices(self) -> list[FakeDLPC350]:
        return list(self.devices)

    def get_device_descriptor(self, dev: FakeDLPC350) -> Any:
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=proto.VENDOR_ID, idProduct=proto.PRODUCT_ID,
            bcdDevice=0x0100, iManufacturer=1, iProduct=2, iSerialNumber=_SERIAL_INDEX, bNumConfigurations=1,
            address=dev.address, bus=dev.bus, port_number=1, port_numbers=(1,), speed=2,
        )  # fmt: skip

    def get_configuration_descriptor(self, dev: FakeDLPC350, config: int) -> Any:
        if config != 0:
            raise IndexError(f"fake DLPC350: no configuration {config}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=41, bNumInterfaces=1, bConfigurationValue=1,
            iConfiguration=0, bmAttributes=0xC0, bMaxPower=50, extra_descriptors=[],
        )  # fmt: skip

    def get_interface_descriptor(self, dev: FakeDLPC350, intf: int, alt: int, config: int) -> Any:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"fake DLPC350: no interface {intf} alternate {alt}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=2,
            bInterfaceClass=_HID_CLASS, bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0,
            extra_descriptors=[],
        )  # fmt: skip

    def get_endpoint_descriptor(self, dev: FakeDLPC350, ep: int, intf: int, alt: int, config: int) -> Any:
        if (intf, alt, config) != (0, 0, 0) or ep not in (0, 1):
            raise IndexError(f"fake DLPC350: no endpoint {ep}")
        address = (proto.EP_IN, proto.EP_OUT)[ep]
        return SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=0x03,
            wMaxPacketSize=proto.REPORT_SIZE, bInterval=1, bRefresh=0, bSynchAddress=0, extra_descriptors=[],
        )  # fmt: skip

    def open_device(self, dev: FakeDLPC350) -> FakeDLPC350:
        return dev

    def close_device(self, dev_handle: FakeDLPC350) -> None:
        pass

    def set_configuration(self, dev_handle: FakeDLPC350, config_value: int) -> None:
        dev_handle.configuration = config_value

    def get_configuration(self, dev_handle: FakeDLPC350) -> int:
        return dev_handle.configuration

    def set_interface_altsetting(self, dev_handle: FakeDLPC350, intf: int, altsetting: int) -> None:
        pass

    def claim_interface(self, dev_handle: FakeDLPC350, intf: int) -> None:
        if dev_handle.kernel_driver.get(intf, False):
            raise usb.core.USBError("Resource busy", errno.EBUSY, errno.EBUSY)

    def release_interface(self, dev_handle: FakeDLPC350, intf: int) -> None:
        pass

    def is_kernel_driver_active(self, dev_handle: FakeDLPC350, intf: int) -> bool:
        return dev_handle.kernel_driver.get(intf, False)

    def detach_kernel_driver(self, dev_handle: FakeDLPC350, intf: int) -> None:
        dev_handle.kernel_driver[intf] = False

    def attach_kernel_driver(self, dev_handle: FakeDLPC350, intf: int) -> None:
        dev_handle.kernel_driver[intf] = True

    def intr_write(self, dev_handle: FakeDLPC350, ep: int, intf: int, data: Any, timeout: int) -> int:
        if ep != proto.EP_OUT or len(data) != proto.REPORT_SIZE:
            raise usb.core.USBError(
                f"fake DLPC350: write of {len(data)} bytes to endpoint 0x{ep:02X}", errno.EIO
            )
        dev_handle.receive(bytes(data))
        return len(data)

    def intr_read(self, dev_handle: FakeDLPC350, ep: int, intf: int, buff: Any, timeout: int) -> int:
        report = dev_handle.send() if ep == proto.EP_IN else None
        if report is None:
            raise usb.core.USBTimeoutError("Operation timed out", errno.ETIMEDOUT, errno.ETIMEDOUT)
        n = min(len(buff), len(report))
        buff[:n] = type(buff)(buff.typecode, report[:n])
        return n

    def ctrl_transfer(
        self, dev_handle: FakeDLPC350, bmRequestType: int, bRequest: int, wValue: int, wIndex: int,
        data: Any, timeout: int,
    ) -> int:  # fmt: skip
        get_string = bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3
        if not get_string:
            raise usb.core.USBError("fake DLPC350: unsupported control request", errno.EPIPE)
        index = wValue & 0xFF
        text = {_SERIAL_INDEX: dev_handle.serial, **_STRINGS}.get(index)
        payload = struct.pack("<H", 0x0409) if index == 0 else (text or "").encode("utf-16-le")
        desc = bytes([2 + len(payload), 3]) + payload
        n = min(len(data), len(desc))
        data[:n] = type(data)(data.typecode, desc[:n])
        return n
