"""Atomic file writing for the output layer (the implementation is :mod:`appliance.atomic_write`, importable from
every layer), and the folder helpers of the share.

A watcher of the target folder never sees a partial file: it sees nothing, then the whole file.
"""

from __future__ import annotations

from pathlib import Path

from appliance.atomic_write import TMP_PREFIX, fsync_dir, write_atomic, write_bytes_atomic, write_files_atomic

__all__ = ["TMP_PREFIX", "fsync_dir", "mkdir_synced", "write_atomic", "write_bytes_atomic", "write_files_atomic"]


def mkdir_synced(folder: Path) -> bool:
    """Create ``folder`` (its parent must exist) and fsync the parent; False when it was already there."""
    try:
        folder.mkdir()
    except FileExistsError:
        if folder.is_dir():
            return False
        raise
    fsync_dir(folder.parent)
    return True
