"""The trigger controller's serial protocol: the one definition shared by host and firmware.

Plain Python that runs unchanged under CPython (host, tests, simulator) and MicroPython (the board):
no imports, no f-strings, no dataclasses, annotations never evaluated at run time. See
``docs/serial-protocol.md`` for the protocol itself.

A frame is one ASCII line ``TYPE SEQ key=value ... *CRC\\n`` of at most :data:`MAX_LINE` bytes; CRC is
CRC-16/CCITT-FALSE over every byte before ``" *"``, as four hex digits.
"""

TYPE_CHECKING = False
if TYPE_CHECKING:
    from collections.abc import Mapping

PROTO_VERSION = 1
FW_VERSION = "1.0.0"

MAX_LINE = 128  # bytes, including the final "\n"
SEQ_MAX = 65535

# Host -> controller
HELLO = "HELLO"
PING = "PING"
CFG = "CFG"
SEQ = "SEQ"
FIRE = "FIRE"
ABORT = "ABORT"
LED = "LED"
BYE = "BYE"
# Controller -> host (HELLO also answers HELLO)
OK = "OK"
ERR = "ERR"
BUTTON = "BUTTON"
TRIG = "TRIG"
DONE = "DONE"
HB = "HB"
FAULT = "FAULT"

REQUESTS = (HELLO, PING, CFG, SEQ, FIRE, ABORT, LED, BYE)
REPLIES = (HELLO, OK, ERR, BUTTON, TRIG, DONE, HB, FAULT)

# ERR codes
E_BADFRAME = "BADFRAME"  # too long, bad CRC, or unparsable; the frame is ignored
E_UNKNOWN = "UNKNOWN"  # well framed, but not a request type this controller knows
E_NOHELLO = "NOHELLO"  # no session: HELLO first (after power-up or after the host went silent)
E_PROTO = "PROTO"  # HELLO with another protocol version; the reply names the controller's
E_RANGE = "RANGE"  # a field is missing, malformed or out of range (the reply names it: key=...)
E_STATE = "STATE"  # not possible in this state (FIRE when not armed)
E_BUSY = "BUSY"  # a sequence is running

# FAULT codes
F_HOSTLOST = "HOSTLOST"  # no frame from the host for HOST_LOST_BEATS heartbeat intervals
F_INTERNAL = "INTERNAL"  # the firmware caught an exception (the reply names it: what=...)

# Sequencer states
S_IDLE = "idle"
S_ARMED = "armed"
S_RUNNING = "running"

# Field ranges (inclusive)
CHANNELS_MAX = 8
N_MAX = 100000
PERIOD_US_MIN = 100
PERIOD_US_MAX = 10000000
WIDTH_US_MIN = 1
WIDTH_US_MAX = 1000000
DELAY_US_MAX = 1000000
HB_MS_MIN = 10
HB_MS_MAX = 60000
HB_MS_DEFAULT = 1000
HOST_LOST_BEATS = 3  # both sides: a link is dead after this many silent heartbeat intervals
POLARITIES = ("high", "low")


def _make_table() -> "list[int]":
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _make_table()


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor).

    Parameters
    ----------
    data : bytes
        The bytes to check.
    crc : int
        Initial value (0xFFFF), or a previous result to continue a running CRC.

    Returns
    -------
    int
        The CRC, 0..0xFFFF; ``crc16(b"123456789") == 0x29B1``.
    """
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFF00) ^ table[((crc >> 8) ^ byte) & 0xFF]
    return crc


class Message:
    """One decoded frame: its type, sequence number and ``key=value`` fields (strings)."""

    __slots__ = ("fields", "kind", "seq")

    def __init__(self, kind: str, seq: int = 0, fields: "dict[str, str] | None" = None) -> None:
        self.kind = kind
        self.seq = seq
        self.fields = fields if fields is not None else {}

    def get(self, key: str, default: str = "") -> str:
        """The field ``key`` as text, or ``default`` when absent."""
        return self.fields.get(key, default)

    def get_int(self, key: str, lo: int, hi: int, default: "int | None" = None) -> "int | None":
        """Field ``key`` as an int in ``[lo, hi]``; ``default`` if absent, None if malformed or outside."""
        text = self.fields.get(key)
        if text is None:
            return default
        if not _is_decimal(text) or len(text) > 12:
            return None
        value = int(text)
        if value < lo or value > hi:
            return None
        return value

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Message):
            return False
        return self.kind == other.kind and self.seq == other.seq and self.fields == other.fields

    def __repr__(self) -> str:
        return f"Message({self.kind!r}, {self.seq}, {self.fields!r})"


def _is_decimal(text: str) -> bool:
    if not text:
        return False
    for ch in text:
        if ch < "0" or ch > "9":
            return False
    return True


def _is_type(text: str) -> bool:
    if not text or len(text) > 16:
        return False
    for ch in text:
        if ch < "A" or ch > "Z":
            return False
    return True


def _is_key(text: str) -> bool:
    if not text or len(text) > 16:
        return False
    for ch in text:
        if not ("a" <= ch <= "z" or "0" <= ch <= "9" or ch == "_"):
            return False
    return True


def _is_value(text: str) -> bool:
    if not text or len(text) > 64:
        return False
    for ch in text:
        if ch <= " " or ch > "~" or ch == "*" or ch == "=":
            return False
    return True


def encode(kind: str, seq: int = 0, fields: "Mapping[str, object] | None" = None) -> bytes:
    """Build one frame, ``\\n`` included.

    Parameters
    ----------
    kind : str
        Message type (upper-case letters), e.g. ``"SEQ"``.
    seq : int
        Sequence number 0..65535 (0 for unsolicited messages).
    fields : mapping, optional
        ``key -> value``; values are written with ``str()`` (bools as 0/1).

    Returns
    -------
    bytes
        The frame, at most :data:`MAX_LINE` bytes.

    Raises
    ------
    ValueError
        If the type, a key or a value cannot be framed, or the frame is too long.
    """
    if not _is_type(kind) or seq < 0 or seq > SEQ_MAX:
        raise ValueError(f"cannot frame message type {kind!r} seq {seq!r}")
    parts = [kind, str(seq)]
    if fields:
        for key in fields:
            value = fields[key]
            text = str(int(value)) if isinstance(value, bool) else str(value)
            if not _is_key(key) or not _is_value(text):
                raise ValueError(f"cannot frame field {key!r}={text!r} of {kind}")
            parts.append(key + "=" + text)
    body = " ".join(parts).encode()
    frame = body + f" *{crc16(body):04X}\n".encode()
    if len(frame) > MAX_LINE:
        raise ValueError(f"{kind} frame is {len(frame)} bytes, more than {MAX_LINE}")
    return frame


def _printable(line: bytes) -> bool:
    for byte in line:
        if byte < 0x20 or byte > 0x7E:
            return False
    return True


def decode(line: bytes) -> "Message | None":
    """Parse one line (without ``\\n``; a trailing ``\\r`` is allowed); None if it is not a valid frame.

    Total: never raises, whatever the bytes.
    """
    if not isinstance(line, (bytes, bytearray)):
        return None
    if line and line[-1] == 0x0D:
        line = line[:-1]
    if len(line) >= MAX_LINE or not _printable(line):
        return None
    cut = line.rfind(b" *")
    if cut < 0 or len(line) - cut != 6:
        return None
    body = bytes(line[:cut])
    crc_text = bytes(line[cut + 2 :]).decode()
    for ch in crc_text:
        if not ("0" <= ch <= "9" or "A" <= ch <= "F"):  # upper case only: a flipped case bit is an error
            return None
    if int(crc_text, 16) != crc16(body):
        return None
    tokens = body.decode().split(" ")
    if len(tokens) < 2 or not _is_type(tokens[0]) or not _is_decimal(tokens[1]) or len(tokens[1]) > 5:
        return None
    seq = int(tokens[1])
    if seq > SEQ_MAX:
        return None
    fields = {}
    for token in tokens[2:]:
        eq = token.find("=")
        if eq <= 0:
            return None
        key = token[:eq]
        value = token[eq + 1 :]
        if not _is_key(key) or not _is_value(value) or key in fields:
            return None
        fields[key] = value
    return Message(tokens[0], seq, fields)


def frame_seq(line: bytes) -> int:
    """Best guess of the SEQ of a line that failed to decode (for ``ERR seq code=BADFRAME``); 0 if none."""
    if not isinstance(line, (bytes, bytearray)):
        return 0
    first = line.find(b" ")
    if first < 0:
        return 0
    second = line.find(b" ", first + 1)
    token = bytes(line[first + 1 : second if second > 0 else len(line)])
    if not token or len(token) > 5:
        return 0
    for byte in token:
        if byte < 0x30 or byte > 0x39:
            return 0
    value = int(token)
    return value if value <= SEQ_MAX else 0


class LineReader:
    """Splits a byte stream into lines; a line longer than :data:`MAX_LINE` is reported once as None.

    Over-long input is dropped up to the next ``\\n``, where the reader resynchronises. Empty lines
    (and lone ``\\r``) are skipped: a sender may precede a frame with ``\\n`` to end any noise.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False

    def reset(self) -> None:
        """Forget any partial line."""
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> "list[bytes | None]":
        """Add bytes; return the complete lines (without ``\\n``), None for each over-long one."""
        out: list[bytes | None] = []
        start = 0
        end = len(data)
        while start < end:
            nl = data.find(b"\n", start)
            chunk_end = end if nl < 0 else nl
            if not self._discarding:
                self._buf.extend(data[start:chunk_end])
                if len(self._buf) >= MAX_LINE:
                    self._buf = bytearray()
                    self._discarding = True
            if nl < 0:
                break
            if self._discarding:
                out.append(None)
                self._discarding = False
            elif self._buf and self._buf != b"\r":
                out.append(bytes(self._buf))
            self._buf = bytearray()
            start = nl + 1
        return out
