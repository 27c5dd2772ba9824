"""The DLPC350 (TI DLP LightCrafter 4500) USB HID command protocol, as pure data and functions.

No USB here: this module encodes request messages into 64-byte HID reports, decodes replies, holds the
command table, builds pattern LUT words and turns status bytes into human messages. The backend
(:mod:`appliance.hardware.lightcrafter4500`) and the fake device (:mod:`appliance.fakes.dlpc350`)
both speak through it.

Wire format (host -> device), zero-padded to 64-byte reports::

    [flags][seq][len lo][len hi][cmd lo][cmd hi][data ...]

``flags`` bit 7 = read, bit 6 = reply wanted (write = 0x40, read = 0xC0); ``len`` counts the two command
bytes plus the data. A message longer than one report continues, raw, in the following 64-byte reports.
Replies are ``[flags][seq][len lo][len hi][data ...]``; flags bit 5 set = NACK.

Flash safety: :func:`check_not_flash` refuses every command of the DLPC350's flash / boot-loader group.
The backend calls it before every write; nothing in the appliance ever reprograms the projector's flash.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from appliance.errors import ProjectorError

VENDOR_ID = 0x0451
PRODUCT_ID = 0x6401
EP_OUT = 0x01
EP_IN = 0x81
REPORT_SIZE = 64
HEADER_SIZE = 4

FLAG_READ = 0x80
FLAG_REPLY = 0x40
FLAG_NACK = 0x20

TRIGGER_DELAY_STEP_NS = 107.2
"""One step of the TRIG_OUT1/TRIG_OUT2 delay registers (ns)."""

MIN_PERIOD_GAP_US = 230
"""Exposure must equal the period or be at most the period minus this (µs)."""

MIN_EXPOSURE_US = {1: 235, 2: 700, 3: 1570, 4: 1700, 5: 2000, 6: 2500, 7: 4500, 8: 8333}
"""Shortest pattern exposure per bit depth (µs), LightCrafter 4500 user's guide."""

MAX_LUT_ENTRIES = 128
MAX_IMAGE_LUT_ENTRIES = 64


class Cmd(IntEnum):
    """DLPC350 command codes used by the appliance (``0x1A1B`` goes on the wire as ``1B 1A``)."""

    POWER_CONTROL = 0x0200
    LED_CURRENT = 0x0B01
    LED_ENABLE = 0x1A07
    HW_STATUS = 0x1A0A
    SYS_STATUS = 0x1A0B
    MAIN_STATUS = 0x1A0C
    LUT_VALIDATE = 0x1A1A
    DISPLAY_MODE = 0x1A1B
    TRIG_OUT1 = 0x1A1D
    TRIG_OUT2 = 0x1A1E
    PATTERN_SOURCE = 0x1A22
    TRIGGER_MODE = 0x1A23
    SEQUENCE_CONTROL = 0x1A24
    EXPOSURE_PERIOD = 0x1A29
    LUT_CONTROL = 0x1A31
    MAILBOX_ADDRESS = 0x1A32
    MAILBOX_CONTROL = 0x1A33
    MAILBOX_DATA = 0x1A34
    TRIG_IN1_DELAY = 0x1A35


@dataclass(frozen=True)
class CommandSpec:
    """One row of the command table.

    ``write_len`` / ``read_len``: data bytes of a write / of a read reply; ``None`` = not allowed,
    ``-1`` = variable (the mailbox data).
    """

    code: int
    name: str
    write_len: int | None
    read_len: int | None
    meaning: str


COMMANDS: dict[int, CommandSpec] = {
    c.code: c
    for c in (
        CommandSpec(Cmd.POWER_CONTROL, "power control", 1, 1, "1 = standby, 0 = normal"),
        CommandSpec(Cmd.LED_CURRENT, "LED current", 3, 3, "PWM red, green, blue (EVM: 255 - x)"),
        CommandSpec(Cmd.LED_ENABLE, "LED enable", 1, 1, "bit 3 sequencer-controlled, bits 0..2 R, G, B"),
        CommandSpec(Cmd.HW_STATUS, "hardware status", None, 1, "bit 0 init ok, 2 DRC error, 6/7 sequencer"),
        CommandSpec(Cmd.SYS_STATUS, "system status", None, 1, "bit 0 internal memory test passed"),
        CommandSpec(Cmd.MAIN_STATUS, "main status", None, 1, "bit 0 parked, 1 running, 2 frozen"),
        CommandSpec(Cmd.LUT_VALIDATE, "validate sequence", 1, 1, "bit 7 busy, bits 0..4 errors"),
        CommandSpec(Cmd.DISPLAY_MODE, "display mode", 1, 1, "0 video, 1 pattern sequence"),
        CommandSpec(Cmd.TRIG_OUT1, "TRIG_OUT1 control", 3, 3, "invert, rising, falling delay"),
        CommandSpec(Cmd.TRIG_OUT2, "TRIG_OUT2 control", 2, 2, "invert, rising delay"),
        CommandSpec(Cmd.PATTERN_SOURCE, "pattern source", 1, 1, "0 video port, 3 internal flash"),
        CommandSpec(Cmd.TRIGGER_MODE, "trigger mode", 1, 1, "0 VSYNC, 1 internal/external"),
        CommandSpec(Cmd.SEQUENCE_CONTROL, "sequence start/stop", 1, 1, "0 stop, 1 pause, 2 start"),
        CommandSpec(Cmd.EXPOSURE_PERIOD, "exposure and period", 8, 8, "exposure µs, period µs (u32 LE)"),
        CommandSpec(
            Cmd.LUT_CONTROL, "LUT control", 4, 4, "entries-1, repeat, patterns/TRIG_OUT2-1, images-1"
        ),
        CommandSpec(Cmd.MAILBOX_ADDRESS, "LUT mailbox address", 1, 1, "entry offset"),
        CommandSpec(
            Cmd.MAILBOX_CONTROL, "LUT mailbox open/close", 1, 1, "1 image LUT, 2 pattern LUT, 0 close"
        ),
        CommandSpec(Cmd.MAILBOX_DATA, "LUT mailbox data", -1, None, "3 bytes per pattern entry, 1 per image"),
        CommandSpec(Cmd.TRIG_IN1_DELAY, "TRIG_IN1 delay", 4, 4, "delay"),
    )
}

# The DLPC350 flash / boot-loader command group, as read from the programmer's guide: program mode
# (0x0030), sector erase (0x0028), sector address (0x0029), download size (0x002C), download data
# (0x0025), checksums (0x0026, 0x0015), flash type and ids (0x002F, 0x000C, 0x000D): we refuse every
# command with a high byte of 0x00. Also refused, as the appliance never needs them: 0x0B00 and
# 0x0F00..0x0FFF. Besides, the backend's own set-up sends only commands of :data:`COMMANDS`.
_FLASH_RANGES: tuple[tuple[int, int], ...] = ((0x0000, 0x00FF), (0x0B00, 0x0B00), (0x0F00, 0x0FFF))


def is_flash_command(code: int) -> bool:
    """True for any command of the DLPC350's flash-programming / boot-loader group."""
    return any(lo <= code <= hi for lo, hi in _FLASH_RANGES)


def check_not_flash(code: int) -> None:
    """Raise :class:`ProjectorError` if ``code`` is a flash-programming command (never sent)."""
    if is_flash_command(code):
        raise ProjectorError(
            f"DLPC350 command 0x{code:04X} belongs to the flash-programming group: the appliance never sends "
            "it (an interrupted flash write can brick the projector); program flash with TI's tools on a "
            "bench"
        )


def command_name(code: int) -> str:
    """``'0x1A1B (display mode)'`` or ``'0x1A7F (unknown)'``."""
    spec = COMMANDS.get(code)
    return f"0x{code:04X} ({spec.name if spec else 'unknown'})"


# --- framing ------------------------------------------------------------------------------------------


def encode_request(code: int, data: bytes = b"", *, read: bool = False, seq: int = 0) -> list[bytes]:
    """Encode one request as 64-byte HID reports.

    Parameters
    ----------
    code : int
        Command code, e.g. ``0x1A1B``.
    data : bytes
        Command data (a write's payload; for a read, optional parameters).
    read : bool
        A read (flags 0xC0) rather than a write with reply (flags 0x40).
    seq : int
        Sequence number 0..255, echoed in the reply.

    Returns
    -------
    list of bytes
        One or more 64-byte reports; continuation reports carry the remaining message bytes raw.
    """
    length = 2 + len(data)
    if length > 0xFFFF:
        raise ProjectorError(
            f"DLPC350 {command_name(code)}: {len(data)} data bytes: too long for one message"
        )
    flags = FLAG_READ | FLAG_REPLY if read else FLAG_REPLY
    message = bytes([flags, seq & 0xFF]) + struct.pack("<HH", length, code) + bytes(data)
    return [
        message[i : i + REPORT_SIZE].ljust(REPORT_SIZE, b"\x00") for i in range(0, len(message), REPORT_SIZE)
    ]


@dataclass(frozen=True)
class Request:
    """A decoded host request (as the device sees it)."""

    flags: int
    seq: int
    code: int
    data: bytes

    @property
    def is_read(self) -> bool:
        """The host asks for data."""
        return bool(self.flags & FLAG_READ)

    @property
    def wants_reply(self) -> bool:
        """The host waits for a reply (always for reads; for writes when flags bit 6 is set)."""
        return bool(self.flags & (FLAG_REPLY | FLAG_READ))


def message_length(first_report: bytes) -> int:
    """Total message size in bytes (header + payload) announced by a first report."""
    return HEADER_SIZE + int(struct.unpack_from("<H", first_report, 2)[0])


def reports_needed(total_bytes: int) -> int:
    """Number of 64-byte reports a message of ``total_bytes`` occupies."""
    return max(1, -(-total_bytes // REPORT_SIZE))


def decode_request(reports: list[bytes]) -> Request:
    """Decode the reports of one host request; raise ``ValueError`` if malformed."""
    blob = b"".join(bytes(r) for r in reports)
    if len(blob) < HEADER_SIZE + 2:
        raise ValueError(f"request of {len(blob)} bytes: shorter than a header and a command")
    flags, seq, length, code = blob[0], blob[1], *struct.unpack_from("<HH", blob, 2)
    if length < 2 or HEADER_SIZE + length > len(blob):
        raise ValueError(f"request length field {length}: does not fit {len(blob)} received bytes")
    return Request(flags, seq, code, blob[HEADER_SIZE + 2 : HEADER_SIZE + length])


def encode_reply(seq: int, data: bytes = b"", *, flags: int = FLAG_REPLY, nack: bool = False) -> list[bytes]:
    """Encode a device reply (``[flags][seq][len lo][len hi][data]``) as 64-byte reports."""
    f = (flags | FLAG_NACK) if nack else (flags & ~FLAG_NACK)
    message = bytes([f & 0xFF, seq & 0xFF]) + struct.pack("<H", len(data)) + bytes(data)
    return [
        message[i : i + REPORT_SIZE].ljust(REPORT_SIZE, b"\x00") for i in range(0, len(message), REPORT_SIZE)
    ]


@dataclass(frozen=True)
class Reply:
    """A decoded device reply."""

    flags: int
    seq: int
    data: bytes

    @property
    def nack(self) -> bool:
        """The device refused the request."""
        return bool(self.flags & FLAG_NACK)


def decode_reply(reports: list[bytes]) -> Reply:
    """Decode the reports of one reply; raise ``ValueError`` if the length does not fit."""
    blob = b"".join(bytes(r) for r in reports)
    if len(blob) < HEADER_SIZE:
        raise ValueError(f"reply of {len(blob)} bytes: shorter than its 4-byte header")
    length = struct.unpack_from("<H", blob, 2)[0]
    if HEADER_SIZE + length > len(blob):
        raise ValueError(
            f"reply length field {length}: more than the {len(blob) - HEADER_SIZE} bytes received"
        )
    return Reply(blob[0], blob[1], blob[HEADER_SIZE : HEADER_SIZE + length])


# --- command payloads ---------------------------------------------------------------------------------


def exposure_period_data(exposure_us: int, period_us: int) -> bytes:
    """Payload of 0x1A29: exposure and frame period (µs, u32 little-endian each)."""
    return struct.pack("<II", exposure_us, period_us)


def lut_control_data(n_entries: int, repeat: bool, patterns_per_trig_out2: int, n_images: int) -> bytes:
    """Payload of 0x1A31 (every count is sent minus one)."""
    if not 1 <= n_entries <= MAX_LUT_ENTRIES:
        raise ProjectorError(f"DLPC350 LUT: {n_entries} entries: must be 1..{MAX_LUT_ENTRIES}")
    if not 1 <= n_images <= MAX_IMAGE_LUT_ENTRIES:
        raise ProjectorError(f"DLPC350 image LUT: {n_images} images: must be 1..{MAX_IMAGE_LUT_ENTRIES}")
    if not 1 <= patterns_per_trig_out2 <= 256:
        raise ProjectorError(f"DLPC350 LUT: {patterns_per_trig_out2} patterns per TRIG_OUT2: must be 1..256")
    return bytes([n_entries - 1, int(repeat), patterns_per_trig_out2 - 1, n_images - 1])


def check_exposure_period(
    exposure_us: int, period_us: int, bit_depths: set[int] | frozenset[int]
) -> list[str]:
    """The device's timing rules, checked on the host; returns the broken rules as messages (empty = ok).

    Rules: exposure == period, or exposure <= period - 230 µs; exposure >= the minimum of each bit depth
    used (:data:`MIN_EXPOSURE_US`).
    """
    problems: list[str] = []
    if exposure_us > period_us:
        problems.append(f"exposure {exposure_us} µs is longer than the period {period_us} µs")
    elif exposure_us != period_us and exposure_us > period_us - MIN_PERIOD_GAP_US:
        problems.append(
            f"exposure {exposure_us} µs with period {period_us} µs: the exposure must equal the period or be "
            f"at most period - {MIN_PERIOD_GAP_US} µs = {period_us - MIN_PERIOD_GAP_US} µs"
        )
    for depth in sorted(bit_depths):
        minimum = MIN_EXPOSURE_US.get(depth)
        if minimum is None:
            problems.append(f"bit depth {depth}: must be 1..8")
        elif exposure_us < minimum:
            problems.append(
                f"exposure {exposure_us} µs is below the {minimum} µs minimum of {depth}-bit patterns"
            )
    return problems


# --- pattern LUT --------------------------------------------------------------------------------------


class Trigger(IntEnum):
    """Trigger type of a pattern LUT entry (bits 1..0)."""

    INTERNAL = 0
    EXTERNAL_POSITIVE = 1  # also the VSYNC in trigger mode 0
    EXTERNAL_NEGATIVE = 2
    CONTINUE = 3  # no trigger: follows the previous pattern


class Led(IntEnum):
    """LED select of a pattern LUT entry (bits 14..12)."""

    NONE = 0
    RED = 1
    GREEN = 2
    YELLOW = 3
    BLUE = 4
    MAGENTA = 5
    CYAN = 6
    WHITE = 7


@dataclass(frozen=True)
class LutEntry:
    """One pattern LUT entry (a 24-bit word).

    ``pattern`` numbers the bit planes of a 24-bit image in units of ``bit_depth``: for 1-bit patterns
    0..7 = G0..G7, 8..15 = R0..R7, 16..23 = B0..B7; for 8-bit patterns 0 = G, 1 = R, 2 = B.
    """

    pattern: int
    bit_depth: int
    led: Led = Led.WHITE
    trigger: Trigger = Trigger.CONTINUE
    invert: bool = False
    insert_black: bool = False
    buffer_swap: bool = False
    trig_out_prev: bool = False

    def __post_init__(self) -> None:
        if not 1 <= self.bit_depth <= 8:
            raise ProjectorError(f"DLPC350 LUT entry: bit_depth = {self.bit_depth}: must be 1..8")
        if not 0 <= self.pattern < 24 // self.bit_depth:
            raise ProjectorError(
                f"DLPC350 LUT entry: pattern = {self.pattern} at bit depth {self.bit_depth}: "
                f"must be 0..{24 // self.bit_depth - 1}"
            )

    def word(self) -> int:
        """The 24-bit LUT word."""
        return (
            int(self.trigger)
            | self.pattern << 2
            | self.bit_depth << 8
            | int(self.led) << 12
            | int(self.invert) << 16
            | int(self.insert_black) << 17
            | int(self.buffer_swap) << 18
            | int(self.trig_out_prev) << 19
        )

    @classmethod
    def from_word(cls, word: int) -> LutEntry:
        """Inverse of :meth:`word`; raises :class:`ProjectorError` for an invalid word."""
        return cls(
            pattern=(word >> 2) & 0x3F,
            bit_depth=(word >> 8) & 0xF,
            led=Led((word >> 12) & 0x7),
            trigger=Trigger(word & 0x3),
            invert=bool(word >> 16 & 1),
            insert_black=bool(word >> 17 & 1),
            buffer_swap=bool(word >> 18 & 1),
            trig_out_prev=bool(word >> 19 & 1),
        )


def encode_lut(entries: list[LutEntry]) -> bytes:
    """Pattern LUT mailbox payload: 3 bytes (little-endian) per entry."""
    return b"".join(e.word().to_bytes(3, "little") for e in entries)


def decode_lut_words(data: bytes) -> list[int]:
    """Split a pattern LUT payload into 24-bit words."""
    return [int.from_bytes(data[i : i + 3], "little") for i in range(0, len(data) - len(data) % 3, 3)]


# --- status decoding ----------------------------------------------------------------------------------

VALIDATION_ERRORS = {
    0: "the exposure or frame period is invalid (exposure must equal the period or be at most "
    "period - 230 µs, and at least the minimum of the bit depth)",
    1: "a pattern number in the LUT is invalid for its bit depth, or the LUT does not match 0x1A31",
    2: "TRIG_OUT1 overlaps: continuous TRIG_OUT1 request or overlapping black sectors",
    3: "post-vector missing before an externally triggered pattern (set insert-black on the pattern before)",
    4: "the gap between exposure and frame period is under 230 µs",
}
VALIDATION_BUSY = 0x80

HARDWARE_STATUS_BITS = {
    1: "incompatible controller or DMD",
    2: "DMD reset controller (DRC) error",
    3: "forced buffer swap error",
    6: "sequencer abort",
    7: "sequencer error",
}

MAIN_STATUS_BITS = {0: "DMD parked", 1: "sequencer running", 2: "video frozen", 3: "external video locked"}


def decode_validation(status: int) -> list[str]:
    """Messages for the error bits 0..4 of a 0x1A1A read (empty = valid)."""
    return [msg for bit, msg in VALIDATION_ERRORS.items() if status >> bit & 1]


def decode_hardware_status(status: int) -> list[str]:
    """Problems reported by the 0x1A0A hardware status byte (empty = healthy)."""
    problems = [] if status & 1 else ["internal initialisation failed"]
    return problems + [msg for bit, msg in HARDWARE_STATUS_BITS.items() if status >> bit & 1]


def decode_main_status(status: int) -> list[str]:
    """The states set in a 0x1A0C main status byte, e.g. ``['sequencer running']``."""
    return [msg for bit, msg in MAIN_STATUS_BITS.items() if status >> bit & 1]
