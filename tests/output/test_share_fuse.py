"""The share writer against a share that really hangs or runs out of room: a FUSE filesystem
(``tests/output/share_hangfs.py``, fusepy on libfuse2) passing through to a real folder, blocking on demand.

Every test unblocks, unmounts (``fusermount -u -z``, else ``umount -l``) and ends the filesystem's process in
its teardown, with timeouts, also when it fails, so no test can hang the suite.
"""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scan_builders import SHAPES, cloud, meta
from share_watch import DirWatch

from appliance.config.schema import OutputConfig
from appliance.output import share as S
from appliance.output.atomic import TMP_PREFIX
from appliance.output.ply import read_ply_vertices

HANGFS = Path(__file__).with_name("share_hangfs.py")
DAY = "2026-01-01"
TIMEOUT_S = 1.0  # output.share_timeout_s in these tests


def _fuse_unavailable() -> str:
    if not os.path.exists("/dev/fuse"):
        return "/dev/fuse is not present on this machine (no FUSE in this kernel or container)"
    try:
        import fuse  # type: ignore[import-untyped]  # noqa: F401
    except ImportError:
        pytest.fail("fusepy is not installed: run scripts/setup-env test (it is in the test extra)")
    except OSError as exc:  # fusepy raises EnvironmentError when libfuse.so.2 is missing
        return f"libfuse2 is not installed ({exc}); scripts/install-system-packages installs it"
    if shutil.which("fusermount") is None and os.geteuid() != 0:
        return "fusermount (Debian package fuse) is missing and this is not root"
    return ""


class HangFs:
    """The running filesystem: ``mnt`` passes through to ``backing``; :meth:`send` controls it."""

    def __init__(self, tmp: Path) -> None:
        self.backing = tmp / "backing"
        self.mnt = tmp / "mnt"
        self.backing.mkdir()
        self.mnt.mkdir()
        self.proc = subprocess.Popen([sys.executable, str(HANGFS), str(self.backing), str(self.mnt)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)

    def _line(self, timeout: float) -> str:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        return self.proc.stdout.readline().strip() if ready else ""

    def wait_ready(self) -> None:
        if self._line(15) != "ready":
            self.proc.kill()
            err = self.proc.stderr.read() if self.proc.stderr is not None else ""
            pytest.fail(f"the FUSE test filesystem did not mount on {self.mnt}: {err.strip()[-400:]}")

    def send(self, cmd: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        assert self._line(10) == "ok", f"the FUSE test filesystem did not take {cmd!r}"

    def teardown(self) -> None:
        try:
            if self.proc.poll() is None and self.proc.stdin is not None:
                self.proc.stdin.write("go\n")
                self.proc.stdin.flush()
                self.proc.stdin.close()
        except OSError:
            pass
        for cmd in (["fusermount", "-u", "-z", str(self.mnt)], ["umount", "-l", str(self.mnt)]):
            if not os.path.ismount(self.mnt):
                break
            try:
                subprocess.run(cmd, timeout=10, capture_output=True, check=False)
            except (OSError, subprocess.TimeoutExpired):
                pass
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()  # closing /dev/fuse aborts the connection: any blocked call returns
            self.proc.wait(5)


def share_op_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "scan3d-share-op" and t.is_alive()]


@pytest.fixture
def hangfs(tmp_path: Path) -> Iterator[HangFs]:
    why = _fuse_unavailable()
    if why:
        pytest.skip(why)
    fs = HangFs(tmp_path)
    try:
        fs.wait_ready()
        yield fs
    finally:
        fs.teardown()
        deadline = time.monotonic() + 10
        while share_op_threads() and time.monotonic() < deadline:  # released: the abandoned ones end
            time.sleep(0.05)
        assert not share_op_threads(), "share operation threads still blocked after the teardown"


def make_writer(fs: HangFs, tmp_path: Path) -> S.ShareWriter:
    return S.ShareWriter(OutputConfig(directory=fs.mnt, spool_directory=tmp_path / "spool", min_free_mb=0,
                                      share_timeout_s=TIMEOUT_S))


def bounded(fn: Callable[[], Any], limit: float) -> tuple[Any, float]:
    """Run ``fn`` in a thread, as the service's writer thread does, and fail when it takes over ``limit`` s.

    The test's own thread never calls into the writer while the share may hang: a call blocked in the kernel
    on a FUSE request cannot be interrupted, and the teardown must still run.
    """
    box: list[tuple[bool, Any]] = []

    def run() -> None:
        try:
            box.append((True, fn()))
        except BaseException as exc:
            box.append((False, exc))

    t = threading.Thread(target=run, name="test-writer", daemon=True)
    t0 = time.monotonic()
    t.start()
    t.join(limit)
    took = time.monotonic() - t0
    if not box:
        pytest.fail(f"the call was still blocked on the share after {limit:g} s")
    ok, value = box[0]
    if not ok:
        raise value
    return value, took


def complete_in(folder: Path, i: int) -> None:
    sid = meta(i).scan_id
    v = read_ply_vertices(folder / f"{sid}.ply")
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], axis=1), cloud(seed=i).xyz)
    assert (folder / f"{sid}.json").is_file() and (folder / f"{sid}.png").is_file()


def wait_until(cond: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_hung_share_spools_within_the_deadline_and_status_answers(hangfs: HangFs, tmp_path: Path) -> None:
    """A hard-mounted share that stops answering: the old writer froze in its first stat for good."""
    w = make_writer(hangfs, tmp_path)
    assert w.write_scan(DAY, meta(1), cloud(seed=1), SHAPES).location == "share"
    hangfs.send("hang")
    out, took = bounded(lambda: w.write_scan(DAY, meta(2), cloud(seed=2), SHAPES), 10 * TIMEOUT_S)
    assert out.location == "spool" and "does not answer" in out.reason
    assert took < 3 * TIMEOUT_S
    # status answers at once from another thread, and says why the share is away
    st, took = bounded(w.status, 5)
    assert took < 0.5 * TIMEOUT_S
    assert not st["available"] and "does not answer" in st["problem"] and st["spooled_scans"] == 1
    # more scans and status calls meanwhile: all spool at once, no second thread piles up on the mount
    for i in (3, 4):
        out, took = bounded(lambda i=i: w.write_scan(DAY, meta(i), cloud(seed=i), SHAPES), 5)
        assert out.location == "spool" and took < 0.5 * TIMEOUT_S
    for _ in range(5):
        assert not bounded(w.status, 5)[0]["available"]
    assert bounded(w.flush_spool, 5)[0] == []
    again = make_writer(hangfs, tmp_path)  # as a reload makes a new writer: it shares the hung share's slot
    assert "does not answer" in bounded(again.share_problem, 5)[0]
    assert len(share_op_threads()) == 1, "at most one outstanding operation per share"
    # the share answers again: the abandoned operation ends, a fresh probe succeeds, the spool moves in order
    hangfs.send("go")
    assert wait_until(lambda: not share_op_threads(), 5)
    assert w.share_problem() == "" and w.status()["available"]
    watch = DirWatch(hangfs.backing / DAY)
    assert [m.scan_id for m in w.flush_spool()] == [meta(i).scan_id for i in (2, 3, 4)]
    assert watch.appeared(".json") == [meta(i).scan_id for i in (2, 3, 4)]
    assert watch.partial_moments() == []
    watch.close()
    for i in (1, 2, 3, 4):
        complete_in(hangfs.backing / DAY, i)
    assert w.spool_entries() == []


def test_status_does_not_wait_for_a_probe_on_a_hung_share(hangfs: HangFs, tmp_path: Path) -> None:
    w = make_writer(hangfs, tmp_path)
    assert w.status()["available"]
    hangfs.send("hang")
    st, took = bounded(w.status, 5)  # its probe hangs: it answers from the last one after S.STATUS_WAIT_S
    assert took < S.STATUS_WAIT_S + 0.5
    assert st["available"]  # not yet known to be away
    time.sleep(TIMEOUT_S + 0.1)
    st, took = bounded(w.status, 5)
    assert took < 0.3 and not st["available"] and "does not answer" in st["problem"]
    assert len(share_op_threads()) == 1


def fds_into(folder: Path) -> list[str]:
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(folder)):
            out.append(target)
    return out


def test_share_hanging_mid_write_is_abandoned_then_cleaned(hangfs: HangFs, tmp_path: Path) -> None:
    """The share stops answering while the cloud is being written: the scan spools within the deadline, the
    half-written temporary file goes once the share answers, the scan arrives complete."""
    w = make_writer(hangfs, tmp_path)
    (hangfs.mnt / DAY).mkdir()
    hangfs.send("hang write")
    out, took = bounded(lambda: w.write_scan(DAY, meta(1), cloud(seed=1), SHAPES), 10 * TIMEOUT_S)
    assert out.location == "spool" and "writing" in out.reason and took < 3 * TIMEOUT_S
    assert any(p.name.startswith(TMP_PREFIX) for p in (hangfs.backing / DAY).iterdir())  # it was mid-write
    hangfs.send("go")
    assert wait_until(lambda: not share_op_threads(), 5)
    assert [m.scan_id for m in w.flush_spool()] == [meta(1).scan_id]
    names = sorted(p.name for p in (hangfs.backing / DAY).iterdir())
    assert names == [f"{meta(1).scan_id}{s}" for s in (".json", ".ply", ".png")]
    complete_in(hangfs.backing / DAY, 1)
    assert fds_into(hangfs.mnt) == []  # the file the abandoned write held is closed


def test_share_out_of_inodes_mid_scan_leaves_nothing_partial_and_is_not_available(
    hangfs: HangFs, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The share's quota allows two more files (its statfs does not show it): the third of the scan fails.
    The old writer left the share 'available'; nothing of the scan may stay visible without its .json."""
    w = make_writer(hangfs, tmp_path)
    (hangfs.mnt / DAY).mkdir()
    watch = DirWatch(hangfs.backing / DAY)
    hangfs.send("quota 2")
    out = w.write_scan(DAY, meta(1), cloud(seed=1), SHAPES)
    assert out.location == "spool" and "No space left" in out.reason
    assert watch.partial_moments() == []
    assert sorted(p.name for p in (hangfs.backing / DAY).iterdir()) == []
    st = w.status()
    assert not st["available"] and "No space left" in st["problem"]
    assert w.write_scan(DAY, meta(2), cloud(seed=2), SHAPES).location == "spool"  # behind the first one
    hangfs.send("quota -1")
    monkeypatch.setattr(S, "FAILURE_HOLD_S", 0.0)  # the hold after a failure is over
    assert [m.scan_id for m in w.flush_spool()] == [meta(1).scan_id, meta(2).scan_id]
    assert watch.partial_moments() == []
    watch.close()
    complete_in(hangfs.backing / DAY, 1)
    complete_in(hangfs.backing / DAY, 2)


def test_teardown_releases_a_writer_still_blocked(hangfs: HangFs, tmp_path: Path) -> None:
    """The fixture's own promise: a thread left blocked in the kernel on the hung mount is released (the
    fixture asserts that no share thread is left after its teardown)."""
    w = make_writer(hangfs, tmp_path)
    hangfs.send("hang")
    assert "does not answer" in bounded(w.share_problem, 5)[0]
    assert len(share_op_threads()) == 1
