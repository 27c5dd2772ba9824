"""``scan3d tune`` through the running service, and why a scan's pixels have no point in ``scan3d status``.

The service on the small virtual rig, in this process; everything asked as a person asks it: the control socket,
``scan3d tune`` and ``scan3d status`` through :func:`appliance.cli.main`. A tune makes the service busy (state
``tuning``; a trigger meanwhile is refused with one line, whatever ``service.busy_policy`` says), returns the
choice, and the rig is rebuilt after it (the probe changed the projector and the exposures), so the next scan
works. ``--apply`` writes the choice into the service's configuration file and the service reloads it.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import re
import threading
from pathlib import Path
from typing import Any

import e2e_helpers as e2e
import pytest
import yaml
from faces_helpers import appliance_copy, running_service, warm  # noqa: F401 (warm: a fixture)
from test_hdr_scan import VIRTUAL_RIG

from appliance import cli
from appliance.config import load_config
from appliance.procedures import tune as tune_module
from appliance.procedures.tune import scan_time_ms
from appliance.service import daemon as D
from appliance.service.control import request
from appliance.service.state import State
from appliance.service.tuning import TuneRefused


@pytest.fixture(scope="module")
def hdr_kernels(tmp_path_factory: pytest.TempPathFactory) -> None:
    """One HDR scan outside any test's loop guard: numba compiles (a cold cache) or loads the multi-exposure
    decoder's kernels here, holding the interpreter for seconds, not inside the service under test."""
    from appliance.scan import scan_once

    folder = tmp_path_factory.mktemp("warm-hdr")
    asyncio.run(scan_once(load_config(_bright_plane_config(folder, [2500, 40_000]))))


pytestmark = pytest.mark.usefixtures("warm", "hdr_kernels")  # numba's kernels loaded before any loop is measured


def _cli(*args: object) -> tuple[int, str]:
    """``scan3d ARGS`` in this process: exit status and output. Called in a thread while the service runs on the
    loop; the redirect is process-wide (pytest's ``-o log_cli=true`` swaps ``sys.stdout`` at every log record
    and loses what is printed meanwhile: run these tests without it)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main([str(a) for a in args])
    return rc, out.getvalue()


async def _ctl(svc: D.Service, timeout_s: float = 60.0, **req: Any) -> dict[str, Any]:
    return await asyncio.to_thread(request, svc.socket_path, req, timeout_s)


async def _ready(svc: D.Service) -> None:
    await e2e.await_for(lambda: svc.board.state == State.IDLE and svc.hardware.ready, 60)


def test_tune_over_the_socket_returns_a_choice_and_refuses_triggers_meanwhile(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = appliance_copy(tmp_path, busy_policy="queue")  # even a queueing service refuses during a tune
    rc, text = _cli("tune", "--config", cfg)  # no service yet: on the rig directly
    assert rc == 0 and "through the service" not in text, text
    direct = next(x for x in text.splitlines() if x.startswith("choice: "))
    tuning = asyncio.Event()
    # the choice (in its thread) waits until the test has triggered and asked the status: a loaded machine
    # cannot make the tune end before the trigger arrives
    asked = threading.Event()
    real_choose = tune_module.choose

    def choose_when_asked(*a: Any) -> Any:
        assert asked.wait(30), "the test did not trigger during the tune"
        return real_choose(*a)

    monkeypatch.setattr(tune_module, "choose", choose_when_asked)

    def seen(board: Any) -> None:
        if board.state == State.TUNING:
            tuning.set()

    async def main() -> None:
        async with running_service(cfg) as svc:
            svc.board.subscribe(seen)
            tune = asyncio.ensure_future(_ctl(svc, cmd="tune", time_budget_ms=2000))
            await asyncio.wait_for(tuning.wait(), 30)
            try:
                during = await _ctl(svc, cmd="trigger")
                rc, status = await asyncio.to_thread(_cli, "status", "--socket", svc.socket_path)
            finally:
                asked.set()
            reply = await tune
            assert reply["ok"], reply
            # the trigger during the tune: refused, with one line that says why and what to do
            assert not during["ok"] and during["result"].startswith("refused: tuning"), during
            assert "\n" not in during["error"] and "trigger again when it is done" in during["error"]
            assert svc.board.counters["triggers_refused"] == 1 and svc.board.counters["triggers_queued"] == 0
            assert rc == 0 and "TUNING" in status.splitlines()[0], status
            # the choice, the expected time and completeness and what cannot be recovered: what the same probe
            # on the rig directly gives (the service's rig, already open, probed in place)
            tuned = reply["tune"]
            choice = tuned["choice"]
            assert direct in tuned["lines"], (direct, tuned["lines"])
            ex = ", ".join(str(e) for e in choice["exposures_us"])
            assert direct.startswith(f"choice: sequence.exposures_us = [{ex}]")
            assert 1 <= len(choice["exposures_us"]) <= 3 and choice["lit_pixels"] > 10_000
            assert any(line.startswith("cannot recover:") for line in tuned["lines"])
            assert "applied" not in tuned
            # the rig is rebuilt after the probe; then scans run as before
            await _ready(svc)
            assert svc.scanner is not None  # the expected time counts the frames of the projector's sequence
            assert choice["scan_ms"] == pytest.approx(scan_time_ms(choice["exposures_us"], len(svc.scanner.sequence)))
            scan = await e2e.scan_once(svc)
            assert scan["points"] > 1000
            # a second tune while a scan runs is refused with one line
            started = await _ctl(svc, cmd="trigger")
            assert started["ok"], started
            busy = await _ctl(svc, cmd="tune")
            assert not busy["ok"] and "busy" in busy["error"] and "\n" not in busy["error"], busy
            bad = await _ctl(svc, cmd="tune", time_budget_ms="soon")
            assert not bad["ok"] and "time_budget_ms" in bad["error"]

    asyncio.run(main())


def _bright_plane_config(tmp: Path, exposures: list[int]) -> Path:
    """The HDR tests' scene (a bright plane that clips at 10 ms, a black box too dark at 2.5 ms) on the
    small rig's service, scanning at ``exposures``."""
    sequence = {"kind": "gray_phase", "axes": "x", "periods_px": [16], "exposures_us": exposures}
    return e2e.write_config(tmp, virtual_rig=VIRTUAL_RIG, sequence=sequence)


def test_status_says_why_pixels_have_no_point_and_tune_apply_fixes_it(tmp_path: Path) -> None:
    cfg = _bright_plane_config(tmp_path, [10_000])

    async def main(svc: D.Service) -> None:
        sock = svc.socket_path
        scan = await e2e.scan_once(svc)
        (side,) = [Path(f) for f in scan["files"] if f.endswith(".json")]
        sidecar = json.loads(await asyncio.to_thread(side.read_text))
        cam = sidecar["counts"]["cameras"]["cam0"]
        # the record carries the sidecar's reason shares, warnings and passes
        assert scan["reasons"] == {"cam0": cam["reason_shares"]}
        assert scan["warnings"] == sidecar["warnings"]
        assert any("saturated" in w and "scan3d tune" in w for w in scan["warnings"]), scan["warnings"]
        assert scan["hdr"]["exposures_us"] == [10_000.0]
        rc, text = await asyncio.to_thread(_cli, "status", "--socket", sock)
        assert rc == 0, text
        assert f"why pixels of {scan['scan_id']} have no point" in text
        lines = [x for x in text.splitlines() if x.startswith("  cam0") and "with a point" in x]
        assert len(lines) == 1, text
        line = lines[0]
        assert f"saturated {100 * cam['reason_shares']['saturated']:.1f} %" in line, line
        assert f"{100 * cam['reason_shares'].get('decoded', 0.0):.1f} % with a point" in line, line
        assert any(x.startswith("warning   cam0:") and "saturated" in x for x in text.splitlines()), text

        # what the warning says to do: scan3d tune, through the running service (found by the config's
        # control socket), with --apply
        rc, text = await asyncio.to_thread(_cli, "tune", "--config", cfg, "--time-budget-ms", 4000, "--apply")
        assert rc == 0, text
        assert "through the service at" in text and "the service reloaded it" in text, text
        chosen = tuple(load_config(cfg).sequence.exposures_us)
        assert 2 <= len(chosen) <= 3 and min(chosen) < 10_000, text
        assert f"sequence.exposures_us = [{', '.join(map(str, chosen))}]" in text
        assert "chosen by scan3d tune" in await asyncio.to_thread(cfg.read_text)
        assert tuple(svc.cfg.sequence.exposures_us) == chosen  # reloaded as an edit over SSH is
        # the optics' blur the probe measured goes in with the exposures (a plane and a box: two code slopes),
        # measured at the probe's exposure with the most pixels in range (the plane clips at the configured one)
        blur = load_config(cfg).reconstruction.edge_blur_px
        assert f"reconstruction.edge_blur_px = {blur:g}" in text and svc.cfg.reconstruction.edge_blur_px == blur
        assert svc.board.counters["reloads"] >= 1 and not svc.board.config_error
        await _ready(svc)
        after = await e2e.scan_once(svc)
        assert after["hdr"]["exposures_us"] == [float(e) for e in chosen]
        assert not any("saturated" in w for w in after["warnings"]), after["warnings"]
        shares = after["reasons"]["cam0"]
        assert shares.get("saturated", 0.0) < cam["reason_shares"]["saturated"] / 4
        assert shares["decoded"] > cam["reason_shares"].get("decoded", 0.0) + 0.5
        rc, text = await asyncio.to_thread(_cli, "status", "--socket", sock)
        ex = ", ".join(f"{float(e):g}" for e in chosen)
        assert f"exposures {ex} µs; share of the decoded pixels each pass gave:" in text, text
        passes = after["hdr"]["cameras"]["cam0"]
        assert len(passes) == len(chosen)
        assert sum(p["decoded_share"] for p in passes) == pytest.approx(1.0, abs=1e-4)

    rc, _ = e2e.run_in_process(cfg, main)
    assert rc == 0


def test_apply_refuses_what_the_last_tune_did_not_choose(tmp_path: Path) -> None:
    cfg = appliance_copy(tmp_path)

    async def main() -> None:
        async with running_service(cfg) as svc:
            with pytest.raises(TuneRefused, match="nothing to apply; run a tune first"):
                await svc.tune_apply(None)
            reply = await _ctl(svc, cmd="tune")
            assert reply["ok"], reply
            before = await asyncio.to_thread(cfg.read_text)
            chosen = reply["tune"]["choice"]["exposures_us"]
            wrong = rf"\[2500\] is not the last tune's choice \({re.escape(str(chosen))}\)"
            with pytest.raises(TuneRefused, match=wrong):
                await svc.tune_apply([2500])
            assert await asyncio.to_thread(cfg.read_text) == before
            await _ready(svc)

    asyncio.run(main())


def test_tune_without_a_service_still_probes_the_rig_directly(tmp_path: Path) -> None:
    """No service answers on the config's control socket: ``scan3d tune`` probes the rig itself, as before;
    ``--socket`` to a dead socket is one line."""
    cfg = appliance_copy(tmp_path)
    rc, text = _cli("tune", "--config", cfg)
    assert rc == 0 and "through the service" not in text and "choice: sequence.exposures_us = [" in text
    rc, text = _cli("tune", "--config", cfg, "--socket", tmp_path / "nobody.sock")
    assert rc == 2 and "is the service running?" in text and len(text.strip().splitlines()) == 2, text
    doc = yaml.safe_load(cfg.read_text())
    assert "exposures_us" not in (doc.get("sequence") or {})


def test_a_stop_during_a_tune_ends_cleanly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM while the tune chooses: the service stops with exit status 0 and the tune's client gets one line
    (its result, or that the service is stopping), not a hang."""
    cfg = appliance_copy(tmp_path)
    gate = threading.Event()
    real_choose = tune_module.choose

    def choose_when_let(*a: Any) -> Any:
        assert gate.wait(30)
        return real_choose(*a)

    monkeypatch.setattr(tune_module, "choose", choose_when_let)
    replies: list[dict[str, Any]] = []
    pending: list[asyncio.Future[None]] = []

    async def body(svc: D.Service) -> None:
        async def tune() -> None:
            replies.append(await _ctl(svc, cmd="tune"))

        pending.append(asyncio.ensure_future(tune()))
        await e2e.await_for(lambda: svc.board.state == State.TUNING, 30)
        asyncio.get_running_loop().call_later(0.3, gate.set)  # the choice ends while the service stops

    rc, _ = e2e.run_in_process(cfg, body)
    gate.set()
    assert rc == 0
    assert len(replies) == 1 and (replies[0]["ok"] or "\n" not in replies[0]["error"]), replies


def test_a_stop_while_the_rig_is_rebuilt_ends_the_service(tmp_path: Path) -> None:
    """A stop that comes while the rig part closes the rig for a rebuild (after a tune, or a reload) and waits for
    its trigger loop to end: the rig part ends with the stop instead of building a new rig (it used to swallow
    its own cancellation there and the stop waited for ever)."""
    import fake_service as F

    class SlowToLetGo(F.FakeTrigger):
        async def next_event(self) -> Any:  # a driver that takes a moment to let go when cancelled
            try:
                return await super().next_event()
            except asyncio.CancelledError:
                await asyncio.sleep(0.3)
                raise

    svc = F.make(tmp_path)
    svc.trigger = SlowToLetGo()

    async def body() -> None:
        svc.hardware.reconnect()  # what a tune does after its probe
        await F.wait_until(lambda: not svc.hardware.connected)  # closing: waiting for the trigger loop
        await asyncio.sleep(0.05)

    async def main() -> int:
        task = asyncio.create_task(svc.run())
        try:
            await F.wait_until(lambda: F.ready(svc) or task.done())
            await body()
        finally:
            svc.request_stop()
        return await asyncio.wait_for(task, 10)

    assert asyncio.run(main()) == 0
