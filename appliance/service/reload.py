"""Live configuration: reload the YAML file on SIGHUP and when it changes (cheap mtime polling).

A file that does not validate is rejected with its ``file:line: key = value: rule`` message; the last good
configuration keeps running and the error is published (status, log).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
from collections.abc import Awaitable, Callable
from pathlib import Path

from appliance.config import AppConfig, load_config
from appliance.config.loader import prepare_service_folders
from appliance.errors import ConfigError

log = logging.getLogger(__name__)

# Module-level so tests can shorten it: wait this long after a change so an editor finishes writing.
SETTLE_S = 0.1
IDLE_RECHECK_S = 1.0  # with polling off, look this often whether a reload turned it on

Stamp = tuple[int, int, int] | None


def load_service_config(path: Path) -> AppConfig:
    """:func:`load_config`, then the service's local folders made and checked
    (:func:`appliance.config.loader.prepare_service_folders`): a reload that would point the state or spool
    folder at a file is rejected like any bad value, and the last good configuration keeps running."""
    cfg = load_config(path)
    prepare_service_folders(cfg, str(path))
    return cfg


def file_stamp(path: Path) -> Stamp:
    """(mtime_ns, size, inode) of ``path``; None when it is missing."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


class ConfigWatcher:
    """Polls ``path`` and reloads it on change or on :meth:`reload`.

    Parameters
    ----------
    path : Path
        The configuration file.
    apply : callable
        ``await apply(cfg)`` with each new valid configuration.
    rejected : callable
        ``rejected(message)`` when a changed file does not validate (message names file, line and key).
    poll_s : float
        Polling period (s); 0 polls never (SIGHUP only).
    """

    def __init__(self, path: Path, apply: Callable[[AppConfig], Awaitable[None]],
                 rejected: Callable[[str], None], poll_s: float) -> None:
        self.path = Path(path)
        self.apply = apply
        self.rejected = rejected
        self.poll_s = poll_s
        self.stamp = file_stamp(self.path)
        self._lock = asyncio.Lock()

    def set_period(self, poll_s: float) -> None:
        """Poll every ``poll_s`` seconds from the next wait on (0: never; SIGHUP only)."""
        self.poll_s = poll_s

    async def reload(self, why: str) -> tuple[bool, str]:
        """Load the file now; apply it when valid.

        Returns
        -------
        (bool, str)
            Whether it was applied, and the error message when it was not.
        """
        async with self._lock:
            # the default pool, not the poll's own thread: a reload also runs without run() (SIGHUP, tests)
            self.stamp = await asyncio.to_thread(file_stamp, self.path)
            loop = asyncio.get_running_loop()
            try:
                cfg = await loop.run_in_executor(None, load_service_config, self.path)
            except ConfigError as exc:
                msg = str(exc)
            except Exception as exc:  # whatever the file holds, the watcher lives on
                log.exception("loading %s", self.path)
                msg = f"{self.path}: cannot be loaded ({exc!r}); fix the file"
            else:
                log.info("configuration %s reloaded (%s)", self.path, why)
                await self.apply(cfg)
                return True, ""
            log.error("configuration %s (%s) rejected; the last good one keeps running:\n%s", self.path, why, msg)
            self.rejected(msg)
            return False, msg

    async def run(self) -> None:
        """Poll until cancelled (never returns by itself; with ``poll_s`` 0 it only waits for a new period).

        The file is looked at (a ``stat``, a file-system call that can wait on the disk) in a thread of the
        watcher's own, not on the event loop: the full suite once saw this poll hold the loop 295 ms with 1 ms
        of CPU. One thread of its own rather than the loop's default pool, whose size would then vary with when
        a poll meets other work.
        """
        loop = asyncio.get_running_loop()
        stat = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="scan3d-config-stat")
        try:
            while True:
                if self.poll_s <= 0:
                    await asyncio.sleep(IDLE_RECHECK_S)  # a reload may turn polling on
                    continue
                await asyncio.sleep(self.poll_s)
                if await loop.run_in_executor(stat, file_stamp, self.path) == self.stamp:
                    continue
                await asyncio.sleep(SETTLE_S)
                if await loop.run_in_executor(stat, file_stamp, self.path) is None:
                    continue  # an editor's rename in progress, or removed: keep the running config
                await self.reload("file changed")
        finally:
            stat.shutdown(wait=False, cancel_futures=True)
