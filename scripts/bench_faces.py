#!/usr/bin/env python3
"""Benchmark (not a test): button-to-file latency with the HTTP, MQTT and OPC UA faces all on, against all off.

Runs the service in-process on the reference configuration (config/appliance.yaml, the default virtual rig),
its paths in a temporary folder and mDNS off. "On" means: the HTTP face with a client on /api/events that
fetches /api/scans, the preview and the downsampled cloud after every scan (what the status page does), the
MQTT face on a local Mosquitto broker with a subscriber on <prefix>/#, and the OPC UA face with a client
subscribed to LastScanId. Presses come one at a time with a gap between them (a line does not press back to
back); rounds alternate off / on so that drift on a shared machine hits both. Everything on 127.0.0.1.

    .venv/bin/python scripts/bench_faces.py [--rounds 3] [--scans 8] [--gap-s 0.6]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from appliance.config import load_config  # noqa: E402
from appliance.hardware.base import TriggerEvent  # noqa: E402
from appliance.service.daemon import Service  # noqa: E402
from appliance.service.notify import SdNotifier  # noqa: E402

TOKEN = "bench-token"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def mosquitto(tmp: Path) -> Any:
    exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    port = free_port()
    conf = tmp / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
    proc = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(200):
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
                break
            time.sleep(0.02)
        yield port
    finally:
        proc.kill()
        proc.wait()


def configured(tmp: Path, faces: bool, broker_port: int) -> Any:
    cfg = load_config(REPO / "config" / "appliance.yaml")
    (tmp / "share").mkdir(exist_ok=True)
    (tmp / "token").write_text(TOKEN)
    (tmp / "opcua-pw").write_text("pw")
    output = cfg.output.model_copy(update={"directory": tmp / "share", "spool_directory": tmp / "spool",
                                           "min_free_mb": 0})
    upd: dict[str, Any] = {"control_socket": tmp / "ctl.sock", "state_directory": tmp / "state",
                           "config_poll_s": 0.0, "mdns": cfg.service.mdns.model_copy(update={"enabled": False})}
    if faces:
        s = cfg.service
        upd["http"] = s.http.model_copy(update={"listen": f"127.0.0.1:{free_port()}", "token_file": tmp / "token",
                                                "rate_per_s": 200.0})
        upd["mqtt"] = s.mqtt.model_copy(update={"enabled": True, "host": "127.0.0.1", "port": broker_port})
        upd["opcua"] = s.opcua.model_copy(update={"enabled": True, "username": "line",
                                                  "password_file": tmp / "opcua-pw",
                                                  "endpoint": f"opc.tcp://127.0.0.1:{free_port()}/scan3d"})
    return cfg.model_copy(update={"output": output, "service": cfg.service.model_copy(update=upd)})


@contextlib.asynccontextmanager
async def clients(svc: Service, broker_port: int) -> AsyncIterator[None]:
    """The status page's requests, an MQTT subscriber and an OPC UA subscription, running beside the scans."""
    import aiohttp
    import aiomqtt
    from asyncua import Client

    http = svc.cfg.service.http
    assert http.listen is not None
    base = f"http://{http.listen}"
    prefix = svc.cfg.service.mqtt.topic_prefix.replace("{serial}", svc.cfg.serial)

    async def page() -> None:
        async with aiohttp.ClientSession() as s, s.get(f"{base}/api/events") as stream:
            async for line in stream.content:
                if line.startswith(b"event: scan"):
                    async with s.get(f"{base}/api/scans?limit=20") as r:
                        sid = (await r.json())["scans"][0]["scan_id"]
                    for name in ("preview.png", "cloud.bin"):
                        async with s.get(f"{base}/api/scans/{sid}/{name}") as r:
                            await r.read()

    async def mqtt() -> None:
        async with aiomqtt.Client("127.0.0.1", broker_port, identifier="bench-sub") as c:
            await c.subscribe(f"{prefix}/#")
            async for _ in c.messages:
                pass

    async def opcua() -> None:
        url = svc.cfg.service.opcua.endpoint
        async with Client(url, timeout=30) as c:
            idx = await c.get_namespace_index("urn:scan3d:appliance")
            node = await c.nodes.objects.get_child([f"{idx}:Scanner", f"{idx}:LastScanId"])

            class Handler:
                def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                    pass

            sub = await c.create_subscription(100, Handler())
            await sub.subscribe_data_change(node)
            await asyncio.Event().wait()

    tasks = [asyncio.create_task(f()) for f in (page, mqtt, opcua)]
    await asyncio.sleep(1.5)  # connected and subscribed
    try:
        yield
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def one_round(faces: bool, scans: int, gap_s: float, broker_port: int) -> tuple[list[float], float]:
    with tempfile.TemporaryDirectory(prefix="scan3d-bench-faces-") as name:
        tmp = Path(name)
        svc = Service(REPO / "config" / "appliance.yaml", configured(tmp, faces, broker_port),
                      notifier=SdNotifier(None))
        task = asyncio.create_task(svc.run())
        try:
            while not (svc.board.state == "idle" and str(svc.board.phase) == "ready" and svc.faces.started.is_set()):
                if task.done():
                    raise RuntimeError("the service stopped before it was ready")
                await asyncio.sleep(0.02)
            if faces:
                assert set(svc.faces._faces) == {"http", "mqtt", "opcua"}, svc.faces.disabled
            latencies: list[float] = []
            async with contextlib.AsyncExitStack() as stack:
                if faces:
                    await stack.enter_async_context(clients(svc, broker_port))
                for i in range(scans + 1):  # the first scan of a round is a warm-up, not counted
                    await asyncio.sleep(gap_s)
                    if i == 1:
                        cpu0 = time.process_time()
                    _, job = svc.request_scan(TriggerEvent("bench", time.monotonic_ns()))
                    assert job is not None
                    rec = await job.done
                    if not rec.ok:
                        raise RuntimeError(f"scan failed: {rec.error}")
                    if i:
                        latencies.append(rec.timings_ms["trigger_to_file_ms"])
                cpu_per_scan = (time.process_time() - cpu0) / scans
        finally:
            svc.request_stop()
            await task
    return latencies, cpu_per_scan


async def main_async(rounds: int, scans: int, gap_s: float) -> dict[str, Any]:
    off: list[float] = []
    on: list[float] = []
    cpu: dict[bool, list[float]] = {False: [], True: []}
    with tempfile.TemporaryDirectory(prefix="scan3d-bench-broker-") as bt, mosquitto(Path(bt)) as port:
        for r in range(rounds):
            for faces in (False, True) if r % 2 == 0 else (True, False):
                got, cpu_s = await one_round(faces, scans, gap_s, port)
                (on if faces else off).extend(got)
                cpu[faces].append(cpu_s)
                print(f"round {r + 1} faces {'on ' if faces else 'off'}: median {statistics.median(got):.0f} ms",
                      file=sys.stderr, flush=True)
    m_off, m_on = statistics.median(off), statistics.median(on)
    return {"scans_each": len(off), "gap_s": gap_s,
            "faces_off_ms": {"median": round(m_off, 1), "p90": round(sorted(off)[int(0.9 * (len(off) - 1))], 1)},
            "faces_on_ms": {"median": round(m_on, 1), "p90": round(sorted(on)[int(0.9 * (len(on) - 1))], 1)},
            "difference_pct": round(100 * (m_on - m_off) / m_off, 1),
            "min_ms": {"off": round(min(off), 1), "on": round(min(on), 1)},
            "process_cpu_per_scan_ms": {"off": round(1e3 * statistics.median(cpu[False]), 1),
                                        "on": round(1e3 * statistics.median(cpu[True]), 1)}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--scans", type=int, default=8, help="counted scans per round and mode")
    ap.add_argument("--gap-s", type=float, default=0.6, help="pause between presses (s)")
    a = ap.parse_args()
    print(json.dumps(asyncio.run(main_async(a.rounds, a.scans, a.gap_s)), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
