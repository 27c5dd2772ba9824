"""Atomic file writing: temporary name in the target folder, fsync, rename, fsync the folder.

A watcher of the target folder never sees a partial file: it sees nothing, then the whole file.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from appliance.errors import OutputError

TMP_PREFIX = ".tmp-"


def write_atomic(path: Path, writer: Callable[[BinaryIO], None]) -> Path:
    """Write ``path`` atomically with ``writer(file)``.

    Parameters
    ----------
    path : Path
        Final file path; its folder must exist.
    writer : callable
        Writes the content into the open binary file it is given.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputError
        When the folder is missing, read-only or full (nothing is left behind).
    """
    if "\x00" in str(path):
        raise OutputError(f"{str(path)!r}: a file name cannot hold a NUL character; fix the path")
    tmp = path.with_name(f"{TMP_PREFIX}{path.name}.{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except OSError as exc:
        _remove(tmp)
        raise OutputError(f"{path}: cannot be written ({exc.strerror or exc}); check the folder exists, "
                          "is writable and has free space") from exc
    except BaseException:  # the writer's own error: the old file stays, no temporary is left behind
        _remove(tmp)
        raise
    return path


def _remove(tmp: Path) -> None:
    try:
        tmp.unlink(missing_ok=True)
    except OSError:  # a read-only folder: there is no temporary file to remove either
        pass


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`write_atomic`)."""

    def _write(f: BinaryIO) -> None:
        f.write(data)

    return write_atomic(path, _write)


def fsync_dir(folder: Path) -> None:
    """fsync a directory so a rename, a new file or a new folder in it is durable.

    A filesystem that cannot fsync a directory (EINVAL or ENOTSUP, e.g. some network filesystems, which
    commit names at once) is accepted as it is.
    """
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


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
