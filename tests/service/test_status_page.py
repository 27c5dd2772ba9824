"""The status page in a real headless Chromium (Debian's ``chromium``, driven over its DevTools socket on
127.0.0.1): it shows the state, follows the service live over /api/events (a new scan id within 5 s), draws
the preview and the cloud, triggers with the token it asks for once, refuses a wrong one, and fits a phone."""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from faces_helpers import TOKEN, Chromium, appliance_copy, free_port, running_service, token_file

from appliance.service.client import format_status

SHOT = os.environ.get("SCAN3D_STATUS_PAGE_SCREENSHOT")  # set to write the README's screenshot


def test_page_follows_the_service_live(tmp_path: Path) -> None:
    port = free_port()
    cfg = appliance_copy(tmp_path, top={"sequence": {"axes": "xy"}},
                         http={"listen": f"127.0.0.1:{port}", "token_file": str(token_file(tmp_path))})
    base = f"http://127.0.0.1:{port}"

    # started before the loop runs: forking a big process holds the interpreter for a while
    browser = Chromium("about:blank")

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            try:
                await browser.connect()
                await browser.call("Runtime.enable")
                await browser.call("Page.navigate", url=base + "/")
                el = "document.getElementById"

                async def until(expr: str, timeout_s: float) -> float:
                    t0 = time.monotonic()
                    while not await browser.evaluate(expr):
                        if time.monotonic() - t0 > timeout_s:
                            seen = await browser.evaluate(
                                "['state', 'link', 'last-id', 'trigger-result'].map(i => i + '=' + "
                                "document.getElementById(i).textContent).join(', ')")
                            thrown = [e["params"] for e in browser.events if e["method"] == "Runtime.exceptionThrown"]
                            raise AssertionError(f"page: {expr} not true within {timeout_s} s; page: {seen}; "
                                                 f"exceptions: {thrown}")
                        await asyncio.sleep(0.05)
                    return time.monotonic() - t0

                await until(f"{el}('state').textContent === 'idle' && {el}('link').textContent === 'live'", 30)
                assert await browser.evaluate(f"{el}('last-id').textContent") == "none yet"

                # a scan from elsewhere shows up live
                async with http.post(f"{base}/api/trigger?wait=1", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                    sid = (await r.json())["scan"]["scan_id"]
                shown_after = await until(f"{el}('last-id').textContent === '{sid}'", 5.0)
                assert shown_after < 5.0
                await until(f"{el}('scans').textContent.includes('{sid}')", 5)
                await until(f"{el}('preview').naturalWidth > 0 && !{el}('preview').hidden", 5)
                await until(f"{el}('cloud-info').textContent.includes('points shown')", 5)
                lit = await browser.evaluate(
                    f"(() => {{ const c = {el}('cloud'); const d = c.getContext('2d').getImageData(0, 0, c.width,"
                    " c.height).data; let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i] > 40) n++;"
                    " return n; })()")
                assert lit > 2000  # the cloud is drawn
                # both projector axes coded: each scan measures its calibration health (the exact one here)
                assert (await browser.evaluate(f"{el}('health-text').textContent")).startswith("ok: largest residual")
                assert "SIM-0001" in await browser.evaluate(f"{el}('config').textContent")

                # the trigger button asks for the token once; a wrong one is refused and forgotten
                await browser.evaluate("window.prompt = () => 'not-the-token'; "
                                       f"{el}('trigger').click()")
                await until(f"{el}('trigger-result').textContent.includes('wrong token')", 5)
                assert svc.board.counters["triggers"] == 1
                await browser.evaluate(f"window.prompt = () => '{TOKEN}'; {el}('trigger').click()")
                await until(f"{el}('last-id').textContent !== '{sid}' && "
                            f"{el}('last-id').textContent.endsWith('000002')", 10)
                assert svc.board.last_scans[-1].trigger == "http" and svc.board.counters["scans_done"] == 2
                await browser.evaluate("window.prompt = () => { throw new Error('asked twice'); }; "
                                       f"{el}('trigger').click()")
                await until(f"{el}('last-id').textContent.endsWith('000003')", 10)  # token remembered
                blue = await browser.evaluate(  # the plotted line of three scans (#58a6ff)
                    f"(() => {{ const c = {el}('health'); const d = c.getContext('2d').getImageData(0, 0, c.width,"
                    " c.height).data; let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i + 2] > 200 &&"
                    " d[i] < 120 && d[i + 1] > 130) n++; return n; })()")
                assert blue > 100

                # a broken edit of the configuration: refused, shown with its message, the error with its advice
                good = await asyncio.to_thread(cfg.read_text)

                def save(text: str) -> None:  # as an editor saves: a new file renamed over the old
                    tmp = cfg.with_name(".appliance.yaml.new")
                    tmp.write_text(text)
                    os.replace(tmp, cfg)

                await asyncio.to_thread(save, good.replace("busy_policy: refuse", "busy_policy: maybe"))
                await until(f"!{el}('rejected').hidden && {el}('rejected').textContent.includes('busy_policy')", 5)
                assert "REJECTED" in await browser.evaluate(f"{el}('rejected').textContent")
                # what the service answers now, replayed below as replies that come after the fix's event
                stale = await browser.call("Runtime.evaluate", awaitPromise=True, returnByValue=True, expression=(
                    "(async () => { window.staleReplies = {}; for (const u of ['/api/status', '/api/config'])"
                    " window.staleReplies[u] = await (await fetch(u, { cache: 'no-store' })).text();"
                    " return window.staleReplies; })()"))
                stale = {u: json.loads(t) for u, t in stale["result"]["value"].items()}
                assert "busy_policy" in stale["/api/status"]["config"]["error"]
                assert "busy_policy" in stale["/api/config"]["rejected_edit"]
                # the error and its advice arrive in the same state event, but may be drawn a moment later
                await until(f"{el}('advice').textContent.includes('validate-config')", 5)
                assert "config" in await browser.evaluate(f"{el}('error').textContent")
                await asyncio.to_thread(save, good)  # put right: the rejection goes away
                saved_utc = dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")
                try:
                    await until(f"{el}('rejected').hidden", 5)
                except AssertionError as exc:  # say whether the reload came late or the page missed its event
                    raise AssertionError(f"{exc}; board: {svc.board.config_error!r} {svc.board.counters}; saved "
                                         f"{saved_utc}, applied {svc.board.config_loaded_utc}") from None
                # a reply answered before the fix but read after the event that cleared the rejection (they
                # travel on two connections) must not bring it back: it is older than what the page shows
                replayed = await browser.call("Runtime.evaluate", awaitPromise=True, returnByValue=True, expression=(
                    "(async () => { const real = window.fetch; window.fetch = async (u, o) => u in"
                    " window.staleReplies ? new Response(window.staleReplies[u]) : real(u, o);"
                    " try { await refreshStatus(); await refreshConfig(); } finally { window.fetch = real; }"
                    f" return [{el}('rejected').hidden, {el}('state').textContent]; }})()"))
                assert replayed["result"]["value"] == [True, "idle"], replayed

                if SHOT:
                    await browser.call("Emulation.setDeviceMetricsOverride", width=1100, height=1180,
                                       deviceScaleFactor=1, mobile=False)
                    await asyncio.sleep(0.5)
                    await browser.screenshot(Path(SHOT))
                # a phone: nothing wider than the screen
                await browser.call("Emulation.setDeviceMetricsOverride", width=390, height=844,
                                   deviceScaleFactor=2, mobile=True)
                await asyncio.sleep(1.0)
                wide = await browser.evaluate(  # which cards overflow, to say so when one does
                    "[...document.querySelectorAll('.card')].filter(c => c.scrollWidth > c.clientWidth + 1)"
                    ".map(c => c.querySelector('h2') ? c.querySelector('h2').textContent : c.className).join('; ')")
                assert await browser.evaluate("document.documentElement.scrollWidth") <= 390, wide
                shot = tmp_path / "phone.png"
                await browser.screenshot(shot)
                assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
                errors = [e for e in browser.events if e["method"] == "Runtime.exceptionThrown"]
                assert not errors, errors
            finally:
                await browser.disconnect()

    try:
        asyncio.run(main())
    finally:
        browser.kill()


def _two_camera_config(tmp: Path, **service: Any) -> Path:
    """The face tests' small rig with a second camera 120 mm to the left, both axes coded, mode ``both``."""
    import yaml
    from faces_helpers import SMALL_RIG

    cfg = appliance_copy(tmp, top={"sequence": {"axes": "xy"}, "reconstruction": {"mode": "both"}}, **service)
    doc = yaml.safe_load(cfg.read_text())
    doc["cameras"]["cam1"] = {"type": "sim"}
    doc["virtual_rig"]["cameras"]["cam1"] = {**SMALL_RIG["cameras"]["cam0"], "position_mm": [-120, 0, 0]}
    cfg.write_text(yaml.safe_dump(doc, sort_keys=False))
    return cfg


@pytest.fixture(scope="module")
def two_camera_kernels(tmp_path_factory: pytest.TempPathFactory) -> None:
    """One scan of the two-camera rig outside any test's loop guard: numba compiles (a cold cache) or loads the
    camera-camera kernels here, holding the interpreter for seconds, not inside the service under test."""
    from appliance.config import load_config
    from appliance.scan import scan_once

    asyncio.run(scan_once(load_config(_two_camera_config(tmp_path_factory.mktemp("warm")))))


@pytest.mark.usefixtures("two_camera_kernels")
def test_page_shows_the_share_of_pixels_both_cameras_see(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A two-camera rig in mode ``both``: each scan's record carries the camera-camera matcher's both-seen figure
    (the sidecar's extra.stereo.both_seen), and the page shows it under the last scan and in the scans table."""
    caplog.set_level(logging.INFO, logger="appliance")
    port = free_port()
    cfg = _two_camera_config(tmp_path, http={"listen": f"127.0.0.1:{port}",
                                             "token_file": str(token_file(tmp_path))})
    base = f"http://127.0.0.1:{port}"
    browser = Chromium("about:blank")

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            try:
                async with http.post(f"{base}/api/trigger?wait=1", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                    reply = await r.json()
                scan = reply["scan"]
                assert scan["ok"], reply
                seen = scan["both_seen"]
                assert seen["pixels"] > 10_000 and 0.9 < seen["share"] <= 1.0, seen
                assert seen["reconstructed"] == round(seen["share"] * seen["pixels"])
                async with http.get(f"{base}/api/status") as r:
                    assert (await r.json())["last_scans"][-1]["both_seen"] == seen
                sidecar = next(p for p in map(Path, scan["files"]) if p.suffix == ".json")
                assert json.loads(await asyncio.to_thread(sidecar.read_text))["extra"]["stereo"]["both_seen"] == seen
                await browser.connect()
                await browser.call("Page.navigate", url=base + "/")
                el = "document.getElementById"
                shown = f"(({el}('both-seen') || {{}}).textContent || '')"  # '' until the page is there
                t0 = time.monotonic()
                while f"{100 * seen['share']:.1f} %" not in await browser.evaluate(shown):
                    assert time.monotonic() - t0 < 10, await browser.evaluate(shown)
                    await asyncio.sleep(0.05)
                line = await browser.evaluate(shown)
                assert f"{seen['pixels']:,} pixels both cameras see" in line, line
                row = await browser.evaluate(f"[...{el}('scans').rows[0].cells].map(c => c.textContent)")
                assert row[0] == scan["scan_id"] and row[7] == f"{100 * seen['share']:.1f} %", row
                assert svc.board.last_scans[-1].both_seen == seen
                # scan3d status says it too
                screen = format_status(svc.board.snapshot())
                assert f"camera-camera: {100 * seen['share']:.1f} % of the {seen['pixels']} pixels both" in screen
                # ... and the service's log
                said = f"camera-camera: {100 * seen['share']:.1f} % of the {seen['pixels']} pixels both cameras see"
                assert any(said in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]
                errors = [e for e in browser.events if e["method"] == "Runtime.exceptionThrown"]
                assert not errors, errors
            finally:
                await browser.disconnect()

    try:
        asyncio.run(main())
    finally:
        browser.kill()


def test_page_says_why_pixels_have_no_point_and_tunes(tmp_path: Path) -> None:
    """Under the last scan, the page shows per camera the share with a point and why the others have none (the
    record's reasons, which are the sidecar's reason_shares); the Tune button probes the rig (the service busy
    in state ``tuning`` meanwhile) and shows the choice, and Apply writes it into the configuration file."""
    import yaml

    from appliance.service.state import State

    port = free_port()
    cfg = appliance_copy(tmp_path, http={"listen": f"127.0.0.1:{port}", "token_file": str(token_file(tmp_path))})
    base = f"http://127.0.0.1:{port}"
    browser = Chromium("about:blank")
    states: list[str] = []

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            svc.board.subscribe(lambda b: states.append(str(b.state)))
            try:
                async with http.post(f"{base}/api/trigger?wait=1", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                    scan = (await r.json())["scan"]
                shares = scan["reasons"]["cam0"]
                side = next(p for p in map(Path, scan["files"]) if p.suffix == ".json")
                sidecar = json.loads(await asyncio.to_thread(side.read_text))
                assert shares == sidecar["counts"]["cameras"]["cam0"]["reason_shares"] and "shadow" in shares
                await browser.connect()
                await browser.call("Page.navigate", url=base + "/")
                el = "document.getElementById"

                async def until(expr: str, timeout_s: float) -> str:
                    t0 = time.monotonic()
                    while not await browser.evaluate(expr):
                        seen = await browser.evaluate(f"[...['reasons', 'tune-status', 'tune-result', 'state']]"
                                                      f".map(i => ({el}(i) || {{}}).textContent).join(' | ')")
                        assert time.monotonic() - t0 < timeout_s, f"{expr}: {seen}"
                        await asyncio.sleep(0.05)
                    return str(await browser.evaluate(f"{el}('reasons').textContent"))

                line = await until(f"({el}('reasons') || {{}}).textContent && {el}('reasons').textContent"
                                   ".includes('with a point')", 10)
                assert f"cam0: {100 * shares['decoded']:.1f} % with a point" in line, line
                assert f"shadow {100 * shares['shadow']:.1f} %" in line, line
                await until(f"{el}('state').textContent === 'idle' && !{el}('tune').disabled", 10)
                await browser.evaluate(f"window.prompt = () => '{TOKEN}'; {el}('tune').click()")
                await until(f"{el}('tune-result').textContent.includes('choice: sequence.exposures_us')", 30)
                assert State.TUNING in states  # busy while it probed
                result = await browser.evaluate(f"{el}('tune-result').textContent")
                assert "cannot recover" in result and "expected scan time" in result, result
                await browser.evaluate(f"{el}('tune-apply').click()")
                await until(f"{el}('tune-status').textContent.startsWith('applied:')", 30)
                doc = yaml.safe_load(await asyncio.to_thread(cfg.read_text))
                ex = ", ".join(str(e) for e in doc["sequence"]["exposures_us"])
                assert f"choice: sequence.exposures_us = [{ex}]" in result
                assert list(svc.cfg.sequence.exposures_us) == doc["sequence"]["exposures_us"]
                errors = [e for e in browser.events if e["method"] == "Runtime.exceptionThrown"]
                assert not errors, errors
                await until(f"{el}('state').textContent === 'idle'", 30)  # the rig rebuilt with the choice
            finally:
                await browser.disconnect()

    try:
        asyncio.run(main())
    finally:
        browser.kill()


MIRROR_GROOVE = [  # issue 25's mirror groove (tests/accuracy/hard_scenes.py): a concave corner, the left face a mirror
    {"type": "mesh", "albedo": 0.15, "material": {"mirror": 0.6}, "triangles": [[0, 1, 2], [0, 2, 3]],
     "vertices_mm": [[-70, -90, 590], [0, -90, 660], [0, 90, 660], [-70, 90, 590]]},
    {"type": "mesh", "albedo": 0.9, "triangles": [[0, 1, 2], [0, 2, 3]],
     "vertices_mm": [[0, -90, 660], [70, -90, 590], [70, 90, 590], [0, 90, 660]]},
    {"type": "plane", "point_mm": [0, 0, 700], "normal": [0, 0, -1], "albedo": 0.5},
]


def test_page_status_and_log_say_what_a_mirror_lit_twice_was_taken_apart(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The service scanning the mirror groove (the default projector and sequence, a 480 x 384 camera): the
    matte face lit directly and through the mirror decodes with the two copies taken apart; the scan's record,
    ``scan3d status``, the service's log and the page say which share of the image that was."""
    import yaml

    caplog.set_level(logging.INFO, logger="appliance")
    port = free_port()
    cfg = appliance_copy(tmp_path, http={"listen": f"127.0.0.1:{port}", "token_file": str(token_file(tmp_path))})
    doc = yaml.safe_load(cfg.read_text())
    doc["virtual_rig"].pop("projector", None)  # the default projector (1280 x 800), as the hard scenes use
    doc["virtual_rig"]["cameras"] = {"cam0": {"width": 480, "height": 384, "focal_px": 900, "position_mm": [0, 0, 0],
                                              "look_at_mm": [0, 0, 600]}}  # fmt: skip
    doc["virtual_rig"]["scene"] = MIRROR_GROOVE
    doc["virtual_rig"]["imaging"].update(ambient_dn=10, projector_gain_dn=180, exposure_us=10_000, seed=3)
    cfg.write_text(yaml.safe_dump(doc, sort_keys=False))
    base = f"http://127.0.0.1:{port}"
    browser = Chromium("about:blank")

    async def main() -> None:
        async with running_service(cfg) as svc, aiohttp.ClientSession() as http:
            try:
                async with http.post(f"{base}/api/trigger?wait=1", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                    scan = (await r.json())["scan"]
                assert scan["ok"], scan
                share = scan["separated"]["cam0"]
                side = next(p for p in map(Path, scan["files"]) if p.suffix == ".json")
                cam = json.loads(await asyncio.to_thread(side.read_text))["counts"]["cameras"]["cam0"]
                assert share == round(cam["separated"] / cam["pixels"], 6) and share > 0.1, (share, cam)  # 14 %
                pct = f"{100 * share:.1f} %"
                screen = format_status(svc.board.snapshot())
                assert f"the direct copy taken apart: cam0 {pct} of the image" in screen, screen
                said = f"cam0: {pct} of the image lit by two copies of the pattern (a mirror)"
                assert any(said in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]
                await browser.connect()
                await browser.call("Page.navigate", url=base + "/")
                shown = "((document.getElementById('reasons') || {}).textContent || '')"
                t0 = time.monotonic()
                while "taken apart" not in await browser.evaluate(shown):
                    assert time.monotonic() - t0 < 10, await browser.evaluate(shown)
                    await asyncio.sleep(0.05)
                assert f"the direct copy taken apart: cam0 {pct}" in await browser.evaluate(shown)
                errors = [e for e in browser.events if e["method"] == "Runtime.exceptionThrown"]
                assert not errors, errors
            finally:
                await browser.disconnect()

    try:
        asyncio.run(main())
    finally:
        browser.kill()
