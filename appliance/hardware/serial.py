"""The ``serial`` trigger source: the trigger controller on USB serial (``docs/serial-protocol.md``).

The controller reads the operator's button, fires the camera/projector pulse trains on its own clock and
reports both over a line protocol defined once in :mod:`appliance.firmware.protocol`. This driver:

- opens the port by path (``/dev/ttyACM0``, ``/dev/serial/by-id/...`` or a simulator's pty) with pyserial,
  reads it with ``loop.add_reader`` (never blocking the event loop) and opens/closes it in a thread;
- shakes hands (``HELLO``) and refuses a protocol mismatch with a message naming both versions;
- supervises the link: the controller's heartbeat (``HB``), answered pings, I/O errors. On a fault it
  reports the state, closes the port, retries with exponential backoff and comes back by itself
  (channel and lamp settings are replayed) without a restart of the service;
- turns ``BUTTON`` reports into :class:`~appliance.hardware.base.TriggerEvent` on the host's monotonic
  clock, and runs pulse sequences (``SEQ`` + ``FIRE``, then ``TRIG`` ... ``DONE``).

Every byte from the line goes through total parsers: nothing the controller (or noise) sends can raise.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import enum
import errno
import logging
import os
import select
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

import serial

from appliance.config.backends import SerialTriggerConfig
from appliance.errors import ConfigError, TriggerError
from appliance.firmware import protocol as P
from appliance.hardware.base import TriggerEvent

log = logging.getLogger(__name__)

# Module-level so tests can shorten them.
HANDSHAKE_TIMEOUT_S = 2.0  # HELLO answer
REQUEST_TIMEOUT_S = 1.0  # any other answer
REQUEST_RETRIES = 2  # re-sends of a request the controller saw corrupted (ERR BADFRAME)
RECONNECT_BACKOFF_MIN_S = 0.5
RECONNECT_BACKOFF_MAX_S = 10.0
CLOSE_TIMEOUT_S = 2.0  # closing a port that hangs (output never drains) is abandoned after this
DONE_GRACE_S = 2.0  # beyond n * period for the DONE of a sequence
CLOCK_WINDOW = 32  # ping samples kept for the controller-to-host clock offset
EVENT_QUEUE_MAX = 32  # button presses kept while nobody waits (oldest dropped)
PROBE_TIMEOUT_S = 1.0

_T_US_MAX = 2**62


class LinkState(enum.Enum):
    """Where the link to the controller stands."""

    CLOSED = "closed"
    CONNECTING = "connecting"
    READY = "ready"
    FAULT = "fault"


@dataclass(frozen=True)
class ControllerInfo:
    """What the controller said in its HELLO reply."""

    port: str
    proto: int
    firmware: str
    channels: int
    board_id: str


@dataclass
class LinkStats:
    """Counters for diagnostics (``scan3d status``)."""

    connects: int = 0
    faults: int = 0
    bad_frames: int = 0  # lines that failed to parse (noise, CRC errors, over-long)
    unexpected: int = 0  # valid frames nobody waited for (late replies, stale reports)
    controller_faults: int = 0  # FAULT reports


@dataclass
class _Channel:
    width_us: int
    delay_us: int = 0
    polarity: str = "high"
    enabled: bool = True


@dataclass
class _Run:
    n: int
    done: asyncio.Future[int]
    trig: dict[int, int] = field(default_factory=dict)


class _Refused(TriggerError):
    def __init__(self, message: str, reply: P.Message) -> None:
        super().__init__(message)
        self.reply = reply
        self.code = reply.get("code")


class _Link:
    """One opened port; a reconnect makes a new one, so late callbacks of an old one are recognisable."""

    def __init__(self, ser: serial.Serial, loop: asyncio.AbstractEventLoop) -> None:
        self.ser = ser
        self.fd: int = ser.fileno()
        self.lost: asyncio.Future[str] = loop.create_future()
        self.last_rx = time.monotonic()
        self.reading = False


def _open_port(port: str, baudrate: int) -> serial.Serial:
    ser = serial.Serial(port, baudrate, timeout=0, write_timeout=0, exclusive=True)
    ser.reset_input_buffer()  # stale reports of an earlier session
    return ser


class SerialTrigger:
    """The trigger controller as a :class:`~appliance.hardware.base.TriggerSource`.

    Parameters
    ----------
    cfg : SerialTriggerConfig
        Port, pulse width and period, heartbeat interval and timeout.
    name : str
        Name in messages and in :class:`TriggerEvent` ``source``.
    on_state : callable, optional
        Called with ``(state, reason)`` on every change of :attr:`state` (for the service's health).
    """

    emits_sequence_pulses = True  # run_sequence: the camera/projector pulses of a whole sequence
    has_lamps = True  # set_leds: the ready / busy / fault lamps

    def __init__(
        self,
        cfg: SerialTriggerConfig,
        name: str = "trigger",
        *,
        on_state: Callable[[LinkState, str], None] | None = None,
    ) -> None:
        self.name = name
        self.cfg = cfg
        self.port = cfg.port
        self.heartbeat_interval_s = cfg.heartbeat_interval_ms / 1000.0
        self.heartbeat_timeout_s = cfg.heartbeat_timeout_s
        if self.heartbeat_timeout_s <= 2 * self.heartbeat_interval_s:
            raise ConfigError(
                f"trigger {name!r}: heartbeat_timeout_s = {self.heartbeat_timeout_s} must exceed two "
                f"heartbeats of heartbeat_interval_ms = {cfg.heartbeat_interval_ms}; use about 3.5 intervals"
            )
        self.on_state = on_state
        self.state = LinkState.CLOSED
        self.reason = "not opened"
        self.info: ControllerInfo | None = None
        self.controller_state = "unknown"  # idle | armed | running, from the last heartbeat
        self.last_fault: str | None = None  # last FAULT code the controller reported
        self.stats = LinkStats()
        self._channels = {i: _Channel(cfg.pulse_width_us) for i in range(2)}
        self._leds: tuple[bool, bool, bool] | None = None
        self._events: asyncio.Queue[TriggerEvent | None] = asyncio.Queue()
        self._reader = P.LineReader()
        self._link: _Link | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._pending: dict[int, asyncio.Future[tuple[P.Message, int]]] = {}
        self._seq = 0
        self._run: _Run | None = None
        self._seq_lock = asyncio.Lock()
        self._clock: collections.deque[tuple[int, int]] = collections.deque(maxlen=CLOCK_WINDOW)
        self._last_t_us = -1
        self._state_changed = asyncio.Event()
        self._tasks: set[asyncio.Task[None]] = set()
        self._in_fault_episode = False

    # --- TriggerSource ---------------------------------------------------------------------------------

    async def open(self, *, require: bool = True) -> None:
        """Connect and shake hands; idempotent.

        Parameters
        ----------
        require : bool
            True: raise :class:`~appliance.errors.TriggerError` when the first attempt fails (absent port,
            no answer, protocol mismatch). False: return at once and keep trying in the background.
        """
        if self._supervisor is not None and not self._supervisor.done():
            return
        while not self._events.empty():  # drop a close() sentinel and stale presses
            self._events.get_nowait()
        first: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._supervisor = asyncio.create_task(self._supervise(first, require), name=f"serial-{self.name}")
        if not require:
            return
        try:
            await first
        except BaseException:
            await self.close()
            raise

    async def next_event(self) -> TriggerEvent:
        """Wait for the next button press (``TriggerEvent.t_monotonic_ns`` on the host's clock).

        Link faults do not end the wait (the driver reconnects); :meth:`close` does, with TriggerError.
        """
        event = await self._events.get()
        if event is None:
            self._events.put_nowait(None)  # wake every other waiter too
            raise TriggerError(f"trigger controller {self.name!r} on {self.port}: closed")
        return event

    async def close(self) -> None:
        """Say goodbye to the controller, stop supervising and release the port; idempotent."""
        task, self._supervisor = self._supervisor, None
        link = self._link
        if link is not None and self.state is LinkState.READY:
            with contextlib.suppress(TriggerError):
                await self._request(P.BYE, timeout_s=min(REQUEST_TIMEOUT_S, 0.5), link=link)
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._link is not None:
            await self._drop(self._link, "closed")
        for t in list(self._tasks):
            t.cancel()
        self._set_state(LinkState.CLOSED, "closed")
        self._events.put_nowait(None)

    # --- controller features ---------------------------------------------------------------------------

    async def run_sequence(
        self, n: int, period_us: int | None = None, *, timeout_s: float | None = None
    ) -> list[int]:
        """Fire ``n`` pulses, one every ``period_us`` on every enabled channel, and wait until done.

        Parameters
        ----------
        n : int
            Number of pulses (1..100000), e.g. the number of frames of a pattern sequence.
        period_us : int, optional
            Pulse period (µs, 100..10^7); the configured ``period_us`` when omitted.
        timeout_s : float, optional
            Limit for the whole sequence; ``n * period + DONE_GRACE_S`` by default.

        Returns
        -------
        list of int
            The controller's timestamps (µs, its own clock) of the pulses reported by ``TRIG``, in order;
            exactly ``n`` unless a report was lost on the line. :meth:`to_monotonic_ns` converts them.

        Raises
        ------
        TriggerError
            The link is not ready or fails, the controller refuses, or ``DONE`` does not come in time
            (the sequence is then aborted).
        """
        period = self.cfg.period_us if period_us is None else period_us
        if not (1 <= n <= P.N_MAX) or not (P.PERIOD_US_MIN <= period <= P.PERIOD_US_MAX):
            raise TriggerError(
                f"trigger {self.name!r}: sequence n = {n}, period_us = {period}: need 1 <= n <= {P.N_MAX} "
                f"and {P.PERIOD_US_MIN} <= period_us <= {P.PERIOD_US_MAX}"
            )
        async with self._seq_lock:
            link = self._require_ready()
            run = _Run(n, asyncio.get_running_loop().create_future())
            self._run = run
            try:
                await self._request(P.SEQ, {"n": n, "period_us": period, "report": 1}, link=link)
                await self._request(P.FIRE, link=link)
                limit = timeout_s if timeout_s is not None else n * period / 1e6 + DONE_GRACE_S
                try:
                    done_n = await asyncio.wait_for(run.done, limit)
                except TimeoutError:
                    self._spawn(self._abort_quietly(link))
                    raise TriggerError(
                        f"trigger controller {self.name!r} on {self.port}: no DONE within {limit:.2f} s of "
                        f"FIRE ({len(run.trig)} of {n} pulses reported); sequence aborted"
                    ) from None
            except asyncio.CancelledError:
                self._spawn(self._abort_quietly(link))
                raise
            finally:
                self._run = None
                if run.done.done() and not run.done.cancelled():
                    run.done.exception()  # retrieved: no "never retrieved" warning
        if done_n != n:
            raise TriggerError(f"trigger controller {self.name!r}: DONE after {done_n} pulses, {n} requested")
        if len(run.trig) != n:
            log.warning("trigger %r: %d of %d TRIG reports lost on the line", self.name, n - len(run.trig), n)
        return [run.trig[i] for i in sorted(run.trig)]

    async def abort(self) -> None:
        """Stop a running sequence (no-op when idle)."""
        await self._request(P.ABORT)

    async def configure_channel(
        self, ch: int, width_us: int, delay_us: int = 0, polarity: str = "high", enabled: bool = True
    ) -> None:
        """Set one output channel (kept and replayed after every reconnect).

        Parameters
        ----------
        ch : int
            Channel (0 cameras, 1 projector on the reference wiring).
        width_us, delay_us : int
            Pulse width and delay after the sequence tick (µs); ``delay_us + width_us < period_us``.
        polarity : {"high", "low"}
            Active level of the pulse.
        enabled : bool
            Whether the channel pulses at all.
        """
        if polarity not in P.POLARITIES or not (P.WIDTH_US_MIN <= width_us <= P.WIDTH_US_MAX):
            raise TriggerError(
                f"trigger {self.name!r}: channel {ch}: polarity {polarity!r} / width_us {width_us} invalid: "
                f"polarity high|low, {P.WIDTH_US_MIN} <= width_us <= {P.WIDTH_US_MAX}"
            )
        self._channels[ch] = _Channel(width_us, delay_us, polarity, enabled)
        if self.state is LinkState.READY:
            await self._request(P.CFG, self._cfg_fields(ch))

    async def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        """Set the lamps (kept and replayed after a reconnect; sent now when the link is ready)."""
        self._leds = (ready, busy, fault)
        if self.state is LinkState.READY:
            await self._request(P.LED, {"ready": ready, "busy": busy, "fault": fault})

    async def ping(self) -> float:
        """Round trip to the controller (s)."""
        t0 = time.monotonic()
        await self._request(P.PING)
        return time.monotonic() - t0

    async def wait_state(self, *states: LinkState, timeout_s: float) -> LinkState:
        """Wait until :attr:`state` is one of ``states``; raise TimeoutError after ``timeout_s``."""
        async with asyncio.timeout(timeout_s):
            while self.state not in states:
                event = self._state_changed
                await event.wait()
        return self.state

    def to_monotonic_ns(self, t_us: int) -> int:
        """Convert a controller timestamp (µs) to the host's CLOCK_MONOTONIC (ns).

        The offset comes from the ping with the shortest round trip among the last :data:`CLOCK_WINDOW`
        (its midpoint); the error is at most half that round trip plus the clocks' drift since.
        """
        if not self._clock:  # no sample yet (not connected): the best guess is "now"
            return time.monotonic_ns()
        _, offset = min(self._clock)
        return t_us * 1000 + offset

    def status(self) -> str:
        """One line: state, controller and last fault."""
        if self.state is LinkState.READY and self.info is not None:
            i = self.info
            return (f"ready: firmware {i.firmware} (protocol {i.proto}), {i.channels} channels, "
                    f"id {i.board_id}, controller {self.controller_state}")
        return f"{self.state.value}: {self.reason}"

    # --- supervision -----------------------------------------------------------------------------------

    async def _supervise(self, first: asyncio.Future[None], require: bool) -> None:
        backoff = RECONNECT_BACKOFF_MIN_S
        try:
            while True:
                self._set_state(LinkState.CONNECTING, f"opening {self.port}")
                try:
                    link = await self._connect()
                except (TriggerError, OSError, serial.SerialException) as exc:
                    if not isinstance(exc, TriggerError):
                        exc = TriggerError(f"trigger controller {self.name!r} on {self.port}: {exc}")
                    if require and not first.done():
                        first.set_exception(exc)
                        return
                    self._set_state(LinkState.FAULT, f"{exc}; retrying in {backoff:.2g} s")
                    await asyncio.sleep(backoff)
                    backoff = min(backoff * 2, RECONNECT_BACKOFF_MAX_S)
                    continue
                backoff = RECONNECT_BACKOFF_MIN_S
                if not first.done():
                    first.set_result(None)
                self._set_state(LinkState.READY, "connected")
                reason = await self._watch(link)
                await self._drop(link, reason)
                self._set_state(LinkState.FAULT, f"{reason}; reconnecting")
                await asyncio.sleep(backoff)
        finally:
            if self._link is not None:
                await self._drop(self._link, "closed")
            if not first.done():
                first.set_exception(TriggerError(f"trigger controller {self.name!r} on {self.port}: closed"))
                first.exception()

    async def _connect(self) -> _Link:
        where = f"trigger controller {self.name!r} on {self.port}"
        loop = asyncio.get_running_loop()
        try:
            ser = await asyncio.to_thread(_open_port, self.port, self.cfg.baudrate)
        except (serial.SerialException, OSError, ValueError) as exc:
            present = await asyncio.to_thread(os.path.exists, self.port)
            hint = "is another program using it?" if present else "is it plugged in? check the port path"
            raise TriggerError(f"{where}: cannot open: {exc}; {hint}") from None
        link = _Link(ser, loop)
        self._link = link
        self._reader.reset()
        self._clock.clear()
        self._last_t_us = -1
        loop.add_reader(link.fd, self._on_readable, link)
        link.reading = True
        try:
            try:
                hello = await self._request(
                    P.HELLO, {"proto": P.PROTO_VERSION, "hb_ms": round(self.heartbeat_interval_s * 1000)},
                    timeout_s=HANDSHAKE_TIMEOUT_S, link=link,
                )
            except _Refused as exc:
                if exc.code == P.E_PROTO:
                    raise self._mismatch(exc.reply) from None
                raise
            if hello.kind != P.HELLO or hello.get_int("proto", 0, 65535) != P.PROTO_VERSION:
                raise self._mismatch(hello)
            channels = hello.get_int("ch", 0, P.CHANNELS_MAX, 0) or 0
            self.info = ControllerInfo(self.port, P.PROTO_VERSION, hello.get("fw", "?"), channels,
                                       hello.get("id", "?"))
            self.controller_state = P.S_IDLE  # a new session starts idle
            for ch in range(channels):
                if ch in self._channels:
                    await self._request(P.CFG, self._cfg_fields(ch), link=link)
            if self._leds is not None:
                ready, busy, fault = self._leds
                await self._request(P.LED, {"ready": ready, "busy": busy, "fault": fault}, link=link)
        except BaseException as exc:
            await self._drop(link, f"handshake failed: {exc}")
            raise
        self.stats.connects += 1
        link.last_rx = time.monotonic()
        return link

    def _mismatch(self, reply: P.Message) -> TriggerError:
        return TriggerError(
            f"trigger controller {self.name!r} on {self.port}: its firmware {reply.get('fw', '?')} speaks "
            f"protocol {reply.get('proto', '?')}, this host speaks protocol {P.PROTO_VERSION} "
            f"(firmware {P.FW_VERSION}); install the matching firmware with "
            f"`scan3d firmware install --port {self.port}`"
        )

    async def _watch(self, link: _Link) -> str:
        """Return why the link died: I/O error, heartbeat loss, or the controller ending the session."""
        interval = self.heartbeat_interval_s
        next_ping = time.monotonic() + interval
        while True:
            done, _ = await asyncio.wait([link.lost], timeout=interval / 4)
            if done:
                return link.lost.result()
            now = time.monotonic()
            silent = now - link.last_rx
            if silent > self.heartbeat_timeout_s:
                return f"no heartbeat for {silent:.2f} s (limit {self.heartbeat_timeout_s:g} s)"
            if now >= next_ping:
                next_ping = now + interval
                self._spawn(self._ping_quietly(link))

    async def _ping_quietly(self, link: _Link) -> None:
        try:
            await self._request(P.PING, link=link)
        except _Refused as exc:
            if exc.code == P.E_NOHELLO:
                self._lose(link, "the controller ended the session (it stopped hearing the host)")
        except TriggerError:
            pass  # the heartbeat watch decides

    async def _abort_quietly(self, link: _Link) -> None:
        with contextlib.suppress(TriggerError):
            await self._request(P.ABORT, link=link)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _lose(self, link: _Link, reason: str) -> None:
        """Mark a link dead now (idempotent): stop reading, fail everything waiting on it."""
        if not link.lost.done():
            link.lost.set_result(reason)
        if link.reading:
            link.reading = False
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(link.fd)
        if link is not self._link:
            return
        error = f"trigger controller {self.name!r} on {self.port}: link lost: {reason}"
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(TriggerError(error))
        if self._run is not None and not self._run.done.done():
            self._run.done.set_exception(TriggerError(error))

    async def _drop(self, link: _Link, reason: str) -> None:
        self._lose(link, reason)
        if self._link is link:
            self._link = None
        with contextlib.suppress(Exception):
            link.ser.reset_output_buffer()  # nothing to drain: close() cannot hang on a dead device
        try:
            await asyncio.wait_for(asyncio.to_thread(link.ser.close), CLOSE_TIMEOUT_S)
        except (TimeoutError, OSError, serial.SerialException):
            log.debug("trigger %r: closing %s: gave up", self.name, self.port)

    def _set_state(self, state: LinkState, reason: str) -> None:
        if state is LinkState.FAULT:
            self.stats.faults += 1
            if not self._in_fault_episode:  # log the first failure and the recovery, not every retry
                log.warning("trigger %r on %s: %s", self.name, self.port, reason)
            else:
                log.debug("trigger %r on %s: %s", self.name, self.port, reason)
            self._in_fault_episode = True
        elif state is LinkState.READY:
            level = logging.INFO
            log.log(level, "trigger %r on %s: %s%s", self.name, self.port,
                    "recovered, " if self._in_fault_episode else "", self._connected_text())
            self._in_fault_episode = False
        if state is self.state and reason == self.reason:
            return
        self.state = state
        self.reason = reason
        event, self._state_changed = self._state_changed, asyncio.Event()
        event.set()
        if self.on_state is not None:
            try:
                self.on_state(state, reason)
            except Exception:
                log.exception("trigger %r: on_state callback failed", self.name)

    def _connected_text(self) -> str:
        i = self.info
        if i is None:
            return "connected"
        return f"connected: firmware {i.firmware} (protocol {i.proto}), id {i.board_id}"

    # --- requests --------------------------------------------------------------------------------------

    def _require_ready(self) -> _Link:
        if self.state is not LinkState.READY or self._link is None:
            raise TriggerError(f"trigger controller {self.name!r} on {self.port}: not ready "
                               f"({self.state.value}: {self.reason})")
        return self._link

    def _cfg_fields(self, ch: int) -> dict[str, object]:
        c = self._channels[ch]
        return {"ch": ch, "width_us": c.width_us, "delay_us": c.delay_us, "polarity": c.polarity,
                "en": c.enabled}

    def _next_seq(self) -> int:
        self._seq = self._seq % P.SEQ_MAX + 1  # 1..65535; 0 is for unsolicited messages
        return self._seq

    async def _request(
        self, kind: str, fields: dict[str, object] | None = None, *, timeout_s: float | None = None,
        link: _Link | None = None,
    ) -> P.Message:
        link = link if link is not None else self._require_ready()
        timeout = REQUEST_TIMEOUT_S if timeout_s is None else timeout_s
        loop = asyncio.get_running_loop()
        where = f"trigger controller {self.name!r} on {self.port}"
        for attempt in range(REQUEST_RETRIES + 1):
            if link.lost.done():
                raise TriggerError(f"{where}: link lost: {link.lost.result()}")
            seq = self._next_seq()
            fut: asyncio.Future[tuple[P.Message, int]] = loop.create_future()
            self._pending[seq] = fut
            try:
                sent_ns = time.monotonic_ns()
                self._send(link, P.encode(kind, seq, fields))
                reply, rx_ns = await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise TriggerError(f"{where}: no answer to {kind} within {timeout * 1000:.0f} ms") from None
            finally:
                self._pending.pop(seq, None)
            if reply.kind == P.ERR:
                code = reply.get("code", "?")
                if code == P.E_BADFRAME and attempt < REQUEST_RETRIES:
                    continue
                key = reply.get("key")
                raise _Refused(f"{where}: {kind} refused: {code}" + (f" ({key})" if key else "")
                               + _ERR_HINTS.get(code, ""), reply)
            t_us = reply.get_int("t_us", 0, _T_US_MAX)
            if kind in (P.PING, P.HELLO) and t_us is not None:
                self._clock.append((rx_ns - sent_ns, (sent_ns + rx_ns) // 2 - t_us * 1000))
            return reply
        raise TriggerError(f"{where}: {kind} corrupted on the line {REQUEST_RETRIES + 1} times")

    def _send(self, link: _Link, frame: bytes) -> None:
        data = b"\n" + frame  # the newline ends any noise the controller may hold as a partial line
        try:
            _, writable, _ = select.select([], [link.fd], [], 0)
            written = link.ser.write(data) if writable else 0
        except (serial.SerialException, OSError, ValueError) as exc:
            self._lose(link, f"write failed: {exc}")
            raise TriggerError(f"trigger controller {self.name!r} on {self.port}: write failed: {exc}") \
                from None
        if written != len(data):
            self._lose(link, "output stalled (the controller does not read)")
            raise TriggerError(f"trigger controller {self.name!r} on {self.port}: output stalled")

    # --- input -----------------------------------------------------------------------------------------

    def _on_readable(self, link: _Link) -> None:
        if not link.reading:
            return
        try:
            data = link.ser.read(4096)
        except (serial.SerialException, OSError, TypeError, ValueError) as exc:
            self._lose(link, f"read failed: {exc}")
            return
        if link is self._link:
            self._receive(data)

    def _receive(self, data: bytes) -> None:
        """Parse received bytes and act on every valid frame; total (never raises on any bytes)."""
        rx_ns = time.monotonic_ns()
        for line in self._reader.feed(data):
            msg = P.decode(line) if line is not None else None
            if msg is None:
                self.stats.bad_frames += 1
                continue
            if self._link is not None:
                self._link.last_rx = time.monotonic()
            self._dispatch(msg, rx_ns)

    def _dispatch(self, msg: P.Message, rx_ns: int) -> None:
        kind = msg.kind
        t_us = msg.get_int("t_us", 0, _T_US_MAX)
        if t_us is not None:
            if t_us < self._last_t_us:  # the controller restarted: its clock began again
                self._clock.clear()
            self._last_t_us = t_us
        if kind in (P.OK, P.ERR, P.HELLO) and msg.seq != 0:
            fut = self._pending.get(msg.seq)
            if fut is not None and not fut.done():
                fut.set_result((msg, rx_ns))
            else:
                self.stats.unexpected += 1
        elif kind == P.HB:
            state = msg.get("state")
            if state in (P.S_IDLE, P.S_ARMED, P.S_RUNNING):
                self.controller_state = state
        elif kind == P.BUTTON and t_us is not None:
            t_ns = min(self.to_monotonic_ns(t_us), rx_ns) if self._clock else rx_ns
            self._put_event(TriggerEvent(self.name, t_ns, f"button {msg.get('id', '0')} t_us={t_us}"))
        elif kind == P.TRIG and self._run is not None:
            i = msg.get_int("i", 0, P.N_MAX)
            if i is not None and t_us is not None and i < self._run.n:
                self._run.trig[i] = t_us
        elif kind == P.DONE and self._run is not None and not self._run.done.done():
            n = msg.get_int("n", 0, P.N_MAX)
            self._run.done.set_result(n if n is not None else -1)
        elif kind == P.FAULT:
            self.stats.controller_faults += 1
            self.last_fault = msg.get("code", "?")
            log.warning("trigger %r: controller reports fault %s %s", self.name, self.last_fault,
                        msg.get("what"))
        else:
            self.stats.unexpected += 1

    def _put_event(self, event: TriggerEvent) -> None:
        if self._events.qsize() >= EVENT_QUEUE_MAX:
            with contextlib.suppress(asyncio.QueueEmpty):
                self._events.get_nowait()
        self._events.put_nowait(event)


_ERR_HINTS = {
    P.E_BUSY: "; a sequence is running (wait for it or abort it)",
    P.E_STATE: "; the controller is not armed",
    P.E_RANGE: "; a value is outside the controller's limits (docs/serial-protocol.md)",
    P.E_NOHELLO: "; the controller has no session (it restarted or stopped hearing the host)",
    P.E_UNKNOWN: "; the firmware does not know this request (update it)",
}


def probe_serial(port: str, timeout_s: float | None = None) -> str:
    """Open ``port``, shake hands, say goodbye, and describe what answered in one line (``scan3d devices``).

    Blocking (call it from a thread in async code). Never raises.

    Parameters
    ----------
    port : str
        Serial device path.
    timeout_s : float, optional
        How long to wait for the HELLO answer (:data:`PROBE_TIMEOUT_S` by default).

    Returns
    -------
    str
        e.g. ``"trigger controller: firmware 1.0.0 (protocol 1), 2 channels, id E66058388B4F2A2C"`` or
        ``"absent (no such device)"``.
    """
    if not os.path.exists(port):
        return "absent (no such device)"
    try:
        ser = serial.Serial(port, 115200, timeout=0.05, write_timeout=1.0, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        busy = isinstance(exc, OSError) and exc.errno in (errno.EBUSY, errno.EAGAIN)
        if busy or "lock" in str(exc).lower():
            return "busy (in use, e.g. by the running scan3d service)"
        return f"cannot open: {exc}"
    limit = PROBE_TIMEOUT_S if timeout_s is None else timeout_s
    reader = P.LineReader()
    try:
        with ser:
            ser.reset_input_buffer()
            ser.write(b"\n" + P.encode(P.HELLO, 1, {"proto": P.PROTO_VERSION, "hb_ms": P.HB_MS_DEFAULT}))
            deadline = time.monotonic() + limit
            while time.monotonic() < deadline:
                for line in reader.feed(ser.read(256)):
                    msg = P.decode(line) if line is not None else None
                    if msg is None or msg.seq != 1:
                        continue
                    if (msg.kind == P.ERR and msg.get("code") == P.E_PROTO) or (
                        msg.kind == P.HELLO and msg.get("proto") != str(P.PROTO_VERSION)
                    ):
                        return (f"protocol mismatch: firmware {msg.get('fw', '?')} speaks protocol "
                                f"{msg.get('proto', '?')}, host speaks {P.PROTO_VERSION}; "
                                "run scan3d firmware install")
                    if msg.kind == P.HELLO:
                        ser.write(b"\n" + P.encode(P.BYE, 2))
                        ser.flush()
                        return (f"trigger controller: firmware {msg.get('fw', '?')} "
                                f"(protocol {msg.get('proto')}), {msg.get('ch', '?')} channels, "
                                f"id {msg.get('id', '?')}")
                    return f"answered {msg.kind} {msg.get('code')}: not a scan3d trigger controller?"
            return (f"no answer within {limit:g} s (not a scan3d trigger controller? "
                    "install the firmware with scan3d firmware install)")
    except (serial.SerialException, OSError) as exc:
        return f"I/O error: {exc}"
