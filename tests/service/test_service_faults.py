"""The service survives its faults and never dies silently: the reload/trigger race, a scan that raises,
supervision of its tasks (fault and exit status 1), the watchdog withheld while a scan is wedged (real
sd_notify datagram socket), the refuse hand-over, the SIGTERM reply, deep JSON, advice per backend.

Fake scanner (see test_service.py); the control socket, the share writer and sd_notify are real.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from fake_service import ctl, make, ready, run, wait_until

from appliance.output import share as S
from appliance.service import health as health_mod
from appliance.service import jobs as jobs_mod
from appliance.service.control import request
from appliance.service.notify import SdNotifier
from appliance.service.state import State, advice_for


def lines(path: Path, *requests: dict[str, Any], timeout_s: float = 10.0) -> list[dict[str, Any]]:
    """Send ``requests`` as JSON lines on ONE connection; the replies, in order (blocking)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    s.connect(str(path))
    try:
        s.sendall(b"".join(json.dumps(r).encode() + b"\n" for r in requests))
        f = s.makefile("rb")
        return [json.loads(f.readline()) for _ in requests]
    finally:
        s.close()


def change_rig(config: Path) -> None:
    """Edit a section whose change rebuilds the rig."""
    doc = yaml.safe_load(config.read_text())
    doc["reconstruction"] = {"min_depth_mm": 123}
    config.write_text(yaml.safe_dump(doc))



pytestmark = pytest.mark.usefixtures("loop_guard")

# --- the reload / trigger race ------------------------------------------------------------------------------


def test_reload_then_trigger_on_one_connection_after_a_rig_change(tmp_path: Path) -> None:
    svc = make(tmp_path, config_poll_s=0)

    async def body() -> None:
        change_rig(svc.config_path)
        reload_reply, trigger_reply = await asyncio.to_thread(
            lines, svc.socket_path, {"cmd": "reload"}, {"cmd": "trigger", "wait": True}
        )
        assert reload_reply == {"ok": True}
        # answered either way: refused while the rig reconnects, or scanned on the new rig
        assert trigger_reply["ok"] or trigger_reply["result"].startswith("refused: not ready"), trigger_reply
        await wait_until(lambda: ready(svc))
        assert svc.cfg.reconstruction.min_depth_mm == 123 and svc.plan.closed >= 1  # the rig was rebuilt
        again = await ctl(svc, cmd="trigger", wait=True)  # the worker is alive
        assert again["ok"] and again["scan"]["points"] == 40

    assert run(svc, body) == 0


def test_a_queued_trigger_waits_for_the_rebuilt_rig(tmp_path: Path) -> None:
    svc = make(tmp_path, scan_s=0.4, config_poll_s=0, busy_policy="queue", queue_max=1)

    async def body() -> None:
        assert (await ctl(svc, cmd="trigger"))["result"] == "started"
        await wait_until(lambda: svc.board.busy)
        waiting = asyncio.create_task(ctl(svc, cmd="trigger", wait=True))
        await wait_until(lambda: svc.board.queue_length == 1)
        change_rig(svc.config_path)
        assert (await ctl(svc, cmd="reload"))["ok"]  # applied once the running scan is done
        reply = await asyncio.wait_for(waiting, 10)
        assert reply["ok"] and reply["result"] == "queued", reply
        assert svc.plan.closed >= 1 and svc.board.counters["scans_done"] == 2
        await wait_until(lambda: ready(svc))

    assert run(svc, body) == 0


def test_any_exception_in_a_scan_is_a_failed_scan_and_the_service_goes_on(tmp_path: Path) -> None:
    svc = make(tmp_path, plan={"fail": RuntimeError("frame index out of range (a bug)")})

    async def body() -> None:
        reply = await asyncio.wait_for(ctl(svc, cmd="trigger", wait=True), 10)
        assert not reply["ok"] and "frame index out of range" in reply["error"]
        await wait_until(lambda: svc.board.state == State.IDLE)
        svc.plan.fail = None
        svc.plan.broken_result = True  # fails after the capture, while the sidecar is made
        reply = await asyncio.wait_for(ctl(svc, cmd="trigger", wait=True), 10)
        assert not reply["ok"] and "cam0" in reply["error"], reply
        await wait_until(lambda: svc.board.state == State.IDLE)
        assert svc.board.counters["scans_failed"] == 2
        assert svc.board.last_error is not None and svc.board.last_error.where == "scan"
        svc.plan.broken_result = False
        assert (await ctl(svc, cmd="trigger", wait=True))["ok"]

    assert run(svc, body) == 0


# --- supervision --------------------------------------------------------------------------------------------


def test_a_critical_task_that_dies_is_a_fault_and_exit_status_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    svc = make(tmp_path)
    states: list[str] = []
    svc.board.subscribe(lambda b: states.append(f"{b.state}: {b.detail}"))

    async def body() -> None:
        def broken(self: S.ShareWriter) -> list[Path]:
            raise RuntimeError("spool index corrupt (a bug)")

        monkeypatch.setattr(S.ShareWriter, "spool_entries", broken)  # the spool loop meets a bug
        await wait_until(lambda: svc.stopping, 5)

    assert run(svc, body) == 1  # systemd's Restart=on-failure starts it again
    faults = [s for s in states if s.startswith("fault") and "scan3d-spool" in s]
    assert faults and "spool index corrupt" in faults[0]
    assert svc.board.last_error is not None and "scan3d-spool" in svc.board.last_error.message
    # the log says what failed, then (formatted off the loop, before the exit) where: the traceback
    said = [(r.levelname, r.getMessage(), r.exc_info) for r in caplog.records if "scan3d-spool" in r.getMessage()]
    assert said[0][0] == "CRITICAL" and "stopping with exit status 1" in said[0][1] and not said[0][2]
    tb = [(msg, exc) for level, msg, exc in said if exc]
    assert len(tb) == 1 and tb[0][0].startswith("traceback of internal task scan3d-spool failed")
    assert tb[0][1] is not None and isinstance(tb[0][1][1], RuntimeError)
    assert "in broken" in caplog.text and "spool index corrupt (a bug)" in caplog.text


def test_a_helper_task_that_dies_is_an_error_not_a_fault(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    svc = make(tmp_path)

    async def body() -> None:
        async def probe() -> None:
            await asyncio.sleep(0)
            raise ValueError("mDNS answer malformed (a bug)")

        svc.spawn(probe(), "probe", critical=False)
        await wait_until(lambda: "traceback of task scan3d-probe" in caplog.text, 5)
        assert ready(svc) and not svc.stopping  # a helper is not worth a restart
        assert (await ctl(svc, cmd="trigger", wait=True))["ok"]

    assert run(svc, body) == 0
    assert svc.board.last_error is not None and "internal task scan3d-probe failed" in svc.board.last_error.message
    said = [r for r in caplog.records if "task scan3d-probe" in r.getMessage()]
    assert [r.levelname for r in said] == ["ERROR", "ERROR"] and said[0].exc_info is None
    assert said[1].exc_info is not None and isinstance(said[1].exc_info[1], ValueError)


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[str, list[tuple[float, dict[str, str]]]]]:
    """A real sd_notify datagram socket; (its path, the messages received with their arrival time)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify")
    sock.bind(path)
    sock.settimeout(0.1)
    got: list[tuple[float, dict[str, str]]] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            try:
                data = sock.recv(4096).decode()
            except TimeoutError:
                continue
            except OSError:
                return
            got.append((time.monotonic(), dict(line.split("=", 1) for line in data.splitlines())))

    reader = threading.Thread(target=receive, name="test-notify-reader")
    reader.start()
    yield path, got
    done.set()
    reader.join()
    sock.close()


def test_watchdog_is_withheld_while_a_scan_is_wedged(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    notify_socket: tuple[str, list[tuple[float, dict[str, str]]]],
) -> None:
    path, got = notify_socket
    monkeypatch.setenv("WATCHDOG_USEC", "200000")  # pinged every 0.1 s while healthy
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    monkeypatch.setattr(jobs_mod, "WRITE_DEADLINE_S", 0.3)
    wedge = threading.Event()
    svc = make(tmp_path, notifier=SdNotifier(path), plan={"wedge": wedge}, scan_timeout_s=0.2)

    def pings(since: float) -> int:
        return sum(1 for t, m in list(got) if "WATCHDOG" in m and t >= since)

    async def body() -> None:
        t0 = time.monotonic()
        await asyncio.sleep(0.5)
        assert pings(t0) >= 3  # healthy: pinged
        assert (await ctl(svc, cmd="trigger"))["ok"]
        await wait_until(lambda: "not healthy" in svc.board.detail, 5)
        assert "scan worker" in svc.board.detail and "deadline" in svc.board.detail
        assert svc.board.state == State.FAULT
        t1 = time.monotonic()
        await asyncio.sleep(0.6)
        assert pings(t1) == 0  # wedged: systemd's watchdog runs out and restarts the service
        status = [m["STATUS"] for _, m in list(got) if "STATUS" in m]
        assert any(s.startswith("fault") and "not healthy" in s for s in status)
        wedge.set()  # the driver call returns: the scan completes, the check passes again
        await wait_until(lambda: svc.board.state == State.IDLE and svc.health.problem == "", 5)
        t2 = time.monotonic()
        await asyncio.sleep(0.4)
        assert pings(t2) >= 2

    try:
        assert run(svc, body) == 0
    finally:
        wedge.set()


def test_watchdog_is_withheld_while_the_control_socket_is_gone(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    notify_socket: tuple[str, list[tuple[float, dict[str, str]]]],
) -> None:
    path, got = notify_socket
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.setattr(health_mod, "CONTROL_DEADLINE_S", 0.5)
    svc = make(tmp_path, notifier=SdNotifier(path))

    async def body() -> None:
        svc.socket_path.unlink()  # e.g. removed by a tmp cleaner: nobody can reach the service any more
        await wait_until(lambda: "control socket" in svc.health.problem, 5)
        t1 = time.monotonic()
        await asyncio.sleep(0.5)
        assert not any("WATCHDOG" in m for t, m in list(got) if t >= t1)

    assert run(svc, body) == 0


# --- smaller defects ----------------------------------------------------------------------------------------


def test_refuse_lets_no_second_trigger_in_during_the_hand_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = S.STATVFS

    def slow_statvfs(p: str) -> Any:  # the disk-space check before a scan takes a while (a slow share)
        time.sleep(0.3)
        return real(p)

    svc = make(tmp_path, scan_s=0.1)

    async def body() -> None:
        monkeypatch.setattr(S, "STATVFS", slow_statvfs)
        assert (await ctl(svc, cmd="trigger"))["result"] == "started"
        await wait_until(lambda: not svc.jobs.queue)  # taken by the worker, not scanning yet
        assert not svc.board.busy
        second = await ctl(svc, cmd="trigger")
        assert not second["ok"] and second["result"].startswith("refused: busy"), second
        await wait_until(lambda: svc.board.counters["scans_done"] == 1 and svc.jobs.active is None, 10)

    assert run(svc, body) == 0
    assert svc.board.counters["scans_done"] == 1 and svc.board.counters["triggers_refused"] == 1


def test_sigterm_past_the_grace_answers_the_waiting_client(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    svc = make(tmp_path, scan_s=3.0, stop_grace_s=0.2)
    replies: list[dict[str, Any]] = []

    async def body() -> None:
        waiting = asyncio.create_task(asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True}))
        await wait_until(lambda: svc.board.state == State.SCANNING)
        os.kill(os.getpid(), signal.SIGTERM)
        replies.append(await asyncio.wait_for(waiting, 10))

    caplog.set_level(logging.DEBUG)
    assert run(svc, body) == 0
    (reply,) = replies
    assert not reply["ok"] and "stop_grace_s = 0.2" in reply["error"] and "no file was written" in reply["error"]
    text = "\n".join(f"{r.getMessage()} {r.exc_text or ''}" for r in caplog.records)
    assert "CancelledError" not in text and "Traceback" not in text


def test_deeply_nested_json_gets_an_answer(tmp_path: Path) -> None:
    svc = make(tmp_path)

    async def body() -> None:
        deep = b"[" * 20000 + b"]" * 20000 + b"\n"

        def send() -> dict[str, Any]:
            s = socket.socket(socket.AF_UNIX)
            s.settimeout(5)
            s.connect(str(svc.socket_path))
            s.sendall(deep)
            reply = json.loads(s.makefile().readline())
            s.close()
            return reply  # type: ignore[no-any-return]

        reply = await asyncio.to_thread(send)
        assert not reply["ok"] and "nested too deeply" in reply["error"]
        assert (await ctl(svc, cmd="status"))["ok"]  # and the socket still serves

    assert run(svc, body) == 0


@pytest.mark.parametrize(
    ("where", "message", "wanted", "not_wanted"),
    [
        (
            "scan",
            "scan S-1 failed: scan failed: camera 'cam0' (sim): no frame within 500 ms of trigger 7 of 28",
            "virtual rig",
            "USB cable",
        ),
        (
            "scan",
            "scan S-1 failed: scan failed: camera 'left' (aravis, 192.168.3.11): no frame within 500 ms of trigger 7",
            "network cable",
            "trigger controller",
        ),
        ("hardware", "trigger serial: /dev/ttyACM0: no such device", "USB cable", "camera"),
        ("hardware", "trigger gpio: /dev/gpiochip0 line 17: busy", "gpio", "USB cable"),
        (
            "disk",
            "scan refused: spool /var/lib/scan3d/spool: [Errno 30] Read-only file system",
            "read-only",
            "free space",
        ),
        ("disk", "scan refused: spool /x: Permission denied", "permission", "free space"),
        ("disk", "scan refused: the share is full (12 MB free, 80 MB needed)", "free space", "read-only"),
    ],
)
def test_advice_fits_the_backend_and_the_cause(where: str, message: str, wanted: str, not_wanted: str) -> None:
    advice = advice_for(where, message).lower()
    assert wanted.lower() in advice and not_wanted.lower() not in advice, advice


# --- configuration files that are not a mapping --------------------------------------------------------------


def test_the_watcher_survives_binary_empty_and_non_utf8_edits(tmp_path: Path) -> None:
    svc = make(tmp_path)
    path = svc.config_path
    good = yaml.safe_load(path.read_text())

    async def body() -> None:
        for data, wanted in ((b"\xff\xfe\x00b\x00", "binary data"), (b"", "(empty)"), (b"serial: caf\xe9\n", "UTF-8")):
            before = svc.board.counters["reloads_rejected"]
            path.write_bytes(data)
            await wait_until(lambda b=before: svc.board.counters["reloads_rejected"] > b)  # type: ignore[misc]
            assert "not a YAML mapping" in svc.board.config_error and wanted in svc.board.config_error
            assert "\n" not in svc.board.config_error
            assert svc.watcher is not None and svc.cfg.serial == "TEST-1"  # the last good one keeps running
        path.write_text(yaml.safe_dump(dict(good, serial="TEST-3")))  # later edits are still picked up
        await wait_until(lambda: svc.cfg.serial == "TEST-3")
        assert svc.board.config_error == ""
        assert (await ctl(svc, cmd="trigger", wait=True))["scan"]["scan_id"].endswith("TEST-3-000001")

    assert run(svc, body) == 0


@pytest.mark.parametrize("data", [b"", b"\x89PNG\r\n\x1a\n\x00\x00"], ids=["empty", "binary"])
def test_run_refuses_an_empty_or_binary_config_in_one_line(tmp_path: Path, data: bytes) -> None:
    import subprocess
    import sys

    path = tmp_path / "appliance.yaml"
    path.write_bytes(data)
    r = subprocess.run(
        [sys.executable, "-m", "appliance", "run", "--config", str(path), "--control-socket", str(tmp_path / "s")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    out = (r.stdout + r.stderr).strip()
    assert r.returncode != 0 and "Traceback" not in out and "not a YAML mapping" in out, out
    assert out.count("\n") == 0, out


def test_watchdog_is_withheld_while_the_writer_thread_hangs(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    notify_socket: tuple[str, list[tuple[float, dict[str, str]]]],
) -> None:
    path, got = notify_socket
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.setattr(health_mod, "WRITER_DEADLINE_S", 0.5)
    hang = threading.Event()
    svc = make(tmp_path, notifier=SdNotifier(path))

    async def body() -> None:
        real = S.ShareWriter.status

        def hung_status(self: S.ShareWriter) -> dict[str, Any]:  # a share that stops answering a stat
            hang.wait()
            return real(self)

        monkeypatch.setattr(S.ShareWriter, "status", hung_status)
        svc.output.submit(lambda: svc.writer.status())  # the writer thread is stuck in it
        await wait_until(lambda: "writer thread" in svc.health.problem, 5)
        t1 = time.monotonic()
        await asyncio.sleep(0.5)
        assert not any("WATCHDOG" in m for t, m in list(got) if t >= t1)
        hang.set()
        await wait_until(lambda: svc.health.problem == "", 5)

    try:
        assert run(svc, body) == 0
    finally:
        hang.set()
