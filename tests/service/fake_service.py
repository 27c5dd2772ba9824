"""The service with a fake scanner and a fake button (no rig, no numba), and the helpers that run it: for
``test_service.py`` and ``test_service_faults.py``."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import yaml

from appliance.errors import CameraError
from appliance.hardware.base import TriggerEvent
from appliance.patterns.sequence import gray_code_sequence
from appliance.reconstruct.pipeline import Reconstruction
from appliance.reconstruct.types import DecodedMaps, PointCloud
from appliance.replay import ScanResult
from appliance.service import daemon as D
from appliance.service.control import request
from appliance.service.notify import SdNotifier
from appliance.service.state import Phase, State

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
    """The service with :meth:`make_scanner` handed in as its rig factory (the test seam)."""

    def __init__(self, *a: Any, plan: SimpleNamespace, **kw: Any) -> None:
        self.plan = plan
        self.trigger = FakeTrigger()
        super().__init__(*a, make_scanner=self.make_scanner, **kw)

    def make_scanner(self, cfg: Any, on_phase: Any) -> tuple[Any, Any]:
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
