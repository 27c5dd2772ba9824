"""The service end to end, from outside: its config file on disk, the service in this process or in its own,
scans asked for over the control socket, files checked on the share (for ``tests/service/test_service_e2e.py``
and the service tests that build on it)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from appliance.output.atomic import TMP_PREFIX
from appliance.output.ply import read_ply_vertices
from appliance.service import daemon as D
from appliance.service.control import request
from appliance.service.state import Phase, State

REPO = Path(__file__).resolve().parents[2]

SMALL_RIG = {
    "projector": {
        "width": 320,
        "height": 200,
        "focal_px": 400,
        "principal_px": [160, 190],
        "position_mm": [175, 0, 0],
        "look_at_mm": [0, 40, 580],
    },
    "cameras": {
        "cam0": {
            "width": 320,
            "height": 256,
            "focal_px": 450,
            "position_mm": [0, 0, 0],
            "look_at_mm": [0, 0, 580],
        }
    },
}


def write_config(
    tmp: Path,
    *,
    mdns: str | None = None,
    trigger: dict[str, Any] | None = None,
    camera: dict[str, Any] | None = None,
    service: dict[str, Any] | None = None,
    **top: Any,
) -> Path:
    """A small-virtual-rig configuration with everything under ``tmp``; returns its path."""
    doc: dict[str, Any] = {
        "serial": "E2E-1",
        "cameras": {"cam0": {"type": "sim", **(camera or {})}},
        "trigger": trigger or {"type": "sim"},
        "virtual_rig": SMALL_RIG,
        "reconstruction": {"min_depth_mm": 300, "max_depth_mm": 900},
        "output": {"directory": str(tmp / "share"), "spool_directory": str(tmp / "spool"), "min_free_mb": 0},
        "service": {
            "control_socket": str(tmp / "ctl.sock"),
            "state_directory": str(tmp / "state"),
            "config_poll_s": 0.1,
            "mdns": {
                "enabled": mdns is not None,
                "interfaces": ["127.0.0.1"],
                **({"instance_name": mdns} if mdns else {}),
            },
            **(service or {}),
        },
        **top,
    }
    (tmp / "share").mkdir(exist_ok=True)
    path = tmp / "appliance.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def day_of(scan_id: str) -> str:
    """The share's day folder of ``scan_id``: the UTC day its scan started, as the id begins with it.

    Never the clock when the test looks: a run across midnight puts scans in two folders.
    """
    return f"{scan_id[:4]}-{scan_id[4:6]}-{scan_id[6:8]}"


def scan_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file()) if root.exists() else []


def no_partial_files(*roots: Path) -> None:
    leftovers = [p for r in roots for p in scan_files(r) if p.name.startswith(TMP_PREFIX)]
    assert leftovers == [], f"partial files left: {leftovers}"


def complete_scan(folder: Path, scan_id: str) -> None:
    """Cloud, preview and sidecar of ``scan_id`` are in ``folder`` and whole."""
    side = json.loads((folder / f"{scan_id}.json").read_text())
    v = read_ply_vertices(folder / side["files"]["cloud"])
    assert len(v) == side["counts"]["points"] > 1000
    assert (folder / side["files"]["preview"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def wait_for(pred: Callable[[], Any], timeout_s: float = 60.0, what: str = "condition") -> Any:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} not met within {timeout_s} s")


async def await_for(pred: Callable[[], Any], timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > end:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.02)


class ServiceProcess:
    """``scan3d run`` as a subprocess, with its log."""

    def __init__(self, config: Path, tmp: Path, env: dict[str, str] | None = None, *args: str) -> None:
        self.sock = tmp / "sock"
        self.log = tmp / "service.log"
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "appliance",
                "run",
                "--config",
                str(config),
                "--control-socket",
                str(self.sock),
                *args,
            ],
            cwd=REPO,
            stdout=self.log.open("w"),
            stderr=subprocess.STDOUT,
            env={**os.environ, **(env or {})},
        )

    def status(self) -> dict[str, Any]:
        try:
            return request(self.sock, {"cmd": "status"}, 5)["status"]  # type: ignore[no-any-return]
        except Exception:
            return {}

    def wait_ready(self, timeout_s: float = 120.0) -> dict[str, Any]:
        def ok() -> dict[str, Any] | None:
            assert self.proc.poll() is None, f"service exited: {self.log.read_text()}"
            st = self.status()
            return st if st.get("state") == "idle" else None

        return wait_for(ok, timeout_s, "service ready")  # type: ignore[no-any-return]

    def stop(self, timeout_s: float = 60.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"service did not stop on SIGTERM: {self.log.read_text()}") from None


def run_in_process(config: Path, body: Callable[[D.Service], Any], **kw: Any) -> tuple[int, D.Service]:
    svc = D.Service(config, **kw)

    async def main() -> int:
        task = asyncio.create_task(svc.run())
        try:
            await await_for(
                lambda: (svc.board.phase == Phase.READY and svc.board.state == State.IDLE) or task.done(), 120
            )
            assert not task.done(), "service ended early"
            await body(svc)
        finally:
            svc.request_stop()
        return await asyncio.wait_for(task, 60)

    return asyncio.run(main()), svc


async def scan_once(svc: D.Service) -> dict[str, Any]:
    reply = await asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True}, 120)
    assert reply["ok"], reply
    return reply["scan"]  # type: ignore[no-any-return]
