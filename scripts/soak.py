"""Chaos soak of ``scan3d run`` on the virtual rig (a benchmark-like tool, not a unit test).

The service runs as a subprocess (what systemd runs) with everything under a temporary folder. A driver
triggers scans through the control socket while a fault injector, in random order, reloads configurations
that change the rig with a trigger right behind on the same connection, removes and restores the share,
makes it full, hangs it, writes empty and binary configurations, sends garbage to the control socket, kills
the camera mid-scan (it stops delivering frames), and SIGKILLs and restarts the service. Meanwhile a watcher
samples the share for partial scans and a pinger measures how long the service goes without answering
``status``.

The share is a FUSE filesystem (``tests/output/share_hangfs.py``, passing through to a real folder) where FUSE is
available (root or fusermount, /dev/fuse, fusepy and libfuse2): the ``share_hang`` fault makes every operation
on it block, as a hard-mounted NFS/SMB share whose server stopped answering does, while scans are triggered,
then lets them go. Without FUSE (``--no-fuse``, or when it is missing) the share is a plain folder and that
fault is left out (said in the ledger's ``share``). The watcher and the final check read the backing folder,
which is what the share shows, so they never block on a hung share themselves.

The ledger at the end: every scan reported successful is on the share exactly once and complete (PLY read
back, point count as in its sidecar); every failed one was reported with a reason; nothing partial was ever
seen; no silent hang (> :data:`MAX_GAP_S` without an answer outside a restart); RSS at the start and the end.

    scripts/soak [--scans 500] [--seed 1] [--rig small|default] [--no-fuse] [--json] [--keep DIR]

Exit status 0 when the ledger is clean, 1 otherwise.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from appliance.errors import ApplianceError  # noqa: E402
from appliance.output.atomic import TMP_PREFIX  # noqa: E402
from appliance.service.control import request  # noqa: E402

MAX_GAP_S = 10.0  # the service must answer status within this, outside a restart
PING_S = 0.5
WATCH_S = 0.05
SCAN_WAIT_S = 120.0
SHARE_TIMEOUT_S = 1.0  # output.share_timeout_s of the soak's service: a hung share counts as away after this
HANGFS = REPO / "tests" / "output" / "share_hangfs.py"

SMALL_RIG = {
    "projector": {"width": 320, "height": 200, "focal_px": 400, "principal_px": [160, 190],
                  "position_mm": [175, 0, 0], "look_at_mm": [0, 40, 580]},
    "cameras": {"cam0": {"width": 320, "height": 256, "focal_px": 450, "position_mm": [0, 0, 0],
                         "look_at_mm": [0, 0, 580]}},
}

# fault -> relative weight (a plain scan has weight SCAN_WEIGHT)
FAULTS = {"reload_rig_then_trigger": 3, "share_away": 2, "share_full": 2, "share_hang": 2, "bad_config": 2,
          "garbage": 2, "camera_dies": 1, "sigkill": 2}
SCAN_WEIGHT = 14


def base_config(tmp: Path, rig: str) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "serial": "SOAK-1",
        "cameras": {"cam0": {"type": "sim"}},
        "output": {"directory": str(tmp / "share"), "spool_directory": str(tmp / "spool"), "min_free_mb": 0,
                   "share_timeout_s": SHARE_TIMEOUT_S},
        "service": {"control_socket": str(tmp / "sock"), "state_directory": str(tmp / "state"),
                    "config_poll_s": 0.2, "scan_timeout_s": 4.0, "stop_grace_s": 5.0,
                    "mdns": {"enabled": False}},
    }
    if rig == "small":
        doc["virtual_rig"] = SMALL_RIG
        doc["reconstruction"] = {"min_depth_mm": 300, "max_depth_mm": 900}
    return doc


def fuse_unavailable() -> str:
    """Why the share cannot be a FUSE filesystem here ('' when it can)."""
    if not os.path.exists("/dev/fuse"):
        return "/dev/fuse is not present (no FUSE in this kernel or container)"
    try:
        import fuse  # type: ignore[import-untyped]  # noqa: F401
    except ImportError:
        return "fusepy is not installed (scripts/setup-env test installs it)"
    except OSError as exc:  # fusepy raises EnvironmentError when libfuse.so.2 is missing
        return f"libfuse2 is not installed ({exc}); scripts/install-system-packages installs it"
    if shutil.which("fusermount") is None and os.geteuid() != 0:
        return "fusermount (Debian package fuse) is missing and this is not root"
    return ""


class HangShare:
    """The share as a FUSE filesystem: ``mnt`` passes through to ``backing``; :meth:`send` hangs or frees it."""

    def __init__(self, backing: Path, mnt: Path) -> None:
        self.backing, self.mnt = backing, mnt
        backing.mkdir(parents=True, exist_ok=True)
        mnt.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen([sys.executable, str(HANGFS), str(backing), str(mnt)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if self._line(15) != "ready":
            self.close()
            raise RuntimeError(f"the FUSE share did not mount on {mnt}")

    def _line(self, timeout: float) -> str:
        import select

        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        return self.proc.stdout.readline().strip() if ready else ""

    def send(self, cmd: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        if self._line(10) != "ok":
            raise RuntimeError(f"the FUSE share did not take {cmd!r}")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            if self.proc.poll() is None and self.proc.stdin is not None:
                self.proc.stdin.write("go\n")
                self.proc.stdin.flush()
                self.proc.stdin.close()
        for cmd in (["fusermount", "-u", "-z", str(self.mnt)], ["umount", "-l", str(self.mnt)]):
            if not os.path.ismount(self.mnt):
                break
            with contextlib.suppress(OSError, subprocess.TimeoutExpired):
                subprocess.run(cmd, timeout=10, capture_output=True, check=False)
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()  # closing /dev/fuse aborts the connection: any blocked call returns
            self.proc.wait(5)


class Soak:
    """One soak run: the service, the driver, the faults, the watcher, the pinger and the ledger."""

    def __init__(self, tmp: Path, seed: int, rig: str, scans: int, fuse: bool = True) -> None:
        self.tmp = tmp
        self.rng = random.Random(seed)
        self.scans_wanted = scans
        self.share = tmp / "share"  # what the service writes to
        self.fuse_why = fuse_unavailable() if fuse else "--no-fuse"
        self.hangfs: HangShare | None = None
        # the folder the share shows: the FUSE filesystem's backing folder, or the share itself
        self.files = tmp / "share-backing" if not self.fuse_why else self.share
        self.away = tmp / "share-away"
        self.sock = tmp / "sock"
        self.config = tmp / "appliance.yaml"
        self.good = base_config(tmp, rig)
        self.rig_variant = 0
        self.share.mkdir(parents=True, exist_ok=True)
        if not self.fuse_why:
            self.hangfs = HangShare(self.files, self.share)
        self.write_config(self.good)
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = (tmp / "service.log").open("ab")
        self.ok: dict[str, dict[str, Any]] = {}  # scan id -> reply's scan record
        self.failed: list[dict[str, Any]] = []  # replies of failed / refused triggers
        self.unanswered = 0  # triggers whose reply was lost to a SIGKILL
        self.faults: collections.Counter[str] = collections.Counter()
        self.partial: list[str] = []
        self.watcher_error = ""
        self.attempts = 0
        self.restarting = threading.Event()
        self.worst_gap_s = 0.0
        self.rss_mb: list[float] = []
        self.exit_codes: list[int] = []
        self.driver_errors: list[str] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()

    # --- the service -----------------------------------------------------------------------------------

    def write_config(self, doc: dict[str, Any]) -> None:
        tmp = self.config.with_suffix(".new")
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
        os.replace(tmp, self.config)

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "appliance", "run", "--config", str(self.config)],
            cwd=REPO, stdout=self.log, stderr=subprocess.STDOUT,
            env={**os.environ, "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))},
        )
        end = time.monotonic() + 180
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the service exited with {self.proc.returncode} at start; see {self.log.name}")
            st = self.status(2.0)
            if st.get("state") == "idle":
                return
            time.sleep(0.1)
        raise RuntimeError("the service did not become ready within 180 s")

    def status(self, timeout_s: float) -> dict[str, Any]:
        try:
            return request(self.sock, {"cmd": "status"}, timeout_s).get("status", {})  # type: ignore[no-any-return]
        except (ApplianceError, OSError):
            return {}

    def rss(self) -> float:
        st = self.status(5.0)
        return float(st.get("rss_mb", 0.0))

    def kill_and_restart(self) -> None:
        assert self.proc is not None
        self.restarting.set()
        try:
            self.proc.send_signal(signal.SIGKILL)
            self.exit_codes.append(self.proc.wait(30))
            self.start()
        finally:
            self.restarting.clear()

    # --- the driver ------------------------------------------------------------------------------------

    def record(self, reply: dict[str, Any]) -> None:
        with self._lock:
            if reply.get("ok") and reply.get("scan"):
                self.ok[reply["scan"]["scan_id"]] = reply["scan"]
            else:
                self.failed.append(reply)

    def trigger(self) -> None:
        self.attempts += 1
        try:
            reply = request(self.sock, {"cmd": "trigger", "wait": True}, SCAN_WAIT_S)
        except (ApplianceError, OSError) as exc:
            raise RuntimeError(f"trigger got no answer: {exc}") from exc
        self.record(reply)

    def lines(self, *reqs: dict[str, Any], timeout_s: float = SCAN_WAIT_S) -> list[dict[str, Any]]:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(timeout_s)
            s.connect(str(self.sock))
            s.sendall(b"".join(json.dumps(r).encode() + b"\n" for r in reqs))
            f = s.makefile("rb")
            return [json.loads(f.readline()) for _ in reqs]

    def wait_config(self, serial: str | None = None, rejected_more_than: int | None = None) -> None:
        end = time.monotonic() + 30
        while time.monotonic() < end:
            st = self.status(5.0)
            if serial is not None and st.get("serial") == serial and st.get("state") == "idle":
                return
            rejected = st.get("counters", {}).get("reloads_rejected", 0)
            if rejected_more_than is not None and rejected > rejected_more_than:
                return
            time.sleep(0.05)
        raise RuntimeError("the service did not take the configuration within 30 s")

    def wait_idle(self) -> None:
        end = time.monotonic() + 60
        while time.monotonic() < end:
            if self.status(5.0).get("state") == "idle":
                return
            time.sleep(0.05)
        raise RuntimeError("the service did not return to idle within 60 s")

    # --- faults ----------------------------------------------------------------------------------------

    def fault_reload_rig_then_trigger(self) -> None:
        self.rig_variant ^= 1
        doc = json.loads(json.dumps(self.good))
        rc = doc.setdefault("reconstruction", {})
        rc["min_depth_mm"] = rc.get("min_depth_mm", 300) + (5 if self.rig_variant else 0)
        self.good = doc
        self.write_config(doc)
        self.attempts += 1
        reload_reply, trig_reply = self.lines({"cmd": "reload"}, {"cmd": "trigger", "wait": True})
        if not reload_reply.get("ok"):
            raise RuntimeError(f"reload of a valid configuration failed: {reload_reply}")
        self.record(trig_reply)
        self.wait_idle()

    def fault_share_away(self) -> None:
        self.files.rename(self.away)  # on FUSE: every path on the mount answers ENOENT, as an unmounted share
        try:
            for _ in range(self.rng.randint(1, 3)):
                self.trigger()
        finally:
            self.away.rename(self.files)

    def fault_share_hang(self) -> None:
        assert self.hangfs is not None
        self.hangfs.send("hang")  # every operation on the share blocks from now on
        try:
            for _ in range(self.rng.randint(1, 2)):
                self.trigger()  # answered within the deadline: the scan spools
            time.sleep(self.rng.uniform(0.0, 2.0 * SHARE_TIMEOUT_S))
        finally:
            self.hangfs.send("go")

    def fault_share_full(self) -> None:
        doc = json.loads(json.dumps(self.good))
        doc["output"]["min_free_mb"] = 10_000_000  # more than any disk has: the share counts as full
        doc["serial"] = "SOAK-FULL"
        self.write_config(doc)
        self.wait_config(serial="SOAK-FULL")
        try:
            self.trigger()
        finally:
            self.write_config(self.good)
            self.wait_config(serial=self.good["serial"])

    def fault_bad_config(self) -> None:
        before = self.status(5.0).get("counters", {}).get("reloads_rejected", 0)
        self.config.write_bytes(self.rng.choice([b"", b"\x00\x01binary\xff\xfe", b"serial: caf\xe9\n", b"- a\n"]))
        self.wait_config(rejected_more_than=before)
        self.trigger()  # the last good configuration keeps scanning
        self.write_config(self.good)
        self.wait_config(serial=self.good["serial"])

    def fault_garbage(self) -> None:
        junk = [bytes(self.rng.getrandbits(8) for _ in range(self.rng.randint(1, 200))) + b"\n",
                b"[" * 20000 + b"]" * 20000 + b"\n", b"{" + b" " * 70000 + b"}\n", b'{"cmd": 5}\n',
                b'{"cmd": "format-disk"}\n', b"\xff\xfe\n"]
        for data in self.rng.sample(junk, 3):
            with contextlib.suppress(OSError), socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(10)
                s.connect(str(self.sock))
                s.sendall(data)
                with contextlib.suppress(TimeoutError):
                    s.recv(65536)  # an error reply (or a closed connection), never a hang
        if not self.status(MAX_GAP_S):
            raise RuntimeError("the service stopped answering after garbage on its control socket")

    def fault_camera_dies(self) -> None:
        doc = json.loads(json.dumps(self.good))
        doc["cameras"]["cam0"]["fail_after_frames"] = self.rng.randint(0, 6)
        doc["serial"] = "SOAK-CAM"
        self.write_config(doc)
        self.wait_config(serial="SOAK-CAM")
        try:
            self.trigger()  # fails (no frames): reported with its reason
        finally:
            self.write_config(self.good)
            self.wait_config(serial=self.good["serial"])

    def fault_sigkill(self) -> None:
        self.attempts += 1
        waiter: list[Any] = []

        def wait_reply() -> None:
            try:
                waiter.append(request(self.sock, {"cmd": "trigger", "wait": True}, SCAN_WAIT_S))
            except (ApplianceError, OSError) as exc:
                waiter.append(exc)

        t = threading.Thread(target=wait_reply)
        t.start()
        time.sleep(self.rng.uniform(0.0, 0.3))
        self.kill_and_restart()
        t.join(30)
        if waiter and isinstance(waiter[0], dict):
            self.record(waiter[0])  # it finished before the kill
        else:
            self.unanswered += 1

    # --- watcher and pinger ----------------------------------------------------------------------------

    def watch_share(self) -> None:
        try:
            self._watch_share()
        except BaseException as exc:  # the ledger must not pass without its watcher
            self.watcher_error = f"{type(exc).__name__}: {exc}"
            raise

    def _watch_share(self) -> None:
        while not self._stop.is_set():
            try:
                sides = list(self.files.glob("*/*.json"))
            except FileNotFoundError:
                sides = []  # the share, or a day folder, went away while being listed: look again
            for side in sides:
                if side.name.startswith("."):
                    continue
                try:
                    meta = json.loads(side.read_text())
                except FileNotFoundError:
                    continue  # moved away with the share
                except (OSError, ValueError) as exc:
                    self.partial.append(f"{side}: unreadable sidecar ({exc})")
                    continue
                for name in meta.get("files", {}).values():
                    f = side.parent / name
                    try:
                        if f.stat().st_size == 0:
                            self.partial.append(f"{f}: empty while its sidecar is visible")
                    except FileNotFoundError:
                        if side.exists():
                            self.partial.append(f"{f}: missing while its sidecar is visible")
            self._stop.wait(WATCH_S)

    def ping(self) -> None:
        last = time.monotonic()  # the last answer (or the end of a restart)
        while not self._stop.is_set():
            ok = bool(self.status(MAX_GAP_S + 1))
            now = time.monotonic()
            if self.restarting.is_set():
                last = now
            else:
                self.worst_gap_s = max(self.worst_gap_s, now - last - PING_S)
                if ok:
                    last = now
            self._stop.wait(PING_S)

    # --- run and check ---------------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        self.start()
        threads = [threading.Thread(target=self.watch_share, name="soak-watch", daemon=True),
                   threading.Thread(target=self.ping, name="soak-ping", daemon=True)]
        for t in threads:
            t.start()
        names = [n for n in FAULTS if n != "share_hang" or self.hangfs is not None]
        weights = [FAULTS[n] for n in names] + [SCAN_WEIGHT]
        t0 = time.monotonic()
        first = self.rng.sample(names, len(names))  # every fault once, in random order, then at random
        try:
            while self.attempts < self.scans_wanted:
                if first and self.attempts % 2:
                    action = first.pop()
                else:
                    action = self.rng.choices([*names, "scan"], weights)[0]
                try:
                    if action == "scan":
                        self.trigger()
                    else:
                        self.faults[action] += 1
                        getattr(self, f"fault_{action}")()
                except (RuntimeError, OSError, ValueError) as exc:  # the service misbehaved: stop, report
                    self.driver_errors.append(f"{action}: {exc}")
                    break
                if len(self.rss_mb) == 0 and len(self.ok) >= 10:
                    self.rss_mb.append(self.rss())
            self.write_config(self.good)
            end = time.monotonic() + 120
            while time.monotonic() < end and self.status(5.0).get("share", {}).get("spooled_scans", 1) != 0:
                time.sleep(0.2)
            self.rss_mb.append(self.rss())
        finally:
            self._stop.set()
            for t in threads:
                t.join(15)
            if self.proc is not None and self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.exit_codes.append(self.proc.wait(60))
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.exit_codes.append(-9)
            if self.hangfs is not None:
                self.hangfs.close()
        return self.check(time.monotonic() - t0)

    def check(self, seconds: float) -> dict[str, Any]:
        from appliance.output.ply import read_ply_vertices

        sidecars: collections.Counter[str] = collections.Counter()
        problems: list[str] = []
        for side in self.files.glob("*/*.json"):
            sidecars[side.stem] += 1
        duplicated = [s for s, n in sidecars.items() if n > 1]
        lost, incomplete = [], []
        for scan_id in self.ok:
            found = list(self.files.glob(f"*/{scan_id}.json"))
            if not found:
                lost.append(scan_id)
                continue
            meta = json.loads(found[0].read_text())
            try:
                n = len(read_ply_vertices(found[0].parent / meta["files"]["cloud"]))
            except Exception as exc:  # any reading problem is an incomplete scan
                incomplete.append(f"{scan_id}: {exc}")
                continue
            if n != meta["counts"]["points"]:
                incomplete.append(f"{scan_id}: {n} points in the PLY, {meta['counts']['points']} in the sidecar")
        no_reason = [r for r in self.failed if not str(r.get("error", "")).strip()]
        leftovers = [str(p) for p in self.files.rglob(f"{TMP_PREFIX}*")]
        bad_exit = [c for c in self.exit_codes[-1:] if c != 0]
        problems.extend(f"driver: {e}" for e in self.driver_errors)
        if lost:
            problems.append(f"{len(lost)} successful scan(s) not on the share: {lost[:5]}")
        if duplicated:
            problems.append(f"{len(duplicated)} scan(s) on the share more than once: {duplicated[:5]}")
        if incomplete:
            problems.append(f"{len(incomplete)} incomplete: {incomplete[:5]}")
        if self.partial:
            problems.append(f"{len(self.partial)} partial file sightings: {self.partial[:5]}")
        if self.watcher_error:
            problems.append(f"the share watcher stopped: {self.watcher_error}")
        if no_reason:
            problems.append(f"{len(no_reason)} failed trigger(s) without a reason: {no_reason[:3]}")
        if leftovers:
            problems.append(f"temporary files left on the share: {leftovers[:5]}")
        if self.worst_gap_s > MAX_GAP_S:
            problems.append(f"unresponsive for {self.worst_gap_s:.1f} s outside a restart")
        if bad_exit:
            problems.append(f"the last service exited with {bad_exit[0]} on SIGTERM")
        reasons = collections.Counter(" ".join(str(r.get("error", "")).split()[:6]) for r in self.failed)
        return {
            "scans_attempted": self.attempts, "scans_ok": len(self.ok), "scans_failed_with_reason": len(self.failed),
            "unanswered_by_sigkill": self.unanswered, "unreported_on_share": len(set(sidecars) - set(self.ok)),
            "lost": len(lost), "duplicated": len(duplicated), "incomplete": len(incomplete),
            "partial_seen": len(self.partial), "worst_unresponsive_s": round(self.worst_gap_s, 2),
            "faults": dict(sorted(self.faults.items())), "failure_results": dict(reasons.most_common(8)),
            "rss_mb_start_end": self.rss_mb, "seconds": round(seconds, 1), "problems": problems,
            "share": "FUSE (hangs on demand)" if self.hangfs is not None else f"plain folder ({self.fuse_why})",
        }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", type=int, default=500, help="triggers to send (faults included)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rig", choices=["small", "default"], default="small",
                    help="small: a 320x256 camera (fast); default: the shipped 1280x1024 virtual rig")
    ap.add_argument("--no-fuse", action="store_true", help="a plain folder as the share (no share_hang fault)")
    ap.add_argument("--json", action="store_true", help="print the ledger as JSON")
    ap.add_argument("--keep", type=Path, default=None, help="run in this folder and keep it (default: a temp one)")
    a = ap.parse_args(argv)
    tmp = a.keep or Path(tempfile.mkdtemp(prefix="scan3d-soak-"))
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        ledger = Soak(tmp, a.seed, a.rig, a.scans, fuse=not a.no_fuse).run()
    finally:
        if a.keep is None:
            shutil.rmtree(tmp, ignore_errors=True)
    if a.json:
        print(json.dumps(ledger, indent=2))
    else:
        print(f"soak: {ledger['scans_attempted']} triggers, {ledger['scans_ok']} scans ok, "
              f"{ledger['scans_failed_with_reason']} failed with a reason, {ledger['unanswered_by_sigkill']} lost "
              f"to SIGKILL; lost {ledger['lost']}, duplicated {ledger['duplicated']}, partial seen "
              f"{ledger['partial_seen']}; worst unresponsive {ledger['worst_unresponsive_s']} s; RSS "
              f"{ledger['rss_mb_start_end']} MB; faults {ledger['faults']}; share {ledger['share']}; "
              f"{ledger['seconds']} s")
        for p in ledger["problems"]:
            print(f"  PROBLEM: {p}")
    return 0 if not ledger["problems"] else 1


if __name__ == "__main__":
    sys.exit(main())
