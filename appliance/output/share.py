"""The share writer: scan files into ``output.directory/YYYY-MM-DD/``, or a local spool while it is away.

Every file is written under a temporary name, fsynced and renamed (:mod:`appliance.output.atomic`), so a
watcher of the share never sees a partial file; the sidecar (``.json``) comes last. When the share is
missing, not a mount point (``output.require_mount``), full or fails, the scan goes to
``output.spool_directory``, one folder per scan (renamed into place when complete), and is moved over,
oldest first, once the share is back. Spooled scans are moved before any newer one is written, so the
share sees scans in order.

The writer is synchronous and not thread-safe: the service calls it from one writer thread.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance.config.schema import OutputConfig
from appliance.errors import OutputError
from appliance.output.atomic import TMP_PREFIX, fsync_dir, write_atomic
from appliance.output.scanfiles import ScanFiles, write_scan_files
from appliance.output.sidecar import ScanMetadata
from appliance.reconstruct.types import PointCloud

log = logging.getLogger(__name__)

# Module-level so tests can fake a full disk: path -> os.statvfs_result-like (f_bavail, f_frsize).
STATVFS: Callable[[str], Any] = os.statvfs

ENTRY_FILE = "entry.json"
MB = 1024 * 1024


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


def _dir_bytes(path: Path) -> int:
    total = 0
    for p in path.iterdir():
        try:
            total += p.stat().st_size
        except OSError:
            pass
    return total


class ShareWriter:
    """Writes scans to the share or the spool, moves the spool over, applies retention.

    Parameters
    ----------
    cfg : OutputConfig
        ``directory`` (the share), ``spool_directory``, ``spool_max_mb``, ``spool_max_age_days``,
        ``min_free_mb``, ``require_mount``.
    """

    def __init__(self, cfg: OutputConfig) -> None:
        self.cfg = cfg
        self.directory = Path(cfg.directory)
        self.spool = Path(cfg.spool_directory)
        self.dropped = 0
        self.last_reason = ""

    # --- share -----------------------------------------------------------------------------------

    def share_problem(self, need_bytes: int = 0) -> str:
        """Why the share cannot take ``need_bytes`` now ('' when it can)."""
        d = self.directory
        if not d.is_dir():
            return f"share {d} is not there (not mounted, removed or renamed)"
        if self.cfg.require_mount and not os.path.ismount(d):
            return f"share {d} is not a mount point (output.require_mount is set)"
        if not os.access(d, os.W_OK):
            return f"share {d} is not writable"
        try:
            free = free_bytes(d)
        except OSError as exc:
            return f"share {d}: cannot read its free space ({exc.strerror})"
        if free < need_bytes + self.cfg.min_free_mb * MB:
            return (f"share {d} is full: {free / MB:.0f} MB free, a scan needs up to "
                    f"{need_bytes / MB:.0f} MB and output.min_free_mb = {self.cfg.min_free_mb:g} MB "
                    "must stay free")
        return ""

    def storage_problem(self, need_bytes: int) -> str:
        """Why a scan of ``need_bytes`` fits neither on the share nor in the spool ('' when it fits)."""
        share = self.share_problem(need_bytes)
        if not share:
            return ""
        spool = self.spool_problem(need_bytes)
        return f"{share}; and the spool cannot take it: {spool}" if spool else ""

    # --- spool -----------------------------------------------------------------------------------

    def spool_problem(self, need_bytes: int) -> str:
        """Why the spool cannot take ``need_bytes`` now ('' when it can)."""
        try:
            self.spool.mkdir(parents=True, exist_ok=True)
            free = free_bytes(self.spool)
        except OSError as exc:
            return f"spool {self.spool}: {exc.strerror or exc}"
        if free < need_bytes + self.cfg.min_free_mb * MB:
            return (f"spool {self.spool}: {free / MB:.0f} MB free, needs {need_bytes / MB:.0f} MB "
                    "+ output.min_free_mb")
        used = self.spool_bytes()
        if used + need_bytes > self.cfg.spool_max_mb * MB:
            return (f"spool {self.spool} holds {used / MB:.0f} MB of output.spool_max_mb = "
                    f"{self.cfg.spool_max_mb:g} MB")
        return ""

    def spool_entries(self) -> list[Path]:
        """Complete spooled scans, oldest first."""
        if not self.spool.is_dir():
            return []
        entries = [p for p in self.spool.iterdir()
                   if p.is_dir() and not p.name.startswith(TMP_PREFIX) and (p / ENTRY_FILE).is_file()]
        return sorted(entries, key=lambda p: p.name)

    def spool_bytes(self) -> int:
        """Bytes held by the spool."""
        return sum(_dir_bytes(e) for e in self.spool_entries())

    def _next_order(self) -> int:
        heads = [p.name.split("-", 1)[0] for p in self.spool_entries()]
        orders = [int(h) for h in heads if h.isdigit()]
        return max(orders, default=0) + 1

    def cleanup_incomplete(self) -> int:
        """Remove temporary folders and files left by a crash (spool and today's share folder)."""
        removed = 0
        if self.spool.is_dir():
            for p in self.spool.iterdir():
                if p.name.startswith(TMP_PREFIX):
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
                    removed += 1
        return removed

    def _write_spool(self, day: str, meta: ScanMetadata, cloud: PointCloud, shapes: list[tuple[int, int]],
                     normals: bool, preview: bool) -> ScanFiles:
        self.spool.mkdir(parents=True, exist_ok=True)
        name = f"{self._next_order():08d}-{meta.scan_id}"
        tmp = self.spool / f"{TMP_PREFIX}{name}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        try:
            files = write_scan_files(tmp, meta, cloud, shapes, normals=normals, preview=preview)
            entry = {"day": day, "scan_id": meta.scan_id, "files": [p.name for p in files.all()]}
            (tmp / ENTRY_FILE).write_text(json.dumps(entry))
            final = self.spool / name
            os.replace(tmp, final)
            fsync_dir(self.spool)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return ScanFiles(*(final / p.name if p is not None else None
                           for p in (files.cloud, files.sidecar, files.preview)))  # type: ignore[arg-type]

    def _move_entry(self, entry: Path) -> list[Path]:
        info = json.loads((entry / ENTRY_FILE).read_text())
        folder = self.directory / str(info["day"])
        folder.mkdir(exist_ok=True)
        moved = []
        for name in info["files"]:  # cloud, preview, sidecar: the sidecar last
            src, dst = entry / name, folder / name
            try:
                os.rename(src, dst)  # same filesystem: atomic
            except OSError:
                with open(src, "rb") as f:
                    write_atomic(dst, lambda out, f=f: shutil.copyfileobj(f, out, 1 << 20))  # type: ignore[misc]
            moved.append(dst)
        fsync_dir(folder)
        shutil.rmtree(entry)
        return moved

    def flush_spool(self) -> list[WriteOutcome]:
        """Move spooled scans to the share, oldest first, until the share refuses one.

        Returns
        -------
        list of WriteOutcome
            The scans moved (location ``share``).
        """
        moved: list[WriteOutcome] = []
        for entry in self.spool_entries():
            need = _dir_bytes(entry)
            problem = self.share_problem(need)
            if problem:
                self.last_reason = problem
                break
            try:
                files = self._move_entry(entry)
            except (OSError, OutputError, ValueError) as exc:
                self.last_reason = f"moving {entry.name} to the share failed: {exc}"
                log.warning("%s; it stays in the spool", self.last_reason)
                break
            scan_id = entry.name.split("-", 1)[1]
            log.info("spooled scan %s moved to the share", scan_id)
            moved.append(WriteOutcome(scan_id, "share", files))
        return moved

    def enforce_retention(self, now: float | None = None) -> list[str]:
        """Drop spooled scans older than ``spool_max_age_days``, then the oldest beyond ``spool_max_mb``.

        Returns
        -------
        list of str
            The entries dropped (each is logged as a warning).
        """
        now = time.time() if now is None else now
        dropped: list[str] = []
        entries = self.spool_entries()
        max_age = self.cfg.spool_max_age_days * 86400.0
        sizes = {e: _dir_bytes(e) for e in entries}
        total = sum(sizes.values())
        for e in entries:
            too_old = now - e.stat().st_mtime > max_age
            too_big = total > self.cfg.spool_max_mb * MB
            if not (too_old or too_big):
                continue
            shutil.rmtree(e, ignore_errors=True)
            total -= sizes[e]
            dropped.append(e.name)
            why = "older than output.spool_max_age_days" if too_old else "spool over output.spool_max_mb"
            log.warning("spool retention dropped %s (%s)", e.name, why)
        self.dropped += len(dropped)
        return dropped

    # --- one scan --------------------------------------------------------------------------------

    def write_scan(self, day: str, meta: ScanMetadata, cloud: PointCloud, shapes: list[tuple[int, int]], *,
                   normals: bool = False, preview: bool = True) -> WriteOutcome:
        """Write one scan's cloud, preview and sidecar to ``share/day/``, or to the spool.

        Parameters
        ----------
        day : str
            ``YYYY-MM-DD`` folder of the scan (its UTC start date).
        meta, cloud, shapes, normals, preview
            As for :func:`appliance.output.scanfiles.write_scan_files`.

        Raises
        ------
        OutputError
            When neither the share nor the spool can take the scan.
        """
        if self.spool_entries():
            self.flush_spool()
        need = estimate_scan_bytes(shapes, normals=normals, preview=preview)
        reason = "older scans are still in the spool" if self.spool_entries() else self.share_problem(need)
        if not reason:
            folder = self.directory / day
            try:
                folder.mkdir(exist_ok=True)
                files = write_scan_files(folder, meta, cloud, shapes, normals=normals, preview=preview)
                self.last_reason = ""
                return WriteOutcome(meta.scan_id, "share", files.all())
            except (OSError, OutputError) as exc:
                reason = f"writing to the share failed: {exc}"
                for suffix in (".ply", ".png", ".json"):  # nothing half-done stays on the share
                    try:
                        (folder / f"{meta.scan_id}{suffix}").unlink(missing_ok=True)
                    except OSError:
                        pass
        self.last_reason = reason
        spool_problem = self.spool_problem(need)
        if spool_problem:
            raise OutputError(f"scan {meta.scan_id} cannot be stored: {reason}; {spool_problem}; "
                              "free space or bring the share back")
        try:
            files = self._write_spool(day, meta, cloud, shapes, normals, preview)
        except OSError as exc:
            raise OutputError(f"scan {meta.scan_id}: spool {self.spool} failed ({exc}); "
                              "check the disk") from exc
        log.warning("scan %s spooled in %s: %s", meta.scan_id, self.spool, reason)
        self.enforce_retention()
        return WriteOutcome(meta.scan_id, "spool", files.all(), reason)

    def status(self) -> dict[str, Any]:
        """Share and spool state for ``scan3d status``."""
        problem = self.share_problem(0)
        entries = self.spool_entries()
        out: dict[str, Any] = {
            "directory": str(self.directory),
            "available": not problem,
            "problem": problem,
            "spool_directory": str(self.spool),
            "spooled_scans": len(entries),
            "spool_mb": round(sum(_dir_bytes(e) for e in entries) / MB, 2),
            "spool_dropped": self.dropped,
        }
        if not problem:
            try:
                out["free_mb"] = round(free_bytes(self.directory) / MB, 1)
            except OSError:
                pass
        return out
