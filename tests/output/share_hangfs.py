"""A FUSE filesystem for the share tests: passes through to a real folder, hangs or runs out of room on demand.

Run as ``python tests/output/share_hangfs.py ROOT MOUNTPOINT`` (root, with /dev/fuse and libfuse2). It mounts,
prints ``ready`` on stdout and then reads commands from stdin, one a line, answering ``ok`` to each:

``hang [OP ...]``
    Every later operation (or only the FUSE operations named, e.g. ``hang write``) blocks (in the kernel's
    view: the server does not answer), like a hard-mounted NFS/SMB share whose server stopped answering.
``go``
    Blocked operations continue, new ones pass.
``quota N``
    Only ``N`` more files or folders may be created; then ``create``/``mkdir`` fail with ENOSPC, while statfs
    still shows the backing folder's free inodes, as a quota on an SMB share does (``quota -1``: no limit).

End of stdin (the test closing the pipe) releases every blocked operation and unmounts. The tests also
unmount with ``fusermount -u`` / ``umount -l`` and kill this process in their teardown, so nothing can hang.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
from typing import Any

from fuse import FUSE, FuseOSError, Operations  # type: ignore[import-untyped]


class HangFS(Operations):  # type: ignore[misc]
    """Passthrough to ``root`` with a gate every operation waits at and a create quota."""

    def __init__(self, root: str) -> None:
        self.root = os.path.realpath(root)
        self.gate = threading.Event()  # set: operations pass
        self.gate.set()
        self.blocked: set[str] | None = None  # the operations the gate holds (None: all)
        self.quota = -1
        self._qlock = threading.Lock()

    def _p(self, path: str) -> str:
        return os.path.join(self.root, path.lstrip("/"))

    def _take_quota(self) -> None:
        with self._qlock:
            if self.quota == 0:
                raise FuseOSError(errno.ENOSPC)
            if self.quota > 0:
                self.quota -= 1

    def __call__(self, op: str, path: str, *args: Any) -> Any:
        if not self.gate.is_set() and (self.blocked is None or op in self.blocked):
            self.gate.wait()
        try:
            return super().__call__(op, path, *args)
        except OSError as exc:
            if isinstance(exc, FuseOSError):
                raise
            raise FuseOSError(exc.errno or errno.EIO) from exc

    # --- metadata --------------------------------------------------------------------------------

    def access(self, path: str, mode: int) -> None:
        if not os.access(self._p(path), mode):
            raise FuseOSError(errno.EACCES)

    def getattr(self, path: str, fh: int | None = None) -> dict[str, Any]:
        st = os.lstat(self._p(path))
        keys = ("st_atime", "st_ctime", "st_gid", "st_mode", "st_mtime", "st_nlink", "st_size", "st_uid")
        return {k: getattr(st, k) for k in keys}

    def readdir(self, path: str, fh: int) -> list[str]:
        return [".", "..", *os.listdir(self._p(path))]

    def statfs(self, path: str) -> dict[str, Any]:
        st = os.statvfs(self._p(path))
        keys = ("f_bavail", "f_bfree", "f_blocks", "f_bsize", "f_favail", "f_ffree", "f_files", "f_flag",
                "f_frsize", "f_namemax")
        return {k: getattr(st, k) for k in keys}  # the quota is not shown (like a quota on an SMB share)

    def chmod(self, path: str, mode: int) -> None:
        os.chmod(self._p(path), mode)

    def chown(self, path: str, uid: int, gid: int) -> None:
        os.chown(self._p(path), uid, gid)

    def utimens(self, path: str, times: tuple[float, float] | None = None) -> None:
        os.utime(self._p(path), times)

    # --- names -----------------------------------------------------------------------------------

    def mkdir(self, path: str, mode: int) -> None:
        p = self._p(path)
        self._take_quota()
        os.mkdir(p, mode)

    def rmdir(self, path: str) -> None:
        os.rmdir(self._p(path))

    def unlink(self, path: str) -> None:
        os.unlink(self._p(path))

    def rename(self, old: str, new: str) -> None:
        os.rename(self._p(old), self._p(new))

    # --- file data -------------------------------------------------------------------------------

    def create(self, path: str, mode: int, fi: Any = None) -> int:
        p = self._p(path)
        self._take_quota()
        return os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)

    def open(self, path: str, flags: int) -> int:
        return os.open(self._p(path), flags)

    def read(self, path: str, size: int, offset: int, fh: int) -> bytes:
        return os.pread(fh, size, offset)

    def write(self, path: str, data: bytes, offset: int, fh: int) -> int:
        return os.pwrite(fh, data, offset)

    def truncate(self, path: str, length: int, fh: int | None = None) -> None:
        with open(self._p(path), "r+b") as f:
            f.truncate(length)

    def flush(self, path: str, fh: int) -> None:
        pass

    def release(self, path: str, fh: int) -> None:
        os.close(fh)

    def fsync(self, path: str, datasync: int, fh: int) -> None:
        os.fsync(fh)

    def fsyncdir(self, path: str, datasync: int, fh: int) -> None:
        pass


def _commands(fs: HangFS, mountpoint: str) -> None:
    for line in sys.stdin:
        cmd = line.split()
        if cmd and cmd[0] == "hang":
            fs.blocked = set(cmd[1:]) or None
            fs.gate.clear()
        elif cmd == ["go"]:
            fs.gate.set()
        elif len(cmd) == 2 and cmd[0] == "quota":
            with fs._qlock:
                fs.quota = int(cmd[1])
        print("ok", flush=True)
    fs.gate.set()  # the test is gone: release everything and unmount
    import subprocess

    if subprocess.call(["fusermount", "-u", "-z", mountpoint], stderr=subprocess.DEVNULL) != 0:
        subprocess.call(["umount", "-l", mountpoint], stderr=subprocess.DEVNULL)


def main() -> None:
    root, mountpoint = sys.argv[1], sys.argv[2]
    fs = HangFS(root)
    threading.Thread(target=_commands, args=(fs, mountpoint), daemon=True).start()

    def _ready() -> None:  # once the mount is there, say so
        import time

        for _ in range(500):
            if os.path.ismount(mountpoint):
                print("ready", flush=True)
                return
            time.sleep(0.01)

    threading.Thread(target=_ready, daemon=True).start()
    FUSE(fs, mountpoint, foreground=True, nothreads=False, allow_other=False,
         attr_timeout=0, entry_timeout=0, negative_timeout=0, default_permissions=False)


if __name__ == "__main__":
    main()
