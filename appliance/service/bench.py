"""Service benchmark on the virtual rig: button-to-file latency and scans per minute.

Runs the real service in-process (``Service``) with the given configuration, its output, spool, state and
control socket redirected into a temporary folder and mDNS off; presses the simulated button the way the rig
does (a :class:`~appliance.hardware.base.TriggerEvent` with the press time) and measures until the sidecar of
the scan is renamed into the share.
"""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from appliance.config import load_config
from appliance.hardware.base import TriggerEvent
from appliance.service.daemon import Service
from appliance.service.notify import SdNotifier
from appliance.service.state import Phase, State


async def bench_service(config_path: Path, scans: int) -> dict[str, Any]:
    """Measure the service on the configured (virtual) rig.

    Parameters
    ----------
    config_path : Path
        Configuration file; its output/service paths are replaced by a temporary folder.
    scans : int
        Scans for each measurement (latency: one at a time; throughput: back to back).

    Returns
    -------
    dict
        ``start_to_ready_s``; ``button_to_file_ms`` (min, median, p95, max over ``scans`` single presses);
        ``stage_median_ms`` (capture, reconstruct, write, scan); ``scans_per_minute`` (presses queued back
        to back); ``points_median``; ``camera`` (W x H) and ``frames``.
    """
    cfg = load_config(config_path)
    with tempfile.TemporaryDirectory(prefix="scan3d-bench-") as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "share").mkdir()
        output = cfg.output.model_copy(update={"directory": tmp / "share", "spool_directory": tmp / "spool"})
        service = cfg.service.model_copy(update={
            "control_socket": tmp / "ctl.sock", "state_directory": tmp / "state", "config_poll_s": 0.0,
            "busy_policy": "queue", "queue_max": 2,
            "mdns": cfg.service.mdns.model_copy(update={"enabled": False}),
        })
        cfg = cfg.model_copy(update={"output": output, "service": service})
        svc = Service(config_path, cfg, notifier=SdNotifier(None))
        t0 = time.perf_counter()
        task = asyncio.create_task(svc.run())
        try:
            while not (svc.board.phase == Phase.READY and svc.board.state == State.IDLE):
                if task.done():
                    task.result()
                    raise RuntimeError("the service stopped before it was ready")
                await asyncio.sleep(0.01)
            ready_s = time.perf_counter() - t0
            latencies, records = [], []
            for _ in range(scans):
                _, job = svc.request_scan(TriggerEvent("bench", time.monotonic_ns()))
                assert job is not None
                rec = await job.done
                if not rec.ok:
                    raise RuntimeError(f"scan failed: {rec.error}")
                latencies.append(rec.timings_ms["trigger_to_file_ms"])
                records.append(rec)
            t1 = time.perf_counter()
            frames = len(svc.scanner.sequence) if svc.scanner is not None else 0
            pending = None
            done = []
            for _ in range(scans):  # back to back: the next press is queued while a scan runs
                _, job = svc.request_scan(TriggerEvent("bench", time.monotonic_ns()))
                assert job is not None
                if pending is not None:
                    done.append(await pending)
                pending = job.done
            if pending is not None:
                done.append(await pending)
            minutes = (time.perf_counter() - t1) / 60
            if not all(r.ok for r in done):
                raise RuntimeError("a back-to-back scan failed")
        finally:
            svc.request_stop()
            await task
    lat = sorted(latencies)

    def med(key: str) -> float:
        return round(statistics.median(r.timings_ms.get(key, 0.0) for r in records), 1)

    cam = next(iter(cfg.virtual_rig.cameras.values()))
    return {
        "start_to_ready_s": round(ready_s, 2),
        "button_to_file_ms": {"min": round(lat[0], 1), "median": round(statistics.median(lat), 1),
                              "p95": round(lat[min(len(lat) - 1, int(0.95 * len(lat)))], 1),
                              "max": round(lat[-1], 1)},
        "stage_median_ms": {k: med(k) for k in ("capture_ms", "reconstruct_ms", "write_ms", "scan_ms")},
        "scans_per_minute": round(scans / minutes, 1),
        "points_median": int(statistics.median(r.points for r in records)),
        "camera": f"{cam.width}x{cam.height}",
        "frames": frames,
    }
