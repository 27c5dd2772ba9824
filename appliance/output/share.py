"""The share writer: scan files into ``output.directory/YYYY-MM-DD/``, or a local spool while it is away.

The share's layout is ``YYYY-MM-DD/<scan-id>.ply``, ``.png`` and ``.json``. **The sidecar (``.json``) is the
completion marker**: each file is written under a hidden temporary name (``.tmp-<scan-id>...``), fsynced and
renamed; the cloud and the preview are renamed first, the folder fsynced, then the sidecar is renamed and
the folder fsynced again. A scan whose ``.json`` is visible is complete; a ``.ply``/``.png`` without its
``.json`` is a write in progress or one that failed, and the writer removes it (after a failed write at once,
after a crash at the next start, after a hang as soon as the share answers again: every write is first noted
in a small journal in the spool folder, ``.share-inflight.json``).

**Deadlines.** Every operation on the share (the probe: stat, access, statvfs; creating a file, each write of
up to 4 MB, fsync, close, rename, listing, unlink, mkdir) runs in a worker thread of its own and is waited for
at most ``output.share_timeout_s``. An operation past its deadline is abandoned (its daemon thread may stay
blocked in the kernel on a hung mount) and the share counts as away: no new operation is started while the
abandoned one still runs (at most one outstanding operation per share), and the share is back only when a
fresh probe after it succeeds. A failed operation (ENOSPC, EDQUOT, EIO, ...) counts the share as away for
:data:`FAILURE_HOLD_S`. The spool is local and used directly.

**Spool.** When the share is missing, not a mount point (``output.require_mount``), full, slow or failing,
the scan goes to ``output.spool_directory``: one folder per scan (``NNNNNNNN-<scan-id>``, written as
``.tmp-...`` and renamed into place when complete, with ``entry.json`` naming each file's size and SHA-256),
moved over oldest first once the share is back; spooled scans are moved before any newer one is written, so
the share sees scans in order. A move is idempotent (a file already on the share with the same size and
checksum counts as moved), and an entry that cannot be moved for its own fault (unreadable ``entry.json``,
a file missing or changed) goes to ``spool/quarantine/`` with one log line instead of blocking the queue.

The writer is meant for one writer thread; :meth:`ShareWriter.status` may be called from any other thread at
the same time and never waits for the share (it reports the last probe while an operation is running).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from appliance.config.schema import OutputConfig
from appliance.errors import OutputError
from appliance.output.atomic import TMP_PREFIX, fsync_dir, mkdir_synced, write_bytes_atomic
from appliance.output.scanfiles import FileContent, scan_file_contents
from appliance.output.sidecar import ScanMetadata
from appliance.output.spool import (
    DAY,
    ENTRY_FILE,
    Spool,
    SpoolEntryBroken,
    SpoolFile,
    dir_bytes,
)
from appliance.reconstruct.types import PointCloud

log = logging.getLogger(__name__)

# Module-level so tests can fake a full disk: path -> os.statvfs_result-like (f_bavail, f_frsize).
STATVFS: Callable[[str], Any] = os.statvfs

JOURNAL_FILE = ".share-inflight.json"
MB = 1024 * 1024
CHUNK = 4 * MB  # one write to the share, one deadline
FAILURE_HOLD_S = 30.0  # after a failed operation the share counts as away this long (s)
MIN_FREE_INODES = 16  # fewer free inodes than this on the share (where it counts them): full
STALE_TMP_S = 3600.0  # at start, temporary files this old in the newest day folders are removed (s)
STATUS_WAIT_S = 0.5  # status waits this long for a probe, then answers from the last one (s)

T = TypeVar("T")


class ShareUnavailable(OutputError):
    """The share did not answer within ``output.share_timeout_s`` or an operation on it failed."""


class _GateBusy(Exception):
    """The share's one operation slot is taken (only for callers that do not wait)."""


@dataclass
class WriteOutcome:
    """Where the files of one scan went."""

    scan_id: str
    location: str  # "share" or "spool"
    files: list[Path] = field(default_factory=list)
    reason: str = ""  # why the share was not used


def estimate_scan_bytes(shapes: list[tuple[int, int]], *, normals: bool, preview: bool) -> int:
    """An upper bound of the bytes one scan writes (every pixel a point), for the disk-space guard.

    Parameters
    ----------
    shapes : list of (int, int)
        (H, W) of each camera (px).
    normals, preview : bool
        Whether the PLY has normals and a preview PNG is written.
    """
    pixels = sum(h * w for h, w in shapes)
    record = 12 + (12 if normals else 0) + 4 + 1 + 1 + 4
    total = pixels * record + 4096 + 8192
    if preview:
        total += pixels * 3 + 200_000
    return total


def free_bytes(path: Path) -> int:
    """Bytes available to this user on the filesystem of ``path`` (via :data:`STATVFS`)."""
    st = STATVFS(str(path))
    return int(st.f_bavail) * int(st.f_frsize)


def _write_all(fd: int, data: memoryview) -> None:
    while data:
        n = os.write(fd, data)
        data = data[n:]


class ShareGate:
    """Runs operations on one share, each in a daemon thread with a deadline, at most one at a time.

    An operation runs in a thread of its own; the caller waits for it at most ``timeout_s``. One still running
    past its deadline is abandoned: it keeps the share's one operation slot, so no second thread piles up on a
    hung mount, and every caller meanwhile gets :class:`ShareUnavailable` at once. When it ends, the slot is
    free again.

    Parameters
    ----------
    name : str
        The share (for messages).
    timeout_s : float
        Deadline of one operation (s).
    """

    def __init__(self, name: str, timeout_s: float) -> None:
        self.name = name
        self.timeout_s = timeout_s
        self._cond = threading.Condition()
        self._running: tuple[str, float] | None = None  # the operation in the slot and its start (monotonic)

    def _hung_locked(self, now: float) -> str:
        if self._running is None or now - self._running[1] <= self.timeout_s:
            return ""
        what, since = self._running
        return (f"share {self.name} does not answer: {what} has been waiting {now - since:.0f} s, longer than "
                f"output.share_timeout_s = {self.timeout_s:g} s (a hung network mount?); scans are spooled "
                "until it answers again")

    def busy(self) -> bool:
        """Whether an operation is running (within its deadline or past it)."""
        with self._cond:
            return self._running is not None

    def call(self, what: str, fn: Callable[[], T], *, wait_slot: bool = True, wait_s: float | None = None) -> T:
        """Run ``fn()`` in a worker thread and wait for it at most ``timeout_s``.

        Parameters
        ----------
        what : str
            The operation, for messages (``"fsync x.ply"``).
        fn : callable
            The operation; its exceptions are raised here.
        wait_slot : bool
            Wait while another caller's operation runs (within its deadline); False: raise
            :class:`_GateBusy` at once.
        wait_s : float, optional
            Wait this long (< ``timeout_s``) and raise :class:`_GateBusy` when the operation is still running
            then; it goes on (with its deadline) and reports through ``fn`` itself.

        Raises
        ------
        ShareUnavailable
            Past the deadline (the operation is abandoned), or an earlier one is still running past its own.
        """
        with self._cond:
            t0 = time.monotonic()
            while self._running is not None:
                now = time.monotonic()
                hung = self._hung_locked(now)
                if hung:
                    raise ShareUnavailable(hung)
                if not wait_slot:
                    raise _GateBusy
                left = min(t0 + self.timeout_s, self._running[1] + self.timeout_s) - now
                if left <= 0:
                    raise ShareUnavailable(f"share {self.name}: no operation finished within "
                                           f"output.share_timeout_s = {self.timeout_s:g} s")
                self._cond.wait(left + 0.01)
            self._running = (what, time.monotonic())
        box: list[tuple[bool, Any]] = []
        done = threading.Event()

        def run() -> None:
            try:
                box.append((True, fn()))
            except BaseException as exc:  # handed to the caller
                box.append((False, exc))
            finally:
                with self._cond:
                    self._running = None
                    self._cond.notify_all()
                done.set()

        threading.Thread(target=run, name="scan3d-share-op", daemon=True).start()
        if wait_s is not None and wait_s < self.timeout_s and not done.wait(wait_s):
            raise _GateBusy
        if not done.wait(self.timeout_s if wait_s is None else self.timeout_s - wait_s):
            log.warning("share %s: %s took longer than output.share_timeout_s = %g s; abandoned, the share "
                        "counts as away until it answers again", self.name, what, self.timeout_s)
            raise ShareUnavailable(
                f"share {self.name} does not answer: {what} took longer than output.share_timeout_s = "
                f"{self.timeout_s:g} s (a hung network mount?); scans are spooled until it answers again")
        ok, value = box[0]
        if ok:
            return value  # type: ignore[no-any-return]
        raise value


_GATES: dict[str, ShareGate] = {}
_GATES_LOCK = threading.Lock()


def gate_for(directory: Path, timeout_s: float) -> ShareGate:
    """The one :class:`ShareGate` of a share in this process (a writer made anew on a reload shares it, so an
    operation hung on the old one still keeps every other off the mount)."""
    key = os.path.abspath(directory)
    with _GATES_LOCK:
        gate = _GATES.get(key)
        if gate is None:
            gate = _GATES[key] = ShareGate(str(directory), timeout_s)
        gate.timeout_s = timeout_s
        return gate


def _unlink_if_there(path: Path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


class ShareWriter:
    """Writes scans to the share or the spool, moves the spool over, applies retention.

    Parameters
    ----------
    cfg : OutputConfig
        ``directory`` (the share), ``spool_directory``, ``spool_max_mb``, ``spool_max_age_days``,
        ``min_free_mb``, ``require_mount``, ``share_timeout_s``.
    """

    def __init__(self, cfg: OutputConfig) -> None:
        self.cfg = cfg
        self.directory = Path(cfg.directory)
        self.spool = Spool(Path(cfg.spool_directory), cfg, lambda path: free_bytes(path))
        self.last_reason = ""
        self.gate = gate_for(self.directory, cfg.share_timeout_s)
        self.delivered: deque[str] = deque(maxlen=10_000)  # scan ids, in the order their sidecars appeared
        self._state = threading.Lock()
        self._failure: tuple[str, float] | None = None
        self._last_problem = ""
        self._last_free: int | None = None
        self._orphan_fds: list[int] = []

    # --- share: probe and state ------------------------------------------------------------------

    def _op(self, what: str, fn: Callable[[], T]) -> T:
        """One operation on the share under the deadline; an OSError counts the share as away."""
        try:
            return self.gate.call(what, fn)
        except OSError as exc:
            reason = f"share {self.directory}: {what} failed ({exc.strerror or exc})"
            with self._state:
                self._failure = (reason, time.monotonic())
                self._last_problem = reason
            raise ShareUnavailable(f"{reason}; free space or inodes on the share, or check it") from exc

    def _probe(self, need_bytes: int) -> str:
        """The probe (in the worker): present, a mount point where required, writable, free space, inodes."""
        d = self.directory
        free: int | None = None
        if not d.is_dir():
            problem = f"share {d} is not there (not mounted, removed or renamed)"
        elif self.cfg.require_mount and not os.path.ismount(d):
            problem = f"share {d} is not a mount point (output.require_mount is set)"
        elif not os.access(d, os.W_OK):
            problem = f"share {d} is not writable"
        else:
            try:
                st = STATVFS(str(d))
                free = int(st.f_bavail) * int(st.f_frsize)
                files, favail = int(getattr(st, "f_files", 0)), int(getattr(st, "f_favail", MIN_FREE_INODES))
                if free < need_bytes + self.cfg.min_free_mb * MB:
                    problem = (f"share {d} is full: {free / MB:.0f} MB free, a scan needs up to "
                               f"{need_bytes / MB:.0f} MB and output.min_free_mb = {self.cfg.min_free_mb:g} MB "
                               "must stay free")
                elif files > 0 and favail < MIN_FREE_INODES:
                    problem = (f"share {d} is out of inodes: {favail} free, at least {MIN_FREE_INODES} needed; "
                               "remove old scans or files from it")
                else:
                    problem = ""
            except OSError as exc:
                problem = f"share {d}: cannot read its free space ({exc.strerror})"
        with self._state:
            self._last_problem, self._last_free = problem, free
            if not problem:
                self._failure = None
        return problem

    def share_problem(self, need_bytes: int = 0, *, wait: bool = True) -> str:
        """Why the share cannot take ``need_bytes`` now ('' when it can).

        Parameters
        ----------
        need_bytes : int
            Bytes the next write needs (beyond ``output.min_free_mb``).
        wait : bool
            False: never wait for the share (at most :data:`STATUS_WAIT_S`); while another operation runs or
            the probe takes longer, answer from the last probe.
        """
        with self._state:
            failure = self._failure
        if failure is not None and time.monotonic() - failure[1] < FAILURE_HOLD_S:
            return failure[0]
        try:
            return self.gate.call("probing (stat, statvfs)", partial(self._probe, need_bytes),
                                  wait_slot=wait, wait_s=None if wait else STATUS_WAIT_S)
        except _GateBusy:
            with self._state:
                return self._last_problem
        except ShareUnavailable as exc:
            with self._state:
                self._last_problem = str(exc)
            return str(exc)

    def storage_problem(self, need_bytes: int) -> str:
        """Why a scan of ``need_bytes`` fits neither on the share nor in the spool ('' when it fits)."""
        share = self.share_problem(need_bytes)
        if not share:
            return ""
        spool = self.spool_problem(need_bytes)
        return f"{share}; and the spool cannot take it: {spool}" if spool else ""

    # --- share: writing --------------------------------------------------------------------------

    def _journal(self) -> list[dict[str, str]]:
        try:
            data = json.loads((self.spool.directory / JOURNAL_FILE).read_text())
            return [r for r in data if isinstance(r, dict) and {"folder", "scan_id"} <= r.keys()]
        except (OSError, ValueError, TypeError):
            return []

    def _set_journal(self, records: list[dict[str, str]]) -> None:
        path = self.spool.directory / JOURNAL_FILE
        try:
            if records:
                self.spool.directory.mkdir(parents=True, exist_ok=True)
                write_bytes_atomic(path, json.dumps(records).encode())
            elif path.exists():
                path.unlink()
                fsync_dir(self.spool.directory)
        except OSError as exc:
            raise OutputError(f"spool {self.spool.directory}: the share journal {JOURNAL_FILE} cannot be written "
                              f"({exc.strerror or exc}); check the local disk") from exc

    def _clean_share_leftovers(self) -> int:
        """Remove what the journal says may be half-written on the share: temporary files, and a scan's
        cloud and preview without its sidecar. Raises :class:`ShareUnavailable` when the share does not
        answer (the journal keeps the rest for the next time)."""
        with self._state:
            fds, self._orphan_fds = self._orphan_fds, []
        while fds:  # left open by operations abandoned on a hung share, which has answered since
            try:
                self._op("closing an abandoned file", partial(os.close, fds[-1]))
            except OutputError as exc:
                if isinstance(exc.__cause__, OSError):
                    fds.pop()  # closed with an error: gone all the same
                with self._state:
                    self._orphan_fds += fds
                raise
            fds.pop()
        removed = 0
        records = self._journal()
        while records:
            rec = records[0]
            folder, sid = Path(rec["folder"]), rec["scan_id"]
            names = self._op(f"listing {folder}", partial(lambda f: os.listdir(f) if f.is_dir() else [], folder))
            complete = f"{sid}.json" in names
            for n in names:
                if n.startswith(f"{TMP_PREFIX}{sid}") or (not complete and n in (f"{sid}.ply", f"{sid}.png")):
                    self._op(f"removing {n}", partial(_unlink_if_there, folder / n))
                    log.info("share: removed %s left by an unfinished write", folder / n)
                    removed += 1
            if removed:
                self._op(f"fsync {folder}", partial(fsync_dir, folder))
            records.pop(0)
            self._set_journal(records)
        return removed

    def _put_tmp(self, folder: Path, name: str, content: FileContent | SpoolFile, src: Path | None) -> Path:
        """Write one file to a temporary name in ``folder`` on the share and fsync it; returns that name.

        ``content`` in memory, or a spool file ``src`` checked against its size and SHA-256 while copied.
        """
        tmp = folder / f"{TMP_PREFIX}{name}.{os.getpid()}"
        fd = self._op(f"creating {tmp.name}", partial(os.open, tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC
                                                      | os.O_CLOEXEC, 0o644))
        closed = False
        try:
            if isinstance(content, FileContent):
                for mv in content.chunks():
                    for off in range(0, mv.nbytes, CHUNK):
                        self._op(f"writing {name}", partial(_write_all, fd, mv[off:off + CHUNK]))
            else:
                assert src is not None
                h = hashlib.sha256()
                size = 0
                try:
                    f = open(src, "rb")
                except OSError as exc:
                    raise SpoolEntryBroken(f"{src}: cannot be read ({exc.strerror})") from exc
                with f:
                    while chunk := f.read(CHUNK):
                        h.update(chunk)
                        size += len(chunk)
                        self._op(f"writing {name}", partial(_write_all, fd, memoryview(chunk)))
                if size != content.size or h.hexdigest() != content.sha256:
                    raise SpoolEntryBroken(f"{src}: {size} bytes, SHA-256 {h.hexdigest()[:12]}..., but "
                                           f"{ENTRY_FILE} says {content.size} bytes, {content.sha256[:12]}...")
            self._op(f"fsync {name}", partial(os.fsync, fd))
            closed = True
            self._op(f"closing {name}", partial(os.close, fd))
        finally:
            if not closed:
                if self.gate.busy():  # the abandoned operation still uses it
                    with self._state:
                        self._orphan_fds.append(fd)
                else:
                    try:
                        self._op(f"closing {name}", partial(os.close, fd))
                    except OutputError:
                        pass
        return tmp

    def _same_file(self, path: Path, size: int, sha256: str) -> bool:
        """Whether ``path`` on the share exists with this size and content (read in chunks, each in time)."""
        def open_if_same_size() -> int | None:
            try:
                if path.stat().st_size != size:
                    return None
            except FileNotFoundError:
                return None
            return os.open(path, os.O_RDONLY | os.O_CLOEXEC)

        fd = self._op(f"checking {path.name}", open_if_same_size)
        if fd is None:
            return False
        h = hashlib.sha256()
        try:
            while chunk := self._op(f"reading {path.name}", partial(os.read, fd, CHUNK)):
                h.update(chunk)
        finally:
            if self.gate.busy():
                with self._state:
                    self._orphan_fds.append(fd)
            else:
                with contextlib.suppress(OutputError):
                    self._op(f"closing {path.name}", partial(os.close, fd))
        return h.hexdigest() == sha256

    def _deliver(self, day: str, scan_id: str, files: list[tuple[FileContent | SpoolFile, Path | None]]
                 ) -> list[Path]:
        """Put one scan's files into ``share/day/``: all under temporary names, then the renames, the sidecar
        last. The journal notes the scan first; on any failure what became visible is removed again."""
        folder = self.directory / day
        records = self._journal()
        records.append({"folder": str(folder), "scan_id": scan_id})
        self._set_journal(records)
        try:
            self._op(f"creating {folder.name}", partial(mkdir_synced, folder))
            placed: list[tuple[Path, Path | None]] = []  # (final, tmp or None when it is already there)
            for content, src in files:
                dst = folder / content.name
                if isinstance(content, SpoolFile) and self._same_file(dst, content.size, content.sha256):
                    placed.append((dst, None))  # moved before (a crash after the rename): counts as moved
                    continue
                placed.append((dst, self._put_tmp(folder, content.name, content, src)))
            for i, (dst, tmp) in enumerate(placed):
                if i == len(placed) - 1:  # before the sidecar: the others are durable
                    self._op(f"fsync {folder}", partial(fsync_dir, folder))
                if tmp is not None:
                    self._op(f"renaming {dst.name}", partial(os.replace, tmp, dst))
            self._op(f"fsync {folder}", partial(fsync_dir, folder))
        except BaseException:
            try:
                self._clean_share_leftovers()
            except OutputError as exc:
                log.warning("share: leftovers of scan %s stay until it answers (%s)", scan_id, exc)
            raise
        try:
            self._set_journal([r for r in self._journal() if r["scan_id"] != scan_id])
        except OutputError as exc:  # the scan is complete on the share; a stale note only costs a listing
            log.warning("%s", exc)
        self.delivered.append(scan_id)
        return [dst for dst, _ in placed]

    # --- spool (appliance/output/spool.py) ---------------------------------------------------------

    def spool_problem(self, need_bytes: int) -> str:
        """Why the spool cannot take ``need_bytes`` now ('' when it can)."""
        return self.spool.problem(need_bytes)

    def spool_entries(self) -> list[Path]:
        """Complete spooled scans, oldest first."""
        return self.spool.entries()

    def spool_bytes(self) -> int:
        """Bytes held by the spool."""
        return self.spool.bytes()

    def enforce_retention(self, now: float | None = None) -> list[str]:
        """The spool's retention (:meth:`Spool.enforce_retention`): the entries dropped."""
        return self.spool.enforce_retention(now)

    @property
    def dropped(self) -> int:
        """Spooled scans dropped by retention since start."""
        return self.spool.dropped

    @property
    def quarantined(self) -> int:
        """Spool entries quarantined since start."""
        return self.spool.quarantined

    def cleanup_incomplete(self) -> int:
        """At start: remove what a crash left half-written (spool and share) and quarantine broken entries.

        Returns
        -------
        int
            Temporary folders and files removed.
        """
        removed = self.spool.remove_leftovers()
        try:
            removed += self._clean_share_leftovers()
            removed += self._op("sweeping old temporary files", self._sweep_stale_tmp)
        except OutputError as exc:
            log.warning("share: leftovers of an unfinished write are removed when it answers (%s)", exc)
        return removed

    def _sweep_stale_tmp(self) -> int:
        """Temporary files older than :data:`STALE_TMP_S` in the two newest day folders (left by a writer
        without a journal, e.g. an older version; a write in progress, also another appliance's, is younger)."""
        if not self.directory.is_dir():
            return 0
        days = sorted(n for n in os.listdir(self.directory) if DAY.fullmatch(n))[-2:]
        removed = 0
        now = time.time()
        for day in days:
            folder = self.directory / day
            for n in os.listdir(folder):
                p = folder / n
                if n.startswith(TMP_PREFIX) and p.is_file() and now - p.stat().st_mtime > STALE_TMP_S:
                    _unlink_if_there(p)
                    log.info("share: removed %s, a temporary file left by an unfinished write", p)
                    removed += 1
            if removed:
                fsync_dir(folder)
        return removed

    def flush_spool(self) -> list[WriteOutcome]:
        """Move spooled scans to the share, oldest first, until the share refuses one.

        Returns
        -------
        list of WriteOutcome
            The scans moved (location ``share``).
        """
        moved: list[WriteOutcome] = []
        self.spool.quarantine_strays()
        for path in self.spool_entries():
            try:
                entry = self.spool.read_entry(path)
            except SpoolEntryBroken as exc:
                self.spool.quarantine(path, str(exc))
                continue
            problem = self.share_problem(entry.size)
            if problem:
                self.last_reason = problem
                break
            try:
                self._clean_share_leftovers()
                files = self._deliver(entry.day, entry.scan_id,
                                      [(f, entry.path / f.name) for f in entry.files])
            except SpoolEntryBroken as exc:
                self.spool.quarantine(path, str(exc))
                continue
            except OutputError as exc:
                self.last_reason = f"moving {path.name} to the share failed: {exc}"
                log.warning("%s; it stays in the spool", self.last_reason)
                break
            try:
                self.spool.remove_entry(path)
            except OSError as exc:  # on the share already; a later flush sees it there and removes it
                log.warning("spool entry %s moved but not removed: %s", path.name, exc)
            log.info("spooled scan %s moved to the share", entry.scan_id)
            moved.append(WriteOutcome(entry.scan_id, "share", files))
        return moved

    # --- one scan --------------------------------------------------------------------------------

    def write_scan(self, day: str, meta: ScanMetadata, cloud: PointCloud, shapes: list[tuple[int, int]], *,
                   normals: bool = False, preview: bool = True,
                   reasons: list[npt.NDArray[np.uint8] | None] | None = None) -> WriteOutcome:
        """Write one scan's cloud, preview and sidecar to ``share/day/``, or to the spool.

        Parameters
        ----------
        day : str
            ``YYYY-MM-DD`` folder of the scan (its UTC start date).
        meta, cloud, shapes, normals, preview, reasons
            As for :func:`appliance.output.scanfiles.scan_file_contents`.

        Raises
        ------
        OutputError
            When neither the share nor the spool can take the scan.
        """
        if self.spool_entries():
            self.flush_spool()
        contents = scan_file_contents(meta, cloud, shapes, normals=normals, preview=preview, reasons=reasons)
        need = estimate_scan_bytes(shapes, normals=normals, preview=preview)
        reason = "older scans are still in the spool" if self.spool_entries() else self.share_problem(need)
        if not reason:
            try:
                self._clean_share_leftovers()
                files = self._deliver(day, meta.scan_id, [(c, None) for c in contents])
                self.last_reason = ""
                return WriteOutcome(meta.scan_id, "share", files)
            except OutputError as exc:
                reason = f"writing to the share failed: {exc}"
        self.last_reason = reason
        spool_problem = self.spool_problem(need)
        if spool_problem:
            raise OutputError(f"scan {meta.scan_id} cannot be stored: {reason}; {spool_problem}; "
                              "free space or bring the share back")
        try:
            paths = self.spool.write(day, meta.scan_id, contents)
        except (OSError, OutputError) as exc:
            raise OutputError(f"scan {meta.scan_id}: spool {self.spool.directory} failed ({exc}); "
                              "check the disk") from exc
        log.warning("scan %s spooled in %s: %s", meta.scan_id, self.spool.directory, reason)
        self.enforce_retention()
        return WriteOutcome(meta.scan_id, "spool", paths, reason)

    def status(self) -> dict[str, Any]:
        """Share and spool state for ``scan3d status`` (any thread; never waits for the share)."""
        problem = self.share_problem(0, wait=False)
        entries = self.spool_entries()
        quarantined = self.spool.quarantine_count()
        out: dict[str, Any] = {
            "directory": str(self.directory),
            "available": not problem,
            "problem": problem,
            "spool_directory": str(self.spool.directory),
            "spooled_scans": len(entries),
            "spool_mb": round(sum(dir_bytes(e) for e in entries) / MB, 2),
            "spool_dropped": self.dropped,
            "spool_quarantined": quarantined,
        }
        with self._state:
            free = self._last_free
        if not problem and free is not None:
            out["free_mb"] = round(free / MB, 1)
        return out
