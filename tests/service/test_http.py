"""The HTTP face on 127.0.0.1: the API with a real aiohttp client against the service on the small virtual
rig (a copy of config/appliance.yaml with service.http enabled): the token on every write, the files of known
scans only, server-sent events, request bounds, and a missing aiohttp disabling only this face."""

from __future__ import annotations

import asyncio
import json
import logging
import sys
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
import yaml
from faces_helpers import (  # noqa: F401 (warm: a fixture)
    TOKEN,
    appliance_copy,
    faces_of,
    free_port,
    running_service,
    token_file,
    wait_until,
    warm,
)
from plyfile import PlyData

from appliance.service.control import request

pytestmark = pytest.mark.usefixtures("warm")  # numba's kernels loaded before any loop is measured

AUTH = {"Authorization": f"Bearer {TOKEN}"}


def http_config(tmp: Path, **http: Any) -> tuple[Path, str]:
    port = free_port()
    cfg = appliance_copy(tmp, http={"listen": f"127.0.0.1:{port}", "token_file": str(token_file(tmp)), **http})
    return cfg, f"http://127.0.0.1:{port}"


def test_reference_config_leaves_http_off(tmp_path: Path, loop_guard: None) -> None:
    doc = yaml.safe_load(appliance_copy(tmp_path).read_text())
    assert doc["service"]["http"]["listen"] is None

    async def main() -> None:
        async with running_service(appliance_copy(tmp_path)) as svc:
            assert faces_of(svc).face("http") is None and not faces_of(svc).disabled

    asyncio.run(main())


def test_trigger_needs_the_token_and_the_scan_is_served(
    tmp_path: Path, loop_guard: None, caplog: pytest.LogCaptureFixture
) -> None:
    cfg, base = http_config(tmp_path)
    caplog.set_level(logging.INFO)

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            async with http.post(f"{base}/api/trigger") as r:
                assert r.status == 401 and r.headers["WWW-Authenticate"].startswith("Bearer")
            async with http.post(f"{base}/api/trigger", headers={"Authorization": "Bearer wrong-guess-42"}) as r:
                assert r.status == 401
            assert svc.board.counters["triggers"] == 0  # refused before the service saw it

            async with http.post(f"{base}/api/trigger?wait=1", headers=AUTH) as r:
                assert r.status == 200
                reply = await r.json()
            scan = reply["scan"]
            assert reply["ok"] and reply["result"] == "started" and scan["trigger"] == "http" and scan["points"] > 1000
            async with http.get(f"{base}/api/scans?limit=5") as r:
                listed = (await r.json())["scans"]
            assert listed[0]["scan_id"] == scan["scan_id"] and listed[0]["timings_ms"]["trigger_to_file_ms"] > 0
            assert "calibration_health" in listed[0]

            async with http.get(f"{base}/api/status") as r:
                st = await r.json()
            ctl = (await asyncio.to_thread(request, svc.socket_path, {"cmd": "status"}))["status"]
            assert set(st) == set(ctl) and st["counters"] == ctl["counters"] and st["state"] == "idle"
            assert st["last_scans"][-1]["scan_id"] == scan["scan_id"]

            sid = scan["scan_id"]
            async with http.get(f"{base}/api/scans/{sid}/preview.png") as r:
                assert r.status == 200 and (await r.read())[:8] == b"\x89PNG\r\n\x1a\n"
            async with http.get(f"{base}/api/scans/{sid}/sidecar.json") as r:
                assert json.loads(await r.read())["scan_id"] == sid
            ply = tmp_path / "got.ply"
            async with http.get(f"{base}/api/scans/{sid}/cloud.ply") as r:
                await asyncio.to_thread(ply.write_bytes, await r.read())
            v = (await asyncio.to_thread(PlyData.read, str(ply)))["vertex"]
            assert v.count == scan["points"]
            async with http.get(f"{base}/api/scans/{sid}/cloud.bin") as r:
                xyz = np.frombuffer(await r.read(), "<f4").reshape(-1, 3)
            assert 1000 < len(xyz) <= 20000 and int(r.headers["X-Points"]) == len(xyz)
            full = np.stack([v["x"], v["y"], v["z"]], 1)
            assert np.all(xyz.min(0) >= full.min(0)) and np.all(xyz.max(0) <= full.max(0))
            np.testing.assert_array_equal(xyz[0], full[0])

            # only files of known scans: no traversal, no unknown ids, no other names
            for path in ("/api/scans/..%2F..%2F..%2Fetc%2Fpasswd/cloud.ply", f"/api/scans/{sid}/..%2Fx.ply",
                         f"/api/scans/{sid[:-1]}9/cloud.ply", f"/api/scans/{sid}/cloud.ply.tmp",
                         "/static/../faces.py", "/static/%2e%2e%2ffaces.py"):
                async with http.get(base + path) as r:
                    assert r.status == 404, path

    asyncio.run(main())
    text = caplog.text
    assert text.count("refused: 401") == 2 and "127.0.0.1" in text
    assert TOKEN not in text and "wrong-guess-42" not in text


def test_events_stream_state_and_finished_scan(tmp_path: Path, loop_guard: None) -> None:
    cfg, base = http_config(tmp_path)

    async def main() -> None:
        async with running_service(cfg), aiohttp.ClientSession() as http:
            async with http.get(f"{base}/api/events") as stream:
                assert stream.headers["Content-Type"].startswith("text/event-stream")

                async def next_event() -> tuple[str, dict[str, Any]]:
                    kind, data = "", ""
                    while True:
                        line = (await stream.content.readline()).decode().rstrip("\n")
                        if line.startswith("event: "):
                            kind = line[7:]
                        elif line.startswith("data: "):
                            data = line[6:]
                        elif not line and kind:
                            return kind, json.loads(data)

                kind, first = await asyncio.wait_for(next_event(), 5)
                assert kind == "state" and first["state"] == "idle"
                async with http.post(f"{base}/api/trigger", headers=AUTH) as r:
                    assert (await r.json())["result"] == "started"
                states, scan = [], None
                while scan is None:
                    kind, ev = await asyncio.wait_for(next_event(), 10)
                    if kind == "state":
                        states.append(ev["state"])
                    else:
                        scan = ev
                assert "scanning" in states and scan["ok"] and scan["trigger"] == "http"
                # one camera, one coded axis: nothing redundant to judge the calibration by
                assert scan["calibration_health"]["status"] == "not measured"
            async with http.get(f"{base}/api/scans?limit=1") as r:
                assert (await r.json())["scans"][0]["scan_id"] == scan["scan_id"]

    asyncio.run(main())


def test_request_size_rate_and_stream_bounds(tmp_path: Path, loop_guard: None) -> None:
    cfg, base = http_config(tmp_path, rate_per_s=3, max_request_kb=4, max_event_clients=1)

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            async with http.post(f"{base}/api/trigger", headers=AUTH, data=b"x" * 64 * 1024) as r:
                assert r.status == 413
            await asyncio.sleep(1.0)  # refill the bucket
            codes = []
            for _ in range(12):
                async with http.get(f"{base}/api/status") as r:
                    codes.append(r.status)
            assert codes[:6] == [200] * 6 and 429 in codes  # a burst of twice the rate, then refused
            await asyncio.sleep(1.0)
            async with http.get(f"{base}/api/events") as first:
                assert first.status == 200
                async with http.get(f"{base}/api/events") as second:
                    assert second.status == 503
            assert svc.board.counters["triggers"] == 0

    asyncio.run(main())


def test_missing_aiohttp_disables_only_the_http_face(
    tmp_path: Path, loop_guard: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg, _ = http_config(tmp_path)
    monkeypatch.setitem(sys.modules, "aiohttp", None)  # import aiohttp raises ImportError
    monkeypatch.delitem(sys.modules, "appliance.service.http", raising=False)

    async def main() -> None:
        async with running_service(cfg) as svc:
            why = faces_of(svc).disabled["http"]
            assert "aiohttp" in why and "pip install" in why
            assert svc.board.last_error is not None and "http face disabled" in svc.board.last_error.message
            reply = await asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True})
            assert reply["ok"] and reply["scan"]["points"] > 1000

    asyncio.run(main())


def test_systemd_unit_allows_the_faces_ports_and_stays_exposed_at_most_2(tmp_path: Path) -> None:
    import re
    import shutil
    import subprocess

    from faces_helpers import REPO

    unit = (REPO / "systemd" / "scan3d.service").read_text()
    allowed = re.findall(r"^SocketBindAllow=(\S+)", unit, re.M)
    assert {"tcp:8080", "tcp:4840"} <= set(allowed) and "SocketBindDeny=any" in unit
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not installed (apt package systemd)")
    copy = tmp_path / "scan3d.service"
    copy.write_text(unit.replace("/opt/scan3d/venv/bin/scan3d run", f"{sys.executable} -m appliance run"))
    r = subprocess.run([analyze, "security", "--offline=true", str(copy)], capture_output=True, text=True,
                       timeout=60)
    m = re.search(r"Overall exposure level for scan3d\.service: ([0-9.]+)", r.stdout)
    assert m is not None, r.stdout + r.stderr
    assert float(m.group(1)) <= 2.0


def test_a_reload_starts_moves_and_stops_the_face(tmp_path: Path, loop_guard: None) -> None:
    cfg = appliance_copy(tmp_path)
    p1, p2 = free_port(), free_port()
    tok = str(token_file(tmp_path))

    async def get_status(port: int) -> int:
        async with aiohttp.ClientSession() as http, http.get(f"http://127.0.0.1:{port}/api/status") as r:
            return r.status

    async def main() -> None:
        async with running_service(cfg) as svc:
            faces = faces_of(svc)
            assert faces.face("http") is None
            await asyncio.to_thread(appliance_copy, tmp_path, http={"listen": f"127.0.0.1:{p1}", "token_file": tok})
            await wait_until(lambda: faces.face("http") is not None, 10, "HTTP face started by the reload")
            assert await get_status(p1) == 200
            await asyncio.to_thread(appliance_copy, tmp_path, http={"listen": f"127.0.0.1:{p2}", "token_file": tok})
            await wait_until(lambda: getattr(faces.face("http"), "port", None) == p2, 10, "HTTP face moved")
            assert await get_status(p2) == 200
            with pytest.raises(aiohttp.ClientConnectionError):
                await get_status(p1)
            await asyncio.to_thread(appliance_copy, tmp_path)
            await wait_until(lambda: faces.face("http") is None, 10, "HTTP face stopped")
            with pytest.raises(aiohttp.ClientConnectionError):
                await get_status(p2)
            assert svc.board.counters["reloads"] == 3

    asyncio.run(main())


def test_tune_and_apply_need_the_token_and_write_the_choice(tmp_path: Path, loop_guard: None) -> None:
    """POST /api/tune probes the rig (busy meanwhile) and answers the choice; POST /api/tune/apply writes the
    choice it was shown into the configuration file and the service reloads it; both guarded like a trigger."""
    cfg, base = http_config(tmp_path)

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            for url in ("/api/tune", "/api/tune/apply"):
                async with http.post(base + url) as r:
                    assert r.status == 401 and r.headers["WWW-Authenticate"].startswith("Bearer")
            async with http.post(f"{base}/api/tune/apply", headers=AUTH) as r:
                assert r.status == 409 and "run a tune first" in (await r.json())["error"]
            async with http.post(f"{base}/api/tune?time_budget_ms=later", headers=AUTH) as r:
                assert r.status == 400
            async with http.post(f"{base}/api/tune?time_budget_ms=-5", headers=AUTH) as r:
                assert r.status == 400 and "must be a positive number" in (await r.json())["error"]
            async with http.post(f"{base}/api/tune?time_budget_ms=3000", headers=AUTH) as r:
                assert r.status == 200
                reply = await r.json()
            chosen = reply["tune"]["choice"]["exposures_us"]
            assert chosen and reply["tune"]["time_budget_ms"] == 3000
            assert any(x.startswith("choice: sequence.exposures_us") for x in reply["tune"]["lines"])
            async with http.post(f"{base}/api/tune/apply", headers=AUTH, json={"exposures_us": [1, 2]}) as r:
                assert r.status == 409 and "is not the last tune's choice" in (await r.json())["error"]
            async with http.post(f"{base}/api/tune/apply", headers=AUTH, data=b'{"exposures_us": "lots"}') as r:
                assert r.status == 400
            assert "exposures_us" not in (yaml.safe_load(await asyncio.to_thread(cfg.read_text))["sequence"] or {})
            async with http.post(f"{base}/api/tune/apply", headers=AUTH, json={"exposures_us": chosen}) as r:
                assert r.status == 200
                applied = (await r.json())["applied"]
            assert applied["reloaded"] and applied["exposures_us"] == chosen
            doc = yaml.safe_load(await asyncio.to_thread(cfg.read_text))
            assert doc["sequence"]["exposures_us"] == chosen
            assert list(svc.cfg.sequence.exposures_us) == chosen
            await wait_until(lambda: svc.board.state == "idle", 60)

    asyncio.run(main())


def test_api_json_and_events_are_strict_json_where_a_value_is_not_a_number() -> None:
    """What the HTTP face sends (API replies, server-sent events) parses in a browser's JSON.parse: NaN and
    infinities (a measurement not made yet) go out as null, not as Python's NaN token."""
    from appliance.service import http as face

    def refuse(token: str) -> None:
        raise AssertionError(f"not JSON: {token}")

    status = {"state": "ready", "last_scan": {"rms_mm": float("nan"), "sigma": (1.5, float("-inf"))}}
    body = face._json_response(status).body
    assert isinstance(body, bytes)
    assert json.loads(body, parse_constant=refuse) == {"state": "ready",
                                                       "last_scan": {"rms_mm": None, "sigma": [1.5, None]}}
    event = face._sse({"type": "scan", "points": 10, "rms_mm": float("nan")}).decode()
    assert event.startswith("event: scan\ndata: ")
    assert json.loads(event.split("data: ", 1)[1], parse_constant=refuse) == {"type": "scan", "points": 10,
                                                                              "rms_mm": None}
