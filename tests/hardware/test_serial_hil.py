"""Trigger controller: protocol, firmware logic, and the host driver against the firmware on a pty.

The ``hil`` tests run the real firmware logic (:mod:`appliance.firmware.controller`) behind a
pseudo-terminal and the real host stack (pyserial + :mod:`appliance.hardware.serial`) in front of it.
Every wait is event-based with generous limits; timing constants are shortened through the modules.
"""

from __future__ import annotations

import ast
import asyncio
import binascii
import itertools
import os
import random
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.config.backends import SerialTriggerConfig
from appliance.errors import BackendUnavailableError, TriggerError
from appliance.firmware import controller as C
from appliance.firmware import protocol as P
from appliance.firmware.simulate import SimulatedController
from appliance.hardware import firmware_install
from appliance.hardware import serial as S

FIRMWARE_DIR = Path(P.__file__).resolve().parent

# --- test doubles ---------------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 1_000_000

    def __call__(self) -> int:
        return self.now


class Wire:
    """Collects what the controller writes, decoded."""

    def __init__(self) -> None:
        self.reader = P.LineReader()
        self.messages: list[P.Message] = []

    def __call__(self, data: bytes) -> None:
        for line in self.reader.feed(data):
            assert line is not None
            msg = P.decode(line)
            assert msg is not None, line
            self.messages.append(msg)

    def take(self) -> list[P.Message]:
        out, self.messages = self.messages, []
        return out


def make_controller(**kw: object) -> tuple[C.Controller, FakeClock, Wire]:
    clock, wire = FakeClock(), Wire()
    ctl = C.Controller(clock, C.Pins(), wire, board_id="TEST", **kw)  # type: ignore[arg-type]
    return ctl, clock, wire


def request(ctl: C.Controller, wire: Wire, kind: str, seq: int, **fields: object) -> list[P.Message]:
    ctl.feed(P.encode(kind, seq, fields))
    return wire.take()


def hello(ctl: C.Controller, wire: Wire, hb_ms: int = 1000) -> P.Message:
    (reply,) = request(ctl, wire, P.HELLO, 1, proto=P.PROTO_VERSION, hb_ms=hb_ms)
    return reply


# --- protocol -------------------------------------------------------------------------------------------


def test_crc_check_value_and_crc_hqx() -> None:
    assert P.crc16(b"123456789") == 0x29B1
    assert P.crc16(b"") == 0xFFFF
    assert P.crc16(b"56789", P.crc16(b"1234")) == 0x29B1  # continues a running CRC


@given(st.binary(max_size=300))
def test_crc_matches_binascii(data: bytes) -> None:
    assert P.crc16(data) == binascii.crc_hqx(data, 0xFFFF)


_key = st.text("abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=8)
_value = st.text(st.characters(min_codepoint=0x21, max_codepoint=0x7E, exclude_characters="*="), min_size=1,
                 max_size=12)


@given(
    kind=st.text("ABCDEFGHIJKLMNOPQRSTUVWXYZ", min_size=1, max_size=8),
    seq=st.integers(0, P.SEQ_MAX),
    fields=st.dictionaries(_key, _value, max_size=5),
)
def test_encode_decode_roundtrip(kind: str, seq: int, fields: dict[str, str]) -> None:
    frame = P.encode(kind, seq, fields)
    assert frame.endswith(b"\n") and len(frame) <= P.MAX_LINE
    assert P.decode(frame[:-1]) == P.Message(kind, seq, fields)
    assert P.decode(frame[:-1] + b"\r") == P.Message(kind, seq, fields)  # a terminal's CR LF


def test_decode_rejects_corruption_and_bad_frames() -> None:
    frame = P.encode("SEQ", 12, {"n": 28, "period_us": 16667})[:-1]
    assert P.decode(frame) == P.Message("SEQ", 12, {"n": "28", "period_us": "16667"})
    for i in range(len(frame)):  # every single-bit flip of every byte is caught
        for bit in range(8):
            bad = bytearray(frame)
            bad[i] ^= 1 << bit
            assert P.decode(bytes(bad)) is None, (i, bit)
    assert P.frame_seq(b"SEQ 12 n=28 *0000") == 12
    bad_lines = (b"", b"*", b"seq 1 *ABCD", b"SEQ 99999 *0000", b"SEQ x *0000", b"SEQ 1 a *0",
                 b"SEQ 1 =2 *00FF")
    for line in bad_lines:
        assert P.decode(line) is None
    with pytest.raises(ValueError, match="bytes, more than"):
        P.encode("SEQ", 1, {"x": "y" * 60, "z": "w" * 60})
    with pytest.raises(ValueError, match="cannot frame field"):
        P.encode("SEQ", 1, {"x": "has space"})


def test_line_reader_resynchronises_after_overlong_line() -> None:
    reader = P.LineReader()
    frame = P.encode("PING", 3)
    assert reader.feed(b"x" * 300) == []
    assert reader.feed(b"yy\n\n\r\n" + frame[:5]) == [None]  # one report per over-long line, blanks skipped
    assert reader.feed(frame[5:]) == [frame[:-1]]


def test_firmware_files_are_plain_micropython_compatible_python() -> None:
    """protocol/controller import nothing CPython-only; main imports machine/rp2 only behind a guard."""
    allowed = {"protocol", "controller", "appliance.firmware", "sys", "select", "time", "machine", "rp2",
               "collections.abc", "typing"}
    for name in ("protocol.py", "controller.py", "main.py"):
        tree = ast.parse((FIRMWARE_DIR / name).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert node.module != "__future__", name
                assert node.module in allowed, (name, node.module)
            elif isinstance(node, ast.Import):
                assert all(a.name in allowed for a in node.names), (name, [a.name for a in node.names])
        for node in tree.body:  # typing only inside "if TYPE_CHECKING:" at module level
            if isinstance(node, ast.ImportFrom) and node.module in ("typing", "collections.abc"):
                pytest.fail(f"{name} imports {node.module} at run time")


def test_firmware_runs_from_a_flat_folder_like_the_board(tmp_path: Path) -> None:
    """On the board the files sit flat in the root folder; the fallback imports must work there."""
    for name in firmware_install.FIRMWARE_FILES:
        (tmp_path / name).write_bytes((FIRMWARE_DIR / name).read_bytes())
    code = (
        "import sys; sys.modules['appliance'] = None\n"  # make the package import fail, as on the board
        "import controller, protocol, main\n"
        "out = []\n"
        "ctl = controller.Controller(lambda: 5, controller.Pins(), out.append)\n"
        "ctl.feed(protocol.encode('HELLO', 1, {'proto': protocol.PROTO_VERSION}))\n"
        "assert out and out[0].startswith(b'HELLO 1 proto='), out\n"
        "assert not main.ON_BOARD\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                          timeout=60, env=env, check=False)
    assert proc.returncode == 0, proc.stderr


# --- firmware logic with an injected clock --------------------------------------------------------------


def test_controller_requires_hello_and_checks_protocol_version() -> None:
    ctl, _, wire = make_controller()
    (reply,) = request(ctl, wire, P.PING, 4)
    assert (reply.kind, reply.seq, reply.get("code")) == (P.ERR, 4, P.E_NOHELLO)
    (reply,) = request(ctl, wire, P.HELLO, 5, proto=P.PROTO_VERSION + 1)
    assert (reply.kind, reply.get("code"), reply.get("proto"), reply.get("fw")) == (
        P.ERR, P.E_PROTO, str(P.PROTO_VERSION), P.FW_VERSION)
    reply = hello(ctl, wire)
    assert reply.kind == P.HELLO and reply.get("id") == "TEST" and reply.get("ch") == "2"
    (reply,) = request(ctl, wire, "FOO", 6)
    assert reply.get("code") == P.E_UNKNOWN


def test_controller_sequencer_timing_and_states() -> None:
    ctl, clock, wire = make_controller()
    hello(ctl, wire)
    assert request(ctl, wire, P.FIRE, 2)[0].get("code") == P.E_STATE
    assert request(ctl, wire, P.CFG, 3, ch=1, width_us=300, delay_us=50, polarity="low")[0].kind == P.OK
    assert request(ctl, wire, P.CFG, 4, ch=2, width_us=10)[0].get("key") == "ch"
    assert request(ctl, wire, P.SEQ, 5, n=3, period_us=350)[0].get("key") == "period_us"  # 50 + 300 >= 350
    assert request(ctl, wire, P.SEQ, 6, n=0, period_us=1000)[0].get("key") == "n"
    assert request(ctl, wire, P.SEQ, 7, n=5, period_us=1000)[0].kind == P.OK
    assert ctl.state == P.S_ARMED
    (ok,) = request(ctl, wire, P.FIRE, 8)
    t0 = int(ok.get("t_us"))
    assert t0 == 0  # the null pins start at 0
    assert request(ctl, wire, P.SEQ, 9, n=5, period_us=1000)[0].get("code") == P.E_BUSY
    clock.now = t0 + 2500  # pulses 0, 1, 2 are due
    ctl.poll()
    msgs = wire.take()
    assert [(m.kind, m.get("i"), m.get("t_us")) for m in msgs] == [
        (P.TRIG, str(i), str(t0 + 1000 * i)) for i in range(3)]
    clock.now = t0 + 4000 + 350
    ctl.poll()
    msgs = wire.take()
    assert [m.kind for m in msgs] == [P.TRIG, P.TRIG, P.DONE]
    assert msgs[-1].get("n") == "5" and msgs[-1].get("t_us") == str(t0 + 4000 + 350)  # last pulse's end
    assert ctl.state == P.S_IDLE


def test_controller_debounces_the_button() -> None:
    ctl, clock, wire = make_controller()
    hello(ctl, wire)
    start = clock.now
    for dt, level in ((0, True), (300, False), (700, True), (1500, False), (2100, True)):  # contact bounce
        ctl.button(level, start + dt)
    clock.now = start + 2100 + C.DEBOUNCE_US - 1
    ctl.poll()
    assert wire.take() == []  # not yet stable for DEBOUNCE_US
    clock.now += 1
    ctl.poll()
    (press,) = wire.take()
    assert press.kind == P.BUTTON and press.get("t_us") == str(start)  # the first edge of the burst
    ctl.button(False, clock.now + 100)
    ctl.button(True, clock.now + 5000)  # released for less than the debounce time: same press
    clock.now += 5000 + C.DEBOUNCE_US
    ctl.poll()
    assert wire.take() == []


def test_controller_heartbeat_and_host_loss() -> None:
    ctl, clock, wire = make_controller()
    hello(ctl, wire, hb_ms=100)
    beats = 0
    for _ in range(10):
        clock.now += 50_000
        ctl.poll()
        beats += sum(m.kind == P.HB for m in wire.take())
        if clock.now % 100_000 == 0:
            request(ctl, wire, P.PING, 9)  # the host stays alive
    assert beats == 5
    clock.now += 400_000  # three and a half beats without the host
    ctl.poll()
    msgs = wire.take()
    assert [m.kind for m in msgs] == [P.FAULT] and msgs[0].get("code") == P.F_HOSTLOST
    assert not ctl.session and ctl.leds == (False, False, True)
    assert request(ctl, wire, P.PING, 10)[0].get("code") == P.E_NOHELLO


def _frame(kind: str, seq: int, fields: dict[str, str]) -> bytes:
    """A valid frame of ``kind``: fields are dropped (last first) until it fits the protocol's line limit."""
    items = list(fields.items())
    while True:
        try:
            return P.encode(kind, seq, dict(items))
        except ValueError:
            if not items:
                raise
            items.pop()


_frames = st.builds(
    _frame,
    st.sampled_from(P.REQUESTS + P.REPLIES + ("XYZ",)),
    st.integers(0, P.SEQ_MAX),
    st.dictionaries(st.sampled_from(["n", "i", "t_us", "period_us", "ch", "width_us", "proto", "code",
                                     "state", "ready", "report", "hb_ms", "polarity", "en"]),
                    st.one_of(st.integers(-5, 2**64).map(str), _value), max_size=5),
)
_noise = st.lists(st.one_of(st.binary(max_size=200), _frames), max_size=12).map(b"".join)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(noise=_noise, chunk=st.integers(1, 64))
def test_firmware_parser_is_total_and_resynchronises(noise: bytes, chunk: int) -> None:
    out: list[bytes] = []
    clock = FakeClock()
    ctl = C.Controller(clock, C.Pins(), out.append)
    ctl.feed(P.encode(P.HELLO, 1, {"proto": P.PROTO_VERSION}))
    for i in range(0, len(noise), chunk):
        ctl.feed(noise[i:i + chunk])
        clock.now += 1000
        ctl.poll()
    if not ctl.session:
        ctl.feed(b"\n" + P.encode(P.HELLO, 2, {"proto": P.PROTO_VERSION}))
    out.clear()
    ctl.feed(b"\n" + P.encode(P.PING, 777))
    replies = [P.decode(line) for line in P.LineReader().feed(b"".join(out)) if line is not None]
    assert any(m is not None and m.kind == P.OK and m.seq == 777 for m in replies), replies


@settings(max_examples=150, deadline=None)
@given(noise=_noise, chunk=st.integers(1, 64))
def test_host_parser_is_total(noise: bytes, chunk: int) -> None:
    loop = asyncio.new_event_loop()
    try:
        trig = S.SerialTrigger(SerialTriggerConfig(port="/nonexistent"))
        trig._run = S._Run(5, loop.create_future())
        trig._pending[3] = loop.create_future()
        for i in range(0, len(noise), chunk):
            trig._receive(noise[i:i + chunk])
        trig._receive(b"\n" + P.encode(P.DONE, 0, {"n": 5}))
        assert trig._run.done.done()
    finally:
        loop.close()


# --- firmware install -----------------------------------------------------------------------------------


def test_install_firmware_runs_mpremote(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = tmp_path / "args.txt"
    fake = tmp_path / "bin" / "mpremote"
    fake.parent.mkdir()
    fake.write_text(f"#!/bin/sh\nprintf '%s\\n' \"$@\" > {log}\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    port = tmp_path / "ttyACM9"
    port.write_text("")
    monkeypatch.setenv("PATH", str(fake.parent))
    firmware_install.install_firmware(str(port), verify=False)
    args = log.read_text().split("\n")
    assert args[:2] == ["connect", str(port)]
    copied = [args[i + 2] for i, a in enumerate(args) if a == "cp"]
    assert copied == [":protocol.py", ":controller.py", ":main.py"]  # main.py last
    for i, a in enumerate(args):
        if a == "cp":
            assert Path(args[i + 1]).read_bytes() == (FIRMWARE_DIR / args[i + 2][1:]).read_bytes()
    assert args[-2] == "reset"


def test_install_firmware_without_mpremote(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(sys, "executable", str(tmp_path / "python"))
    with pytest.raises(BackendUnavailableError, match="pip install 'mpremote"):
        firmware_install.install_firmware("/dev/ttyACM0")


# --- hardware in the loop: the firmware on a pty, the host through pyserial ------------------------------


@pytest.fixture
def fast(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(S, "RECONNECT_BACKOFF_MIN_S", 0.02)
    monkeypatch.setattr(S, "RECONNECT_BACKOFF_MAX_S", 0.2)
    monkeypatch.setattr(S, "HANDSHAKE_TIMEOUT_S", 1.0)
    monkeypatch.setattr(S, "DONE_GRACE_S", 3.0)


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimulatedController]:
    controller = SimulatedController(tmp_path / "by-id-trigger")
    controller.start()
    yield controller
    thread = controller._thread
    controller.close()
    assert thread is not None and not thread.is_alive()


def config(port: str, hb_ms: int = 1000, timeout_s: float = 3.5) -> SerialTriggerConfig:
    return SerialTriggerConfig(port=port, heartbeat_interval_ms=hb_ms, heartbeat_timeout_s=timeout_s,
                               pulse_width_us=50, period_us=2000)


def run(coro_fn: object, limit_s: float = 15.0) -> object:
    async def bounded() -> object:
        return await asyncio.wait_for(coro_fn(), limit_s)  # type: ignore[operator]

    return asyncio.run(bounded())


class RawPort:
    """The host side without the driver: pyserial and the protocol module, for malformed traffic."""

    def __init__(self, path: str) -> None:
        self.ser = serial.Serial(path, 115200, timeout=0.05)
        self.reader = P.LineReader()

    def send(self, data: bytes) -> None:
        self.ser.write(data)

    def wait_for(self, kind: str, seq: int, limit_s: float = 5.0) -> P.Message:
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline:
            for line in self.reader.feed(self.ser.read(256)):
                msg = P.decode(line) if line is not None else None
                if msg is not None and msg.kind == kind and msg.seq == seq:
                    return msg
        raise AssertionError(f"no {kind} {seq} within {limit_s} s")

    def close(self) -> None:
        self.ser.close()


@pytest.mark.hil
def test_handshake_sequence_and_probe(sim: SimulatedController, fast: None) -> None:
    assert sim.link is not None

    async def body() -> None:
        trig = S.SerialTrigger(config(sim.link or ""), name="line-button")
        await trig.open()
        await trig.open()  # idempotent
        assert trig.state is S.LinkState.READY and trig.info is not None
        assert (trig.info.firmware, trig.info.proto, trig.info.channels, trig.info.board_id) == (
            P.FW_VERSION, P.PROTO_VERSION, 2, "SIM00000001")
        busy = await asyncio.to_thread(S.probe_serial, sim.link or "")
        assert busy == "busy (in use, e.g. by the running scan3d service)"
        await trig.configure_channel(1, width_us=200, delay_us=100, polarity="low")
        for _ in range(5):
            await trig.ping()  # clock samples for to_monotonic_ns
        before = time.monotonic_ns()
        stamps = await trig.run_sequence(24, 2500)
        after = time.monotonic_ns()
        assert len(stamps) == 24
        assert all(b - a == 2500 for a, b in itertools.pairwise(stamps))
        assert after - before >= 23 * 2500 * 1000  # the host waited for DONE: the train had time to run
        first = trig.to_monotonic_ns(stamps[0])
        assert before - 50_000_000 <= first <= after - 23 * 2500 * 1000  # on the host clock, 50 ms slack
        train = sim.pins.trains[-1]
        assert (train.n, train.period_us, train.t0_us) == (24, 2500, stamps[0])
        assert train.channels == [(0, 50, 0, "high"), (1, 200, 100, "low")]
        await trig.set_leds(ready=True, busy=False, fault=False)
        assert sim.pins.leds == (True, False, False)
        await trig.close()
        assert not sim.controller.session and sim.pins.leds == (False, False, False)  # BYE
        with pytest.raises(TriggerError, match="closed"):
            await trig.next_event()

    run(body)
    status = S.probe_serial(sim.link or "")
    assert status == (f"trigger controller: firmware {P.FW_VERSION} (protocol {P.PROTO_VERSION}), "
                      "2 channels, id SIM00000001")
    assert S.probe_serial("/dev/nonexistent-tty") == "absent (no such device)"


@pytest.mark.hil
def test_version_mismatch_names_both_versions(tmp_path: Path, fast: None) -> None:
    with SimulatedController(tmp_path / "tty", proto=P.PROTO_VERSION + 1, fw="9.9.9") as other:
        async def body() -> None:
            trig = S.SerialTrigger(config(other.link or ""))
            with pytest.raises(TriggerError) as err:
                await trig.open()
            message = str(err.value)
            assert f"firmware 9.9.9 speaks protocol {P.PROTO_VERSION + 1}" in message
            assert f"this host speaks protocol {P.PROTO_VERSION} (firmware {P.FW_VERSION})" in message
            assert "scan3d firmware install" in message
            assert trig.state is S.LinkState.CLOSED

        run(body)
        assert "protocol mismatch" in S.probe_serial(other.link or "")


@pytest.mark.hil
def test_button_presses_become_trigger_events(sim: SimulatedController, fast: None) -> None:
    async def body() -> None:
        trig = S.SerialTrigger(config(sim.link or ""), name="foot")
        await trig.open()
        for _ in range(5):
            await trig.ping()  # clock samples: the offset comes from the shortest round trip
        pressed = []
        for _ in range(3):
            pressed.append(time.monotonic_ns())
            sim.press_button(hold_s=0.03)
            event = await asyncio.wait_for(trig.next_event(), 5.0)
            assert event.source == "foot" and event.detail.startswith("button 0")
            # the controller stamps the first edge: the event time is the press, not the report's arrival
            received = time.monotonic_ns()
            assert pressed[-1] - 10_000_000 <= event.t_monotonic_ns <= received
            assert received - event.t_monotonic_ns >= C.DEBOUNCE_US * 1000 * 0.8  # before the debounce
            await asyncio.sleep(0.03 + 2 * C.DEBOUNCE_US / 1e6)  # released and settled before the next
        await trig.close()

    run(body)


@pytest.mark.hil
def test_crc_errors_and_garbage_are_answered_badframe(sim: SimulatedController) -> None:
    port = RawPort(sim.path)
    try:
        port.send(P.encode(P.HELLO, 1, {"proto": P.PROTO_VERSION}))
        assert port.wait_for(P.HELLO, 1).get("fw") == P.FW_VERSION
        good = P.encode(P.SEQ, 7, {"n": 3, "period_us": 1000})
        bad = good.replace(b"n=3", b"n=4")  # payload changed, CRC not
        port.send(bad)
        assert port.wait_for(P.ERR, 7).get("code") == P.E_BADFRAME
        rng = random.Random(1234)
        for _ in range(20):  # noise, over-long lines, NULs, high bytes...
            port.send(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 400))))
        port.send(b"\n" + P.encode(P.PING, 8))
        assert port.wait_for(P.OK, 8).get("state") == P.S_IDLE
        assert sim.controller.errors >= 2
        port.send(good)
        assert port.wait_for(P.OK, 7).kind == P.OK
        port.send(P.encode(P.FIRE, 9))
        assert port.wait_for(P.DONE, 0).get("n") == "3"
    finally:
        port.close()


@pytest.mark.hil
def test_host_survives_noise_from_the_controller(sim: SimulatedController, fast: None) -> None:
    async def body() -> None:
        trig = S.SerialTrigger(config(sim.link or ""))
        await trig.open()
        rng = random.Random(99)
        noise = bytes(rng.randrange(256) for _ in range(3000)) + b"\nOK 5 *FFFF\n" + b"A" * 500 + b"\n"
        sim.send_raw(noise)
        await trig.ping()  # the reply comes after the noise in the stream: the noise has been parsed
        assert trig.stats.bad_frames >= 2
        assert trig.state is S.LinkState.READY
        assert len(await trig.run_sequence(10, 1000)) == 10
        await trig.close()

    run(body)


@pytest.mark.hil
def test_heartbeat_loss_is_a_fault_and_recovers(sim: SimulatedController, fast: None) -> None:
    states: list[S.LinkState] = []

    async def body() -> None:
        trig = S.SerialTrigger(config(sim.link or "", hb_ms=200, timeout_s=0.7),
                               on_state=lambda s, _reason: states.append(s))
        await trig.open()
        await trig.set_leds(ready=True, busy=False, fault=False)
        sim.pause()  # the board hangs: no heartbeats, no answers
        await trig.wait_state(S.LinkState.FAULT, timeout_s=5.0)
        assert "no heartbeat" in trig.reason
        with pytest.raises(TriggerError, match="not ready"):
            await trig.run_sequence(3, 1000)
        sim.resume()
        await trig.wait_state(S.LinkState.READY, timeout_s=10.0)
        assert len(await trig.run_sequence(5, 1000)) == 5
        assert sim.pins.leds == (True, False, False)  # lamps replayed after the reconnect
        assert trig.stats.connects >= 2
        await trig.close()

    run(body)
    assert states[0] is S.LinkState.CONNECTING and S.LinkState.FAULT in states
    assert states[-2:] == [S.LinkState.READY, S.LinkState.CLOSED]


@pytest.mark.hil
def test_unplug_and_replug_recovers_by_itself(sim: SimulatedController, fast: None) -> None:
    async def body() -> None:
        trig = S.SerialTrigger(config(sim.link or ""))
        await trig.open()
        await trig.configure_channel(0, width_us=77)
        waiter = asyncio.create_task(trig.next_event())
        sim.unplug()  # USB cable out: the read fails at once, the by-id link disappears
        await trig.wait_state(S.LinkState.FAULT, timeout_s=5.0)
        assert "read failed" in trig.reason or "cannot open" in trig.reason
        await asyncio.sleep(0.1)  # a few failed reopen attempts while it is away
        assert trig.state is not S.LinkState.READY
        sim.plug()  # back on a new pty; the link follows it
        await trig.wait_state(S.LinkState.READY, timeout_s=10.0)
        assert not waiter.done()  # next_event() waited through the fault
        sim.press_button(hold_s=0.03)
        assert (await asyncio.wait_for(waiter, 5.0)).detail.startswith("button")
        assert len(await trig.run_sequence(4, 1000)) == 4
        assert sim.pins.trains[-1].channels[0] == (0, 77, 0, "high")  # channel settings replayed
        await trig.close()

    run(body)


@pytest.mark.hil
def test_cancelled_sequence_is_aborted_on_the_controller(sim: SimulatedController, fast: None) -> None:
    async def body() -> None:
        trig = S.SerialTrigger(config(sim.link or ""))
        await trig.open()
        task = asyncio.create_task(trig.run_sequence(1000, 10_000))  # 10 s
        while sim.controller.state != P.S_RUNNING:  # noqa: ASYNC110 (state of the simulator's thread)
            await asyncio.sleep(0.005)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        await trig.ping()
        await trig.ping()  # the ABORT went out before these: the controller is idle again
        assert sim.controller.state == P.S_IDLE and sim.pins.trains[-1].stopped_us is not None
        assert len(await trig.run_sequence(2, 1000)) == 2
        await trig.close()

    run(body)
