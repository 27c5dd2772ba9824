"""Atomic file writing: temporary name in the target folder, fsync, rename, fsync the folder.

A watcher of the target folder never sees a partial file: it sees nothing, then the whole file; a failed write
leaves the old file whole and no temporary behind. It sits beside ``errors.py`` (importable from every layer) so
that every file the appliance writes goes through it: the share's clouds (``output/``) as well as the sequence
manifests of ``patterns/``.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import BinaryIO

from appliance.errors import OutputError

TMP_PREFIX = ".tmp-"


def same_file(path: Path, others: Iterable[tuple[str, Path]]) -> tuple[str, Path] | None:
    """The first ``(what, other)`` whose path is ``path`` itself (links resolved): an output about to be written
    over an input (or another output) of the same command, which every command refuses before any work.

    Parameters
    ----------
    path : Path
        The file a command is about to write.
    others : iterable of (str, Path)
        What each other file is (for the message) and its path.
    """
    real = os.path.realpath(path)
    return next(((what, p) for what, p in others if os.path.realpath(p) == real), None)


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


def write_files_atomic(folder: Path, files: Mapping[str, bytes]) -> list[Path]:
    """Write a set of files into ``folder`` all or none: the old set stays whole if any of them fails.

    Every file is first written to a temporary name and fsynced; only when all are on disk are they renamed
    into place (a rename does not need space) and the folder is fsynced.

    Parameters
    ----------
    folder : Path
        The folder, which must exist.
    files : mapping of str to bytes
        File name (no folder part) to content.

    Returns
    -------
    list of Path
        The files written, in the order given.

    Raises
    ------
    OutputError
        When a file cannot be written (a full disk, a read-only folder, a NUL in a name); every temporary file
        is removed and no file of the set has been replaced.
    """
    if "\x00" in str(folder) or any("\x00" in name or "/" in name for name in files):
        raise OutputError(f"{str(folder)!r}: a file name cannot hold a NUL character or a '/'; fix the path")
    staged: list[tuple[Path, Path]] = []
    try:
        for name, data in files.items():
            path = folder / name
            tmp = path.with_name(f"{TMP_PREFIX}{name}.{os.getpid()}")
            staged.append((tmp, path))
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
    except OSError as exc:
        for tmp, _ in staged:
            _remove(tmp)
        raise OutputError(f"{staged[-1][1]}: cannot be written ({exc.strerror or exc}); nothing of the "
                          f"{len(files)} files was replaced; check the folder is writable and has free space") from exc
    except BaseException:
        for tmp, _ in staged:
            _remove(tmp)
        raise
    try:
        for tmp, path in staged:
            os.replace(tmp, path)
        fsync_dir(folder)
    except OSError as exc:
        for tmp, _ in staged:
            _remove(tmp)
        raise OutputError(f"{folder}: the files cannot be moved into place ({exc.strerror or exc}); "
                          "check the folder") from exc
    return [path for _, path in staged]
