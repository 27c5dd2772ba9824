"""The service's logic with a fake scanner: triggers, busy policy, faults and retries, reload, the control
socket, sd_notify messages, the disk guard and SIGTERM. (End-to-end runs on the virtual rig:
test_service_e2e.py.)"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import os
import re
import signal
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from appliance.errors import ApplianceError, CameraError
from appliance.hardware.base import TriggerEvent
from appliance.output import share as S
from appliance.output.atomic import TMP_PREFIX
from appliance.patterns.sequence import gray_code_sequence
from appliance.reconstruct.pipeline import Reconstruction
from appliance.reconstruct.types import DecodedMaps, PointCloud
from appliance.replay import ScanResult
from appliance.service import daemon as D
from appliance.service import publish as publish_mod
from appliance.service import rig as rig_mod
from appliance.service import writing as writing_mod
from appliance.service.client import format_status, status_command
from appliance.service.control import request
from appliance.service.notify import SdNotifier
from appliance.service.state import Phase, State

pytestmark = pytest.mark.usefixtures("loop_guard")

# --- fakes -----------------------------------------------------------------------------------------------


class FakeTrigger:
    """A :class:`~appliance.hardware.base.TriggerSource` with lamps, driven by the test."""

    name = "fake-button"
    emits_sequence_pulses = False
    has_lamps = True

    def __init__(self) -> None:
        self.events: asyncio.Queue[TriggerEvent] = asyncio.Queue()
        self.leds: list[tuple[bool, bool, bool]] = []

    async def open(self) -> None:
        return None

    def press(self, detail: str = "") -> None:
        self.events.put_nowait(TriggerEvent(self.name, time.monotonic_ns(), detail))

    async def next_event(self) -> TriggerEvent:
        return await self.events.get()

    async def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        self.leds.append((ready, busy, fault))

    def status(self) -> str:
        return "open"

    async def close(self) -> None:
        return None


class FakeScanner:
    """Same async API as appliance.scan.Scanner; a scan sleeps ``scan_s`` and returns a small cloud."""

    def __init__(self, plan: SimpleNamespace) -> None:
        self.plan = plan
        self.sequence = gray_code_sequence(64, 32, "x")
        self.calibration = SimpleNamespace(
            devices={"cam0": SimpleNamespace(width=32, height=24)}, hash=lambda: "fakecal"
        )
        self.scans = 0
        self.camera_info: dict[str, Any] = {}

    async def open(self) -> None:
        if self.plan.open_failures > 0:
            self.plan.open_failures -= 1
            raise CameraError("camera 'cam0' (fake): not found on the bus; check its cable")

    async def warm_up(self) -> None:
        self.plan.warmed += 1

    async def scan(self) -> Any:
        await asyncio.sleep(self.plan.scan_s)
        fail = getattr(self.plan, "fail", None)
        if fail is not None:
            raise fail
        wedge = getattr(self.plan, "wedge", None)
        if wedge is not None:  # a driver call that hangs in its thread and ignores cancellation
            fut = asyncio.get_running_loop().run_in_executor(None, wedge.wait)
            while not fut.done():
                try:
                    await asyncio.shield(fut)
                except asyncio.CancelledError:
                    continue
        self.scans += 1
        rng = np.random.default_rng(self.scans)
        n = 40
        cloud = PointCloud(
            rng.uniform(0, 100, (n, 3)).astype(np.float32),
            rng.integers(0, 24, n).astype(np.int32),
            rng.integers(0, 32, n).astype(np.int32),
            np.zeros(n, np.uint8),
            np.full(n, 128, np.uint8),
            np.ones(n, np.float32),
        )
        broken = getattr(self.plan, "broken_result", False)  # e.g. a backend that lost a camera's maps
        nan = np.full((24, 32), np.nan, np.float32)
        maps = {} if broken else {"cam0": DecodedMaps(nan, nan, np.ones((24, 32), bool), np.ones((24, 32), np.float32))}
        timings = {"scan_ms": 1e3 * self.plan.scan_s, "capture_ms": 1.0, "reconstruct_ms": 1.0}
        return ScanResult(Reconstruction(cloud, {}), maps, {}, timings, {"cam0": (24, 32)})

    async def close(self) -> None:
        self.plan.closed += 1


class RecordingNotifier(SdNotifier):
    def __init__(self) -> None:
        super().__init__(None)
        self.sent: list[dict[str, str]] = []

    def send(self, **fields: str | int) -> bool:
        self.sent.append({k: str(v) for k, v in fields.items()})
        return True

    def keys(self, key: str) -> list[str]:
        return [m[key] for m in self.sent if key in m]


class FakeService(D.Service):
    def __init__(self, *a: Any, plan: SimpleNamespace, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.plan = plan
        self.trigger = FakeTrigger()

    def _make_scanner(self, cfg: Any) -> tuple[Any, Any]:
        rig = SimpleNamespace(cameras={}, projector=None, trigger=self.trigger, virtual=None)
        return rig, FakeScanner(self.plan)


# --- helpers ---------------------------------------------------------------------------------------------


def write_config(tmp: Path, **service: Any) -> Path:
    doc = {
        "serial": "TEST-1",
        "output": {"directory": str(tmp / "share"), "spool_directory": str(tmp / "spool"), "min_free_mb": 0},
        "service": {
            "control_socket": str(tmp / "ctl.sock"),
            "state_directory": str(tmp / "state"),
            "config_poll_s": 0.05,
            "mdns": {"enabled": False},
            **service,
        },
    }
    (tmp / "share").mkdir(exist_ok=True)
    path = tmp / "appliance.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def make(
    tmp: Path,
    scan_s: float = 0.02,
    open_failures: int = 0,
    notifier: SdNotifier | None = None,
    plan: dict[str, Any] | None = None,
    **service: Any,
) -> FakeService:
    p = SimpleNamespace(scan_s=scan_s, open_failures=open_failures, warmed=0, closed=0, **(plan or {}))
    return FakeService(write_config(tmp, **service), plan=p, notifier=notifier or RecordingNotifier())


async def wait_until(pred: Callable[[], bool], timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > end:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.01)


def ready(svc: D.Service) -> bool:
    return svc.board.phase == Phase.READY and svc.board.state == State.IDLE


async def ctl(svc: D.Service, **req: Any) -> dict[str, Any]:
    return await asyncio.to_thread(request, svc.socket_path, req)


def run(svc: D.Service, body: Callable[[], Any]) -> int:
    """Run the service, wait until ready, run ``body()`` (a coroutine function), stop; the exit status."""

    async def main() -> int:
        task = asyncio.create_task(svc.run())
        try:
            await wait_until(lambda: ready(svc) or task.done())
            await body()
        finally:
            svc.request_stop()
        return await asyncio.wait_for(task, 20)

    return asyncio.run(main())


def share_files(tmp: Path) -> list[str]:
    return sorted(p.name for p in (tmp / "share").rglob("*") if p.is_file())


@pytest.fixture(autouse=True)
def fast(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rig_mod, "RETRY_FIRST_S", 0.05)
    monkeypatch.setattr(writing_mod, "SPOOL_RETRY_S", 0.05)
    monkeypatch.setattr(publish_mod, "REFUSED_BLINK_S", 0.05)


# --- tests -----------------------------------------------------------------------------------------------


def test_button_press_writes_files_and_publishes(tmp_path: Path) -> None:
    svc = make(tmp_path)

    async def body() -> None:
        assert svc.plan.warmed == 1
        svc.trigger.press("test")
        await wait_until(lambda: svc.board.counters["scans_done"] == 1 and svc.board.state == State.IDLE)
        st = (await ctl(svc, cmd="status"))["status"]
        assert st["state"] == "idle" and st["counters"]["scans_done"] == 1
        rec = st["last_scans"][-1]
        assert rec["ok"] and rec["location"] == "share" and rec["trigger"] == "fake-button"
        assert rec["timings_ms"]["trigger_to_file_ms"] >= rec["timings_ms"]["write_ms"] > 0
        day = f"{dt.datetime.now(dt.UTC):%Y-%m-%d}"
        sidecar = json.loads((tmp_path / "share" / day / f"{rec['scan_id']}.json").read_text())
        assert (
            sidecar["appliance_serial"] == "TEST-1" and sidecar["extra"]["trigger"]["source"] == "fake-button"
        )
        assert svc.txt_record()["last"] == rec["scan_id"] and svc.txt_record()["scans"] == "1"

    assert run(svc, body) == 0
    assert len(share_files(tmp_path)) == 3  # cloud, preview, sidecar
    n = svc.notifier
    assert isinstance(n, RecordingNotifier)
    assert sum("READY" in m for m in n.sent) == 1
    statuses = n.keys("STATUS")
    assert any(s.startswith("scanning") for s in statuses) and any(s.startswith("writing") for s in statuses)
    assert "STOPPING" in n.sent[-1]
    leds = svc.trigger.leds
    assert (False, True, False) in leds and leds[leds.index((False, True, False)) + 1] == (True, False, False)
    # the scan counter survives a restart (unique scan ids)
    state = json.loads((tmp_path / "state" / D.STATE_FILE).read_text())
    assert state["counter"] == 1 and state["last_scans"][0]["ok"]


def test_trigger_while_busy_is_refused_counted_and_blinked(tmp_path: Path) -> None:
    svc = make(tmp_path, scan_s=0.4)

    async def body() -> None:
        first = await ctl(svc, cmd="trigger")
        await wait_until(lambda: svc.board.busy)
        second = await ctl(svc, cmd="trigger")
        assert first == {"ok": True, "result": "started"}
        assert not second["ok"] and second["result"].startswith("refused: busy")
        await wait_until(lambda: svc.board.counters["scans_done"] == 1 and not svc.board.busy)
        assert svc.board.counters["triggers_refused"] == 1 and svc.board.counters["triggers"] == 2

    assert run(svc, body) == 0
    assert (False, True, True) in svc.trigger.leds  # busy with the fault lamp blinking


def test_trigger_while_busy_is_queued(tmp_path: Path) -> None:
    svc = make(tmp_path, scan_s=0.3, busy_policy="queue", queue_max=1)

    async def body() -> None:
        results = []
        for _ in range(3):
            results.append((await ctl(svc, cmd="trigger"))["result"])
            await wait_until(lambda: svc.board.busy)
        assert results[:2] == ["started", "queued"] and results[2].startswith("refused")
        await wait_until(lambda: svc.board.counters["scans_done"] == 2 and not svc.board.busy)
        assert svc.board.counters["triggers_queued"] == 1 and svc.board.counters["triggers_refused"] == 1

    assert run(svc, body) == 0
    assert len(share_files(tmp_path)) == 6


def test_trigger_wait_returns_the_scan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    svc = make(tmp_path)

    async def body() -> None:
        reply = await ctl(svc, cmd="trigger", wait=True)
        assert reply["ok"] and reply["scan"]["points"] == 40
        assert await asyncio.to_thread(lambda: all(Path(f).is_file() for f in reply["scan"]["files"]))
        assert await asyncio.to_thread(status_command, None, svc.socket_path) == 0

    assert run(svc, body) == 0
    screen = capsys.readouterr().out
    assert "IDLE" in screen and "hardware" in screen and "last scans" in screen and "40 pts" in screen
    rss = re.search(r"RSS (\d+) MB", screen)  # the service's resident memory, from /proc
    assert rss is not None and 20 < int(rss.group(1)) < 4000, screen


def test_absent_hardware_is_retried_and_reported(tmp_path: Path) -> None:
    svc = make(tmp_path, open_failures=3)
    seen: list[str] = []
    svc.board.subscribe(lambda b: seen.append(f"{b.state}/{b.phase}"))

    async def body() -> None:
        assert svc.plan.open_failures == 0
        err = (await ctl(svc, cmd="last_error"))["last_error"]
        assert err["where"] == "hardware" and "check its cable" in err["message"]
        assert "camera" in err["advice"]

    assert run(svc, body) == 0
    assert "fault/connect hardware" in seen and seen.index("fault/connect hardware") < seen.index(
        "idle/ready"
    )
    n = svc.notifier
    assert isinstance(n, RecordingNotifier)
    assert sum("READY" in m for m in n.sent) == 1  # up (in fault) before the hardware came
    assert svc.plan.closed >= 3  # each failed attempt released what it had opened


def test_fault_screen_says_what_to_do(tmp_path: Path) -> None:
    svc = make(tmp_path)
    svc.board.set_state(State.FAULT, "hardware: camera gone", Phase.CONNECT)
    svc.board.error("hardware", "camera 'cam0' (aravis, 192.168.3.11): no answer")
    screen = format_status(svc.board.snapshot())
    assert "FAULT [connect hardware]" in screen
    assert "what to do: check the camera's power and cable" in screen


def test_broken_config_is_rejected_and_a_fixed_one_applied(tmp_path: Path) -> None:
    svc = make(tmp_path)
    path = svc.config_path
    good = yaml.safe_load(path.read_text())

    async def body() -> None:
        broken = dict(good, output={**good["output"], "min_free_mb": -5})
        path.write_text(yaml.safe_dump(broken))
        await wait_until(lambda: svc.board.config_error != "")
        assert "min_free_mb" in svc.board.config_error and "appliance.yaml:" in svc.board.config_error
        assert svc.board.last_error is not None and svc.board.last_error.where == "config"
        reply = await ctl(svc, cmd="trigger", wait=True)  # still scanning with the old configuration
        assert reply["ok"]
        fixed = dict(good, serial="TEST-2")
        path.write_text(yaml.safe_dump(fixed))
        assert (await ctl(svc, cmd="reload"))["ok"]  # the control socket's reload (like SIGHUP)
        assert svc.board.config_error == "" and svc.cfg.serial == "TEST-2"
        reply = await ctl(svc, cmd="trigger", wait=True)
        assert "TEST-2" in reply["scan"]["scan_id"]
        assert svc.board.counters["reloads_rejected"] >= 1 and svc.board.counters["reloads"] >= 1

    assert run(svc, body) == 0


def test_sighup_reloads(tmp_path: Path) -> None:
    svc = make(tmp_path, config_poll_s=0)  # no polling: only the signal

    async def body() -> None:
        doc = yaml.safe_load(svc.config_path.read_text())
        svc.config_path.write_text(yaml.safe_dump(dict(doc, serial="HUP-1")))
        os.kill(os.getpid(), signal.SIGHUP)
        await wait_until(lambda: svc.cfg.serial == "HUP-1")

    assert run(svc, body) == 0


def test_disk_guard_refuses_a_scan_that_cannot_be_stored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(S, "STATVFS", lambda p: SimpleNamespace(f_bavail=10, f_frsize=4096))
    svc = make(tmp_path)

    async def body() -> None:
        reply = await ctl(svc, cmd="trigger", wait=True)
        assert not reply["ok"] and "full" in reply["error"]
        assert svc.board.last_error is not None and svc.board.last_error.where == "disk"

    assert run(svc, body) == 0
    assert share_files(tmp_path) == [] and svc.plan.scan_s and svc.board.counters["scans_done"] == 0


@pytest.mark.parametrize("grace_s", [20.0, 0.0])
def test_sigterm_during_a_scan_exits_0_without_partial_files(tmp_path: Path, grace_s: float) -> None:
    svc = make(tmp_path, scan_s=0.5, stop_grace_s=grace_s)

    async def body() -> None:
        await ctl(svc, cmd="trigger")
        await wait_until(lambda: svc.board.state == State.SCANNING)
        os.kill(os.getpid(), signal.SIGTERM)

    assert run(svc, body) == 0
    files = share_files(tmp_path)
    assert not any(f.startswith(TMP_PREFIX) for f in files)
    assert len(files) == (3 if grace_s else 0)  # finished completely, or aborted before any file
    assert not svc.socket_path.exists()


def test_control_socket_rejects_bad_requests(tmp_path: Path) -> None:
    svc = make(tmp_path)

    async def body() -> None:
        def raw(data: bytes) -> dict[str, Any]:
            import socket

            s = socket.socket(socket.AF_UNIX)
            s.connect(str(svc.socket_path))
            s.sendall(data)
            reply = json.loads(s.makefile().readline())
            s.close()
            return reply  # type: ignore[no-any-return]

        assert "not a JSON line" in (await asyncio.to_thread(raw, b"{oops\n"))["error"]
        assert "cmd" in (await asyncio.to_thread(raw, b"[1, 2]\n"))["error"]
        assert "unknown command" in (await ctl(svc, cmd="format-disk"))["error"]
        assert (await ctl(svc, cmd="last_error")) == {"ok": True, "last_error": None}

    assert run(svc, body) == 0


def test_control_socket_path_conflicts(tmp_path: Path) -> None:
    (tmp_path / "ctl.sock").write_text("not a socket")
    svc = make(tmp_path)
    with pytest.raises(ApplianceError, match="not a socket"):
        asyncio.run(svc.run())
