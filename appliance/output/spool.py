"""The local spool: where a scan waits, on the appliance's own disk, while the share is away.

One folder per scan (``NNNNNNNN-<scan-id>``, written as ``.tmp-...`` and renamed into place when complete, with
``entry.json`` naming each file's size and SHA-256); oldest first by that number. An entry that cannot be moved
for its own fault (unreadable ``entry.json``, a file missing or changed) goes to ``quarantine/`` with one log
line instead of blocking the queue. Retention drops entries older than ``output.spool_max_age_days``, then the
oldest beyond ``output.spool_max_mb``. Moving entries to the share is the share writer's
(:meth:`appliance.output.share.ShareWriter.flush_spool`); the spool is local and used directly.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from appliance.config.schema import OutputConfig
from appliance.errors import OutputError
from appliance.output.atomic import TMP_PREFIX, fsync_dir, write_atomic, write_bytes_atomic
from appliance.output.scanfiles import FileContent

log = logging.getLogger(__name__)

ENTRY_FILE = "entry.json"
QUARANTINE_DIR = "quarantine"
MB = 1024 * 1024
READ_CHUNK = 4 * MB
DAY = re.compile(r"\d{4}-\d{2}-\d{2}")


class SpoolEntryBroken(OutputError):
    """A spool entry that cannot be moved for its own fault (quarantined)."""


@dataclass(frozen=True)
class SpoolFile:
    """One file of a spooled scan, as ``entry.json`` names it (size in bytes, SHA-256 hex)."""

    name: str
    size: int
    sha256: str


@dataclass(frozen=True)
class SpoolEntry:
    """One spooled scan: its folder, the share's day folder it goes to, its scan id and files (sidecar last)."""

    path: Path
    day: str
    scan_id: str
    files: tuple[SpoolFile, ...]

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)


def dir_bytes(path: Path) -> int:
    """Bytes of the files directly in ``path`` (0 where it cannot be read)."""
    total = 0
    try:
        for p in path.iterdir():
            try:
                total += p.stat().st_size
            except OSError:
                pass
    except OSError:
        pass
    return total


def sha256_file(path: Path) -> str:
    """SHA-256 (hex) of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(READ_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class Spool:
    """The spool folder ``directory`` under the limits of ``cfg`` (``spool_max_mb``, ``spool_max_age_days``,
    ``min_free_mb``); ``free_bytes(path)`` says how much its filesystem has free (bytes)."""

    def __init__(self, directory: Path, cfg: OutputConfig, free_bytes: Callable[[Path], int]) -> None:
        self.directory = directory
        self.cfg = cfg
        self._free_bytes = free_bytes
        self.dropped = 0  # entries dropped by retention
        self.quarantined = 0  # entries moved to quarantine/

    def problem(self, need_bytes: int) -> str:
        """Why the spool cannot take ``need_bytes`` now ('' when it can)."""
        d = self.directory
        try:
            d.mkdir(parents=True, exist_ok=True)
            free = self._free_bytes(d)
        except OSError as exc:
            return f"spool {d}: {exc.strerror or exc}"
        if free < need_bytes + self.cfg.min_free_mb * MB:
            return f"spool {d}: {free / MB:.0f} MB free, needs {need_bytes / MB:.0f} MB + output.min_free_mb"
        used = self.bytes()
        if used + need_bytes > self.cfg.spool_max_mb * MB:
            return f"spool {d} holds {used / MB:.0f} MB of output.spool_max_mb = {self.cfg.spool_max_mb:g} MB"
        return ""

    def entries(self) -> list[Path]:
        """Complete spooled scans, oldest first."""
        try:
            entries = [p for p in self.directory.iterdir()
                       if p.is_dir() and not p.name.startswith(TMP_PREFIX) and p.name != QUARANTINE_DIR
                       and (p / ENTRY_FILE).is_file()]
        except OSError:
            return []
        return sorted(entries, key=lambda p: p.name)

    def bytes(self) -> int:
        """Bytes held by the spool's entries."""
        return sum(dir_bytes(e) for e in self.entries())

    def quarantine_count(self) -> int:
        """Entries in ``quarantine/`` now."""
        try:
            return len(list((self.directory / QUARANTINE_DIR).iterdir()))
        except OSError:
            return 0

    def _next_order(self) -> int:
        heads = [p.name.split("-", 1)[0] for p in self.entries()]
        orders = [int(h) for h in heads if h.isdigit()]
        return max(orders, default=0) + 1

    def quarantine(self, entry: Path, why: str) -> None:
        """Move ``entry`` to ``quarantine/`` (or remove it where it cannot be moved), with one warning."""
        qdir = self.directory / QUARANTINE_DIR
        try:
            qdir.mkdir(exist_ok=True)
            os.replace(entry, qdir / entry.name)
            fsync_dir(self.directory)
            fsync_dir(qdir)
        except OSError as exc:  # cannot even move it: drop it, the queue must go on
            shutil.rmtree(entry, ignore_errors=True)
            why += f"; could not be quarantined ({exc.strerror or exc}), removed"
        self.quarantined += 1
        log.warning("spool entry %s quarantined in %s: %s", entry.name, qdir, why)

    def quarantine_strays(self) -> None:
        """Folders in the spool that are neither temporary nor complete entries (no entry.json)."""
        try:
            strays = [p for p in self.directory.iterdir() if p.is_dir() and not p.name.startswith(TMP_PREFIX)
                      and p.name != QUARANTINE_DIR and not (p / ENTRY_FILE).is_file()]
        except OSError:
            return
        for p in strays:
            self.quarantine(p, f"no {ENTRY_FILE} (written half-way?)")

    def read_entry(self, entry: Path) -> SpoolEntry:
        """The entry's ``entry.json``; :class:`SpoolEntryBroken` when it is unreadable or names bad files."""
        try:
            info = json.loads((entry / ENTRY_FILE).read_text())
            day, scan_id = str(info["day"]), str(info["scan_id"])
            files = []
            for f in info["files"]:
                if isinstance(f, str):  # written before sizes and checksums were kept
                    p = entry / f
                    files.append(SpoolFile(f, p.stat().st_size, sha256_file(p)))
                else:
                    files.append(SpoolFile(str(f["name"]), int(f["size"]), str(f["sha256"])))
        except (OSError, ValueError, TypeError, KeyError, UnicodeDecodeError) as exc:
            raise SpoolEntryBroken(f"{ENTRY_FILE} unreadable ({exc})") from exc
        if not DAY.fullmatch(day) or not files or any("/" in f.name or f.name.startswith(".") for f in files):
            raise SpoolEntryBroken(f"{ENTRY_FILE} names day {day!r} and files {[f.name for f in files]}")
        files.sort(key=lambda f: f.name.endswith(".json"))  # the sidecar last
        return SpoolEntry(entry, day, scan_id, tuple(files))

    def remove_leftovers(self) -> int:
        """At start: remove the temporary folders and files a crash left, quarantine stray folders.

        Returns
        -------
        int
            Temporary folders and files removed.
        """
        removed = 0
        if self.directory.is_dir():
            for p in self.directory.iterdir():
                if p.name.startswith(TMP_PREFIX):
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
                    removed += 1
            self.quarantine_strays()
        return removed

    def write(self, day: str, scan_id: str, contents: list[FileContent]) -> list[Path]:
        """Spool one scan's files (a temporary folder renamed into place when complete); returns their paths."""
        self.directory.mkdir(parents=True, exist_ok=True)
        name = f"{self._next_order():08d}-{scan_id}"
        tmp = self.directory / f"{TMP_PREFIX}{name}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        try:
            files = []
            for c in contents:
                write_atomic(tmp / c.name, c.write_to)
                files.append({"name": c.name, "size": c.size, "sha256": c.sha256()})
            entry = {"day": day, "scan_id": scan_id, "files": files,
                     "spooled_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
            write_bytes_atomic(tmp / ENTRY_FILE, json.dumps(entry).encode())  # fsyncs it and the folder
            final = self.directory / name
            os.replace(tmp, final)
            fsync_dir(self.directory)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return [final / c.name for c in contents]

    def remove_entry(self, entry: Path) -> None:
        """Remove a moved entry (renamed to a temporary name first: never half-removed under its own name)."""
        gone = entry.with_name(f"{TMP_PREFIX}{entry.name}")
        os.replace(entry, gone)
        fsync_dir(self.directory)
        shutil.rmtree(gone, ignore_errors=True)

    def enforce_retention(self, now: float | None = None) -> list[str]:
        """Drop spooled scans older than ``spool_max_age_days``, then the oldest beyond ``spool_max_mb``.

        Returns
        -------
        list of str
            The entries dropped (each is logged as a warning).
        """
        now = time.time() if now is None else now
        dropped: list[str] = []
        entries = self.entries()
        max_age = self.cfg.spool_max_age_days * 86400.0
        sizes = {e: dir_bytes(e) for e in entries}
        total = sum(sizes.values())
        for e in entries:
            try:
                too_old = now - e.stat().st_mtime > max_age
            except OSError:
                continue
            too_big = total > self.cfg.spool_max_mb * MB
            if not (too_old or too_big):
                continue
            shutil.rmtree(e, ignore_errors=True)
            total -= sizes[e]
            dropped.append(e.name)
            why = "older than output.spool_max_age_days" if too_old else "spool over output.spool_max_mb"
            log.warning("spool retention dropped %s (%s)", e.name, why)
        qdir = self.directory / QUARANTINE_DIR
        try:
            for q in qdir.iterdir():  # kept for a look, as long as spooled scans are
                if now - q.stat().st_mtime > max_age:
                    shutil.rmtree(q, ignore_errors=True)
                    log.warning("spool retention dropped quarantined %s (older than output.spool_max_age_days)",
                                q.name)
        except OSError:
            pass
        self.dropped += len(dropped)
        return dropped
