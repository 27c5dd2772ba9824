"""A watcher of a share folder for the share tests: the kernel's own record (inotify) of names appearing and
going, in order, and the checks downstream watchers depend on (a ``.json`` is visible only beside its complete
``.ply``/``.png``; nothing is left without its ``.json``)."""

from __future__ import annotations

import ctypes
import errno
import os
import struct
from pathlib import Path

IN_CREATE = 0x100
IN_DELETE = 0x200
IN_MOVED_FROM = 0x40
IN_MOVED_TO = 0x80
_EVENT = struct.Struct("iIII")


class DirWatch:
    """inotify on one folder: which visible names (not starting with ``.``) appeared and went, in order.

    Parameters
    ----------
    folder : Path
        An existing folder (the real one, also when a FUSE mount passes through to it).
    """

    def __init__(self, folder: Path) -> None:
        self._libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self._libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "inotify_init1")
        mask = IN_CREATE | IN_DELETE | IN_MOVED_FROM | IN_MOVED_TO
        if self._libc.inotify_add_watch(self.fd, os.fsencode(folder), mask) < 0:
            raise OSError(ctypes.get_errno(), f"inotify_add_watch {folder}")
        self.log: list[tuple[str, str]] = []  # ("+", name) appeared, ("-", name) went

    def poll(self) -> list[tuple[str, str]]:
        """Read what happened since the last call (appended to :attr:`log`) and return the whole log."""
        while True:
            try:
                data = os.read(self.fd, 65536)
            except OSError as exc:
                if exc.errno == errno.EAGAIN:
                    break
                raise
            off = 0
            while off < len(data):
                _wd, mask, _cookie, n = _EVENT.unpack_from(data, off)
                name = data[off + _EVENT.size: off + _EVENT.size + n].rstrip(b"\0").decode()
                off += _EVENT.size + n
                if name.startswith("."):
                    continue
                self.log.append(("+" if mask & (IN_CREATE | IN_MOVED_TO) else "-", name))
        return self.log

    def appeared(self, suffix: str) -> list[str]:
        """Stems of the names ending in ``suffix`` in the order they appeared."""
        return [Path(n).stem for kind, n in self.poll() if kind == "+" and n.endswith(suffix)]

    def partial_moments(self) -> list[str]:
        """Every moment at which a ``.json`` was visible without its ``.ply`` (a completion marker that lied),
        and, at the end, every ``.ply``/``.png`` left without its ``.json``."""
        visible: set[str] = set()
        bad: list[str] = []
        for kind, name in self.poll():
            if kind == "+":
                visible.add(name)
            else:
                visible.discard(name)
            for n in visible:
                if n.endswith(".json") and f"{n[:-5]}.ply" not in visible:
                    bad.append(f"after {kind}{name}: {n} visible without its .ply")
        for n in sorted(visible):
            stem, ext = os.path.splitext(n)
            if ext in (".ply", ".png") and f"{stem}.json" not in visible:
                bad.append(f"at the end: {n} without {stem}.json")
        return bad

    def close(self) -> None:
        """Stop watching."""
        os.close(self.fd)
