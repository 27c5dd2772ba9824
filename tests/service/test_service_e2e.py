"""The service end to end on a small virtual rig (320x256 camera): the serial controller's firmware on a pty,
mDNS seen from another process, sd_notify, live reload, the share going away, SIGTERM mid-scan, 100 scans.

In-process runs use :class:`appliance.service.daemon.Service`; subprocess runs use
``python -m appliance run --config TMP.yaml --control-socket TMP/sock`` (what ``scan3d run`` does).
"""

from __future__ import annotations

import asyncio
import gc
import os
import re
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
import yaml
from e2e_helpers import (
    REPO,
    ServiceProcess,
    await_for,
    complete_scan,
    day_of,
    no_partial_files,
    run_in_process,
    scan_files,
    scan_once,
    wait_for,
    write_config,
)

from appliance.output import share as S
from appliance.service import daemon as D
from appliance.service import rig as rig_mod
from appliance.service import writing as writing_mod
from appliance.service.control import request
from appliance.service.state import Phase, State

pytestmark = pytest.mark.usefixtures("loop_guard")


@pytest.fixture(autouse=True)
def fast(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rig_mod, "RETRY_FIRST_S", 0.1)
    monkeypatch.setattr(writing_mod, "SPOOL_RETRY_S", 0.1)


# --- the button on the serial controller's firmware (pty), files on the share, mDNS from another process ---


@pytest.mark.hil
def test_serial_button_press_writes_files_and_updates_mdns(tmp_path: Path) -> None:
    from mdns_watch import TxtWatcher

    from appliance.firmware.simulate import SimulatedController

    name = f"scan3d-e2e-{uuid.uuid4().hex[:8]}"
    with SimulatedController(tmp_path / "tty") as board:
        port = board.start()
        config = write_config(tmp_path, mdns=name, trigger={"type": "serial", "port": port})
        watcher = TxtWatcher(name)
        svc = ServiceProcess(config, tmp_path)
        try:
            svc.wait_ready()
            txt = watcher.wait_for(lambda t: t.get("state") == "idle", 30)
            assert (
                txt["scans"] == "0" and txt["serial"] == "E2E-1" and txt["share"] == str(tmp_path / "share")
            )
            wait_for(lambda: board.pins.leds == (True, False, False), 10, "ready lamp")
            board.press_button()
            st = wait_for(
                lambda: (s := svc.status()).get("counters", {}).get("scans_done") == 1 and s,
                60,
                "scan after the button press",
            )
            rec = st["last_scans"][-1]
            assert rec["trigger"] == "trigger" and rec["location"] == "share"
            complete_scan(tmp_path / "share" / day_of(rec["scan_id"]), rec["scan_id"])
            txt = watcher.wait_for(lambda t: t.get("scans") == "1", 30)
            assert txt["last"] == rec["scan_id"] and txt["state"] == "idle"
            assert svc.stop() == 0
        finally:
            if svc.proc.poll() is None:
                svc.proc.kill()
            watcher.close()
    no_partial_files(tmp_path / "share", tmp_path / "spool")


# --- sd_notify ----------------------------------------------------------------------------------------------


def test_sd_notify_ready_watchdog_status_stopping(tmp_path: Path) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    msgs: list[dict[str, str]] = []

    def receive() -> None:
        sock.settimeout(0.2)
        while not getattr(sock, "_closed", False):
            try:
                data = sock.recv(4096).decode()
            except TimeoutError:
                continue
            except OSError:
                return
            msgs.append(dict(line.split("=", 1) for line in data.splitlines()))

    reader = threading.Thread(target=receive, daemon=True)
    reader.start()
    config = write_config(tmp_path)
    svc = ServiceProcess(
        config, tmp_path, {"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "400000"}
    )
    try:
        wait_for(lambda: any("READY" in m for m in msgs), 120, "READY=1")
        ready_at = next(i for i, m in enumerate(msgs) if "READY" in m)
        assert any("warm kernels" in m.get("STATUS", "") for m in msgs[:ready_at])  # warm-up came first
        wait_for(lambda: sum("WATCHDOG" in m for m in msgs[ready_at:]) >= 2, 10, "watchdog pings")
        reply = request(svc.sock, {"cmd": "trigger", "wait": True}, 120)
        assert reply["ok"]
        statuses = [m["STATUS"] for m in msgs if "STATUS" in m]
        assert any(s.startswith("scanning") for s in statuses) and any(
            s.startswith("writing") for s in statuses
        )
        assert svc.stop() == 0
        wait_for(lambda: any("STOPPING" in m for m in msgs), 5, "STOPPING=1")
    finally:
        if svc.proc.poll() is None:
            svc.proc.kill()
        sock.close()


# --- SIGTERM in the middle of a scan -----------------------------------------------------------------------


@pytest.mark.parametrize("grace_s", [0.0, 30.0], ids=["abort", "finish"])
def test_sigterm_mid_scan_leaves_no_partial_file(tmp_path: Path, grace_s: float) -> None:
    config = write_config(tmp_path, camera={"frame_delay_ms": 60}, service={"stop_grace_s": grace_s})
    svc = ServiceProcess(config, tmp_path)
    try:
        svc.wait_ready()
        assert request(svc.sock, {"cmd": "trigger"})["ok"]
        wait_for(lambda: svc.status().get("state") == "scanning", 30, "scanning")
        time.sleep(0.3)  # a few frames in
        assert svc.stop() == 0
    finally:
        if svc.proc.poll() is None:
            svc.proc.kill()
    no_partial_files(tmp_path / "share", tmp_path / "spool", tmp_path / "state")
    files = scan_files(tmp_path / "share")
    if grace_s:
        assert len(files) == 3
        complete_scan(files[0].parent, files[0].stem)
    else:
        assert files == []
    assert "stopped after" in svc.log.read_text()


# --- live configuration ------------------------------------------------------------------------------------


def test_broken_config_keeps_scanning_and_fixed_config_is_picked_up(tmp_path: Path) -> None:
    config = write_config(tmp_path)
    good = yaml.safe_load(config.read_text())

    async def body(svc: D.Service) -> None:
        bad = dict(good, reconstruction={**good["reconstruction"], "min_neighbours": 12})
        config.write_text(yaml.safe_dump(bad, sort_keys=False))
        await await_for(lambda: svc.board.config_error != "", 10)
        assert "reconstruction.min_neighbours" in svc.board.config_error
        assert svc.board.config_error.startswith(f"{config}:")  # file:line: key = value: rule
        rec = await scan_once(svc)  # the last good configuration keeps scanning
        assert rec["ok"] and "E2E-1" in rec["scan_id"] and len(rec["files"]) == 3
        fixed = dict(
            good,
            serial="E2E-2",
            output={**good["output"], "preview": False},
            reconstruction={**good["reconstruction"], "max_depth_mm": 800},
        )
        config.write_text(yaml.safe_dump(fixed, sort_keys=False))
        await await_for(
            lambda: (
                svc.cfg.serial == "E2E-2"
                and svc.board.state == State.IDLE
                and svc.board.phase == Phase.READY
                and svc.scanner is not None
            ),
            60,
        )
        assert svc.board.config_error == "" and svc.scanner.cfg.reconstruction.max_depth_mm == 800
        rec = await scan_once(svc)
        assert "E2E-2" in rec["scan_id"] and len(rec["files"]) == 2  # no preview any more

    rc, svc = run_in_process(config, body)
    assert rc == 0 and svc.board.counters["reloads_rejected"] >= 1


# --- the share goes away (removed, then full) and comes back ------------------------------------------------


def test_share_away_spools_and_delivers_everything_in_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = write_config(tmp_path)
    share, away = tmp_path / "share", tmp_path / "share-unmounted"
    full = {"on": False}
    real = S.STATVFS
    monkeypatch.setattr(
        S,
        "STATVFS",
        lambda p: (
            type("F", (), {"f_bavail": 1, "f_frsize": 4096})()
            if full["on"] and p.startswith(str(share))
            else real(p)
        ),
    )
    ids: list[str] = []

    async def body(svc: D.Service) -> None:
        ids.append((await scan_once(svc))["scan_id"])
        share.rename(away)  # the share disappears during the run
        for _ in range(3):
            rec = await scan_once(svc)
            assert rec["location"] == "spool"
            ids.append(rec["scan_id"])
        st = (await asyncio.to_thread(request, svc.socket_path, {"cmd": "status"}))["status"]
        assert not st["share"]["available"] and st["share"]["spooled_scans"] == 3
        assert st["last_error"]["where"] == "share" and "mounted" in st["last_error"]["advice"]
        away.rename(share)
        full["on"] = True  # back, but full: still spooled
        rec = await scan_once(svc)
        assert rec["location"] == "spool"
        ids.append(rec["scan_id"])
        full["on"] = False
        await await_for(lambda: not svc.writer.spool_entries(), 30)
        ids.append((await scan_once(svc))["scan_id"])

    rc, svc = run_in_process(config, body)
    assert rc == 0
    sidecars = sorted(share.glob("*/*.json"), key=lambda p: p.stat().st_mtime_ns)
    assert [p.stem for p in sidecars] == ids  # every scan, in order
    for scan_id in ids:
        complete_scan(share / day_of(scan_id), scan_id)
    assert svc.board.counters["spooled"] == 4 and svc.board.counters["scans_done"] == 6
    no_partial_files(share, tmp_path / "spool")
    assert svc.writer.spool_entries() == []


# --- 100 scans: memory, threads, file descriptors ----------------------------------------------------------


def _rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.mark.slow
def test_100_scans_memory_threads_and_fds_stay_flat(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_config(
        tmp_path,
        output={
            "directory": str(tmp_path / "share"),
            "min_free_mb": 0,
            "spool_directory": str(tmp_path / "spool"),
            "preview": True,
        },
    )
    samples: dict[int, tuple[int, int, int]] = {}

    async def body(svc: D.Service) -> None:
        for i in range(1, 101):
            outcome, job = svc.request_scan(D.TriggerEvent("bench", time.monotonic_ns()))
            assert job is not None, outcome
            rec = await job.done
            assert rec.ok, rec.error
            if i in (20, 100):  # measured in a thread: a full collection is not for the event loop

                def sample() -> tuple[int, int, int]:
                    gc.collect()
                    # the fewest of a few readings: a file another thread has open for a moment (a state file
                    # being replaced) is no leak; a leaked one is there in every reading
                    counts = []
                    for _ in range(5):
                        counts.append((threading.active_count(), len(os.listdir("/proc/self/fd"))))
                        time.sleep(0.1)
                    return _rss_kb(), min(c[0] for c in counts), min(c[1] for c in counts)

                await asyncio.sleep(0.5)  # the scan's transient threads (camera acquisition) end
                samples[i] = await asyncio.to_thread(sample)

    threads_before = threading.active_count()
    rc, svc = run_in_process(config, body)
    assert rc == 0 and svc.board.counters["scans_done"] == 100
    (rss20, thr20, fd20), (rss100, thr100, fd100) = samples[20], samples[100]
    growth_mb = (rss100 - rss20) / 1024
    with capsys.disabled():
        print(
            f"\n100 scans: RSS {rss20 / 1024:.1f} MB after 20, {rss100 / 1024:.1f} MB after 100 "
            f"(growth {growth_mb:+.1f} MB); threads {thr20} -> {thr100}; fds {fd20} -> {fd100}"
        )
    # 80 scans (the long soak is scripts/soak): a leak of 0.1 MB a scan shows as 8 MB; measured -0.6 to +0.0 MB
    # over 180 scans when this test ran 200
    assert growth_mb < 8, f"resident memory grew {growth_mb:.1f} MB over 80 scans"
    assert thr100 == thr20 and fd100 == fd20  # (the sampling thread counts in both)
    assert len(list((tmp_path / "share").glob("*/*.json"))) == 100  # a run across midnight fills two days
    time.sleep(0.2)
    assert threading.active_count() <= threads_before + 1, [t.name for t in threading.enumerate()]


# --- scripts/run --service: Enter presses the simulated button ----------------------------------------------


def test_stdin_button_scans_then_exits_after_n(tmp_path: Path) -> None:
    config = write_config(tmp_path)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "appliance",
            "run",
            "--config",
            str(config),
            "--control-socket",
            str(tmp_path / "sock"),
            "--stdin-button",
            "--scans",
            "2",
            "--ground-truth",
        ],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdin is not None and proc.stdout is not None
    # the log is read as it comes: a pipe nobody reads blocks the service once it holds 64 kB
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    try:
        wait_for(
            lambda: (
                request(tmp_path / "sock", {"cmd": "status"})["status"]["state"] == "idle"
                if (tmp_path / "sock").exists()
                else False
            ),
            120,
            "ready",
        )
        for n in (1, 2):
            proc.stdin.write("\n")
            proc.stdin.flush()
            wait_for(
                lambda n=n: len(list((tmp_path / "share").rglob("*.json"))) == n or proc.poll() is not None,
                120,  # a loaded two-core machine (the suite beside it) takes several times the usual
                f"scan {n}",
            )
        assert proc.wait(120) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        reader.join(10)
    clouds = sorted((tmp_path / "share").rglob("*.ply"))
    assert len(clouds) == 2 and len(list((tmp_path / "share").rglob("*.json"))) == 2
    log = "".join(lines)
    for cloud in clouds:  # each scan says where its cloud went and how far it is from the truth
        assert f"share: {cloud}" in log or f"share: {cloud.relative_to(REPO)}" in log, log[-2000:]
    errors = re.findall(r"error against ground truth: (\d+) points: RMS ([0-9.]+) mm", log)
    # a sanity bound on this coarse 320x256 rig (its RMS is 0.47-0.52 mm: per-point jump limits keep 97 % of
    # lit pixels, the old fixed 2 mm limit 95.8 %); the accuracy targets are test_virtual_rig_accuracy's
    assert len(errors) == 2 and all(int(n) > 1000 and float(rms) < 0.6 for n, rms in errors), errors


# --- scan numbers across a SIGKILL; the numba threading layer ------------------------------------------------


def _number(scan_id: str) -> int:
    return int(scan_id.rsplit("-", 1)[1])


def test_scan_numbers_are_never_reused_after_a_sigkill(tmp_path: Path) -> None:
    config = write_config(tmp_path, camera={"frame_delay_ms": 60})
    first = ServiceProcess(config, tmp_path)
    try:
        st = first.wait_ready()
        assert st["numba_threading_layer"] in ("omp", "tbb") and st["rss_mb"] > 0
        done = request(first.sock, {"cmd": "trigger", "wait": True}, 120)["scan"]["scan_id"]
        assert request(first.sock, {"cmd": "trigger"})["ok"]
        killed = wait_for(
            lambda: (s := first.status()).get("state") == "scanning" and s["detail"], 30, "second scan running"
        )
        first.proc.kill()  # SIGKILL in the middle of the scan: nothing gets to save anything
        first.proc.wait(30)
    finally:
        if first.proc.poll() is None:
            first.proc.kill()
    assert _number(killed) == _number(done) + 1
    (tmp_path / "sock").unlink(missing_ok=True)
    second = ServiceProcess(config, tmp_path)
    try:
        second.wait_ready()
        after = request(second.sock, {"cmd": "trigger", "wait": True}, 120)["scan"]["scan_id"]
        assert second.stop() == 0
    finally:
        if second.proc.poll() is None:
            second.proc.kill()
    assert _number(after) > _number(killed), (done, killed, after)  # the killed scan's number is not reused
    assert len(list((tmp_path / "share").rglob("*.json"))) == 2
    no_partial_files(tmp_path / "share", tmp_path / "state")


def test_an_unsafe_numba_threading_layer_is_refused_at_start(tmp_path: Path) -> None:
    config = write_config(tmp_path)
    svc = ServiceProcess(config, tmp_path, {"NUMBA_THREADING_LAYER": "workqueue"})
    try:
        rc = svc.proc.wait(180)
    finally:
        if svc.proc.poll() is None:
            svc.proc.kill()
    log = svc.log.read_text()
    assert rc == 1, log
    assert "numba threading layer is 'workqueue'" in log and "omp or tbb" in log
    assert "Traceback" not in log


def test_start_deletes_the_compiled_kernels_of_older_versions(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Each upgrade leaves a keyed kernel folder in /var/cache/scan3d; a start keeps the current and one other."""
    import appliance._numba_cache as nc

    root = tmp_path / "cache"
    current = root / f"src-{nc.source_key()}"
    current.mkdir(parents=True)
    olds = [root / f"src-{c * 12}" for c in "123"]
    for k, d in enumerate(olds):
        d.mkdir()
        os.utime(d, (1_000_000 + k, 1_000_000 + k))
    monkeypatch.setattr(nc.config, "CACHE_DIR", str(current))  # only what prune reads: kernels keep their cache

    async def body(svc: D.Service) -> None:
        await scan_once(svc)

    caplog.set_level("INFO")
    rc, _ = run_in_process(write_config(tmp_path), body)
    assert rc == 0
    assert sorted(p.name for p in root.iterdir()) == sorted([current.name, olds[2].name])
    assert "deleted the compiled kernels of 2 older version(s)" in caplog.text
