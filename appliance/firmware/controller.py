"""The trigger controller's firmware logic: parser, session, sequencer, heartbeat, button debounce.

Plain Python for CPython and MicroPython alike. Nothing here touches hardware or reads a clock by
itself: the board layer (``main.py``) or the simulator (``simulate.py``) injects a microsecond clock,
the pins and the serial writer, feeds received bytes to :meth:`Controller.feed`, reports button edges to
:meth:`Controller.button` and calls :meth:`Controller.poll` often (every millisecond or so).
"""

try:
    from appliance.firmware import protocol as P
except ImportError:  # on the board the files sit flat in the root folder
    import protocol as P  # type: ignore[import-not-found, no-redef]

TYPE_CHECKING = False
if TYPE_CHECKING:
    from collections.abc import Callable

DEBOUNCE_US = 20000  # a button level must be stable this long to count


class Channel:
    """The configuration of one output channel (``CFG``)."""

    __slots__ = ("delay_us", "enabled", "polarity", "width_us")

    def __init__(self) -> None:
        self.width_us = 100
        self.delay_us = 0
        self.polarity = "high"
        self.enabled = True


class Pins:
    """What the controller needs from the board; this base class does nothing (for tests)."""

    def start_pulses(self, n: int, period_us: int, channels: "list[Channel]") -> int:
        """Start ``n`` pulses, one per ``period_us`` on every enabled channel; return the start time (µs)."""
        return 0

    def stop_pulses(self) -> None:
        """Stop a running pulse train now, outputs inactive."""

    def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        """Set the lamps."""


class Controller:
    """The controller's protocol engine.

    Parameters
    ----------
    clock_us : callable
        Monotonic microsecond clock (never wraps; the board layer extends ``ticks_us``).
    pins : Pins
        Pulse outputs and lamps.
    write : callable
        Sends bytes to the host; must not block for long (drop rather than wait).
    board_id : str
        Unique id of the board, reported in the HELLO reply.
    channels : int
        Number of output channels (``ch=0..channels-1``).
    proto, fw : int, str
        Protocol and firmware versions to announce (tests override them to check mismatches).
    """

    def __init__(
        self,
        clock_us: "Callable[[], int]",
        pins: Pins,
        write: "Callable[[bytes], object]",
        board_id: str = "0",
        channels: int = 2,
        proto: int = P.PROTO_VERSION,
        fw: str = P.FW_VERSION,
    ) -> None:
        self.clock_us = clock_us
        self.pins = pins
        self.write = write
        self.board_id = board_id
        self.proto = proto
        self.fw = fw
        self.channels = [Channel() for _ in range(channels)]
        self.reader = P.LineReader()
        self.session = False
        self.state = P.S_IDLE
        self.hb_us = P.HB_MS_DEFAULT * 1000
        self.next_hb_us = 0
        self.last_host_us = 0
        self.leds = (False, False, False)
        self.errors = 0  # frames answered with ERR, for diagnostics
        # sequencer
        self.n = 0
        self.period_us = 0
        self.report = True
        self.t0_us = 0
        self.next_i = 0
        self.end_us = 0
        # button debounce
        self.btn_raw = False
        self.btn_stable = False
        self.btn_edge_us = 0
        self.btn_first_us = -1
        self.pins.set_leds(False, False, False)

    # --- input -----------------------------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        """Process received bytes; answers go out through ``write``. Never raises."""
        try:
            lines = self.reader.feed(data)
        except Exception:  # defensive: the reader is total, but a board must never die on input
            self.reader.reset()
            return
        for line in lines:
            try:
                self._line(line)
            except Exception as exc:
                self._send(P.FAULT, 0, {"code": P.F_INTERNAL, "what": _exc_name(exc)})

    def _line(self, line: "bytes | None") -> None:
        if line is None:
            self._err(0, P.E_BADFRAME)
            return
        msg = P.decode(line)
        if msg is None:
            self._err(P.frame_seq(line), P.E_BADFRAME)
            return
        if msg.kind not in P.REQUESTS:
            self._err(msg.seq, P.E_UNKNOWN)
            return
        if msg.kind == P.HELLO:
            self._hello(msg)
            return
        if not self.session:
            self._err(msg.seq, P.E_NOHELLO)
            return
        self.last_host_us = self.clock_us()
        if msg.kind == P.PING:
            self._send(P.OK, msg.seq, {"t_us": self.clock_us(), "state": self.state})
        elif msg.kind == P.CFG:
            self._cfg(msg)
        elif msg.kind == P.SEQ:
            self._seq(msg)
        elif msg.kind == P.FIRE:
            self._fire(msg)
        elif msg.kind == P.BYE:
            self._stop()
            self.session = False
            self.leds = (False, False, False)
            self.pins.set_leds(False, False, False)
            self._send(P.OK, msg.seq)
        elif msg.kind == P.ABORT:
            done = self.next_i if self.state == P.S_RUNNING else 0
            self._stop()
            self._send(P.OK, msg.seq, {"n": done})
        else:
            self._led(msg)

    def _hello(self, msg: "P.Message") -> None:
        proto = msg.get_int("proto", 0, 65535)
        hb_ms = msg.get_int("hb_ms", P.HB_MS_MIN, P.HB_MS_MAX, P.HB_MS_DEFAULT)
        if proto is None or hb_ms is None:
            self._err(msg.seq, P.E_RANGE, "proto" if proto is None else "hb_ms")
            return
        if proto != self.proto:
            self._send(P.ERR, msg.seq, {"code": P.E_PROTO, "proto": self.proto, "fw": self.fw})
            return
        # A new session starts from the power-on state.
        self._stop()
        self.channels = [Channel() for _ in self.channels]
        self.session = True
        self.hb_us = hb_ms * 1000
        now = self.clock_us()
        self.last_host_us = now
        self.next_hb_us = now + self.hb_us
        self.pins.set_leds(False, False, False)
        self.leds = (False, False, False)
        self._send(P.HELLO, msg.seq, {
            "proto": self.proto, "fw": self.fw, "ch": len(self.channels), "id": self.board_id,
            "t_us": now, "hb_ms": hb_ms,
        })

    def _cfg(self, msg: "P.Message") -> None:
        if self.state == P.S_RUNNING:
            self._err(msg.seq, P.E_BUSY)
            return
        ch = msg.get_int("ch", 0, len(self.channels) - 1)
        old = self.channels[ch] if ch is not None else Channel()
        width = msg.get_int("width_us", P.WIDTH_US_MIN, P.WIDTH_US_MAX, old.width_us)
        delay = msg.get_int("delay_us", 0, P.DELAY_US_MAX, old.delay_us)
        enabled = msg.get_int("en", 0, 1, 1 if old.enabled else 0)
        polarity = msg.get("polarity", old.polarity)
        for key, value in (("ch", ch), ("width_us", width), ("delay_us", delay), ("en", enabled)):
            if value is None:
                self._err(msg.seq, P.E_RANGE, key)
                return
        if polarity not in P.POLARITIES:
            self._err(msg.seq, P.E_RANGE, "polarity")
            return
        assert ch is not None and width is not None and delay is not None
        channel = self.channels[ch]
        channel.width_us = width
        channel.delay_us = delay
        channel.polarity = polarity
        channel.enabled = enabled == 1
        if self.state == P.S_ARMED and not self._fits(self.period_us):
            self.state = P.S_IDLE  # the armed sequence no longer fits: re-arm explicitly
        self._send(P.OK, msg.seq)

    def _fits(self, period_us: int) -> bool:
        for channel in self.channels:
            if channel.enabled and channel.delay_us + channel.width_us >= period_us:
                return False
        return True

    def _seq(self, msg: "P.Message") -> None:
        if self.state == P.S_RUNNING:
            self._err(msg.seq, P.E_BUSY)
            return
        n = msg.get_int("n", 1, P.N_MAX)
        period = msg.get_int("period_us", P.PERIOD_US_MIN, P.PERIOD_US_MAX)
        report = msg.get_int("report", 0, 1, 1)
        for key, value in (("n", n), ("period_us", period), ("report", report)):
            if value is None:
                self._err(msg.seq, P.E_RANGE, key)
                return
        assert n is not None and period is not None
        if not self._fits(period):
            self._err(msg.seq, P.E_RANGE, "period_us")
            return
        self.n = n
        self.period_us = period
        self.report = report == 1
        self.state = P.S_ARMED
        self._send(P.OK, msg.seq)

    def _fire(self, msg: "P.Message") -> None:
        if self.state == P.S_RUNNING:
            self._err(msg.seq, P.E_BUSY)
            return
        if self.state != P.S_ARMED:
            self._err(msg.seq, P.E_STATE)
            return
        tail = 0
        for channel in self.channels:
            if channel.enabled and channel.delay_us + channel.width_us > tail:
                tail = channel.delay_us + channel.width_us
        self.t0_us = self.pins.start_pulses(self.n, self.period_us, self.channels)
        self.end_us = self.t0_us + (self.n - 1) * self.period_us + tail
        self.next_i = 0
        self.state = P.S_RUNNING
        self._send(P.OK, msg.seq, {"t_us": self.t0_us})

    def _led(self, msg: "P.Message") -> None:
        old = self.leds
        ready = msg.get_int("ready", 0, 1, int(old[0]))
        busy = msg.get_int("busy", 0, 1, int(old[1]))
        fault = msg.get_int("fault", 0, 1, int(old[2]))
        for key, value in (("ready", ready), ("busy", busy), ("fault", fault)):
            if value is None:
                self._err(msg.seq, P.E_RANGE, key)
                return
        self.leds = (ready == 1, busy == 1, fault == 1)
        self.pins.set_leds(ready == 1, busy == 1, fault == 1)
        self._send(P.OK, msg.seq)

    def button(self, pressed: bool, t_us: "int | None" = None) -> None:
        """Report a raw button level change (from a pin interrupt or a sampler) at ``t_us`` (default: now)."""
        t = self.clock_us() if t_us is None else t_us
        if pressed == self.btn_raw:
            return
        self.btn_raw = pressed
        self.btn_edge_us = t
        if pressed and not self.btn_stable and self.btn_first_us < 0:
            self.btn_first_us = t

    # --- time ------------------------------------------------------------------------------------------

    def poll(self) -> None:
        """Advance time: debounce, sequencer reports, heartbeat, host supervision. Never raises."""
        try:
            self._poll(self.clock_us())
        except Exception as exc:
            self._send(P.FAULT, 0, {"code": P.F_INTERNAL, "what": _exc_name(exc)})

    def _poll(self, now: int) -> None:
        if self.btn_raw != self.btn_stable and now - self.btn_edge_us >= DEBOUNCE_US:
            self.btn_stable = self.btn_raw
            if self.btn_stable and self.session:
                first = self.btn_first_us if self.btn_first_us >= 0 else self.btn_edge_us
                self._send(P.BUTTON, 0, {"id": 0, "t_us": first})
            self.btn_first_us = -1
        if self.state == P.S_RUNNING:
            while self.next_i < self.n and self.t0_us + self.next_i * self.period_us <= now:
                if self.report:
                    t_us = self.t0_us + self.next_i * self.period_us
                    self._send(P.TRIG, 0, {"i": self.next_i, "t_us": t_us})
                self.next_i += 1
            if now >= self.end_us:
                self.pins.stop_pulses()
                self.state = P.S_IDLE
                self._send(P.DONE, 0, {"n": self.n, "t_us": self.end_us})
        if not self.session:
            return
        if now - self.last_host_us > P.HOST_LOST_BEATS * self.hb_us + self.hb_us // 2:
            self.session = False
            self._stop()
            self.leds = (False, False, True)
            self.pins.set_leds(False, False, True)
            self._send(P.FAULT, 0, {"code": P.F_HOSTLOST})
            return
        if now >= self.next_hb_us:
            self._send(P.HB, 0, {"t_us": now, "state": self.state})
            self.next_hb_us = now + self.hb_us

    # --- helpers ---------------------------------------------------------------------------------------

    def _stop(self) -> None:
        if self.state == P.S_RUNNING:
            self.pins.stop_pulses()
        self.state = P.S_IDLE

    def _err(self, seq: int, code: str, key: str = "") -> None:
        self.errors += 1
        self._send(P.ERR, seq, {"code": code, "key": key} if key else {"code": code})

    def _send(self, kind: str, seq: int, fields: "dict[str, object] | None" = None) -> None:
        try:
            self.write(P.encode(kind, seq, fields))
        except Exception:  # a full or closed link must not stop the controller
            pass


def _exc_name(exc: BaseException) -> str:
    name = type(exc).__name__
    return name if name.isalpha() else "Exception"
