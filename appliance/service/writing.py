"""Writing and spooling: the scan files on the share (or the spool), the spool flush, the persistent state.

Everything here touches files, so it runs in the one writer thread (``scan3d-writer``); the coroutines only
hand work to it. The persistent state (``service-state.json`` in ``service.state_directory``) keeps the scan
counter and the last scans across restarts.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any, TypeVar

from appliance.config import AppConfig
from appliance.errors import ApplianceError
from appliance.output.atomic import write_bytes_atomic
from appliance.output.share import ShareWriter, WriteOutcome
from appliance.service import memory
from appliance.service.state import ScanRecord, StatusBoard

log = logging.getLogger(__name__)

# Module-level so tests can shorten it.
SPOOL_RETRY_S = 2.0  # how often a non-empty spool is offered to the share
STATE_FILE = "service-state.json"

T = TypeVar("T")


class ScanOutput:
    """The share writer, its thread, the spool flush and the persistent state of one service.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (this part writes its ``share`` and the ``spool_dropped`` counter).
    cfg : AppConfig
        The configuration at start (:meth:`configure` takes each applied reload).
    """

    def __init__(self, board: StatusBoard, cfg: AppConfig) -> None:
        self.board = board
        self.cfg = cfg
        self.writer = ShareWriter(cfg.output)
        self.counter = 0
        self._ex = ThreadPoolExecutor(1, thread_name_prefix="scan3d-writer")

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` in the writer thread."""
        return await asyncio.get_running_loop().run_in_executor(self._ex, fn, *args)

    def submit(self, fn: Callable[[], T]) -> Future[T]:
        """Hand ``fn()`` to the writer thread without waiting (the health check's probe)."""
        return self._ex.submit(fn)

    def configure(self, old: AppConfig, new: AppConfig) -> None:
        """A new configuration: a new share writer when the output section changed."""
        self.cfg = new
        if new.output != old.output:
            self.writer = ShareWriter(new.output)

    async def start(self) -> None:
        """Load the persistent state, remove what a crash left half-written."""
        self.load_state()
        await self.call(self.writer.cleanup_incomplete)

    async def spool_loop(self) -> None:
        """Offer the spool to the share every :data:`SPOOL_RETRY_S` while not busy (runs until cancelled)."""
        while True:
            await asyncio.sleep(SPOOL_RETRY_S)
            if self.board.busy:
                continue
            moved = await self.call(self._flush_spool)
            if moved:
                self.board.share = await self.call(self.writer.status)
                self.board.changed()

    async def scan_written(self) -> None:
        """A scan's files are written: look at the share again, save the state file, give the scan's
        temporaries back to the system (all in the writer thread, after the files)."""
        self.board.share = await self.call(self.writer.status)
        await self.save_state()
        await self.call(memory.trim)

    def _flush_spool(self) -> list[WriteOutcome]:
        if not self.writer.spool_entries():
            return []
        moved = self.writer.flush_spool()
        dropped = self.writer.enforce_retention()
        if dropped:
            self.board.counters["spool_dropped"] += len(dropped)
        return moved

    # --- persistent state (scan counter, last scans) --------------------------------------------

    def state_path(self) -> Path:
        """``service-state.json`` in ``service.state_directory``."""
        return Path(self.cfg.service.state_directory) / STATE_FILE

    def load_state(self) -> None:
        """Read the scan counter and the last scans (a missing or broken file starts from zero)."""
        try:
            data = json.loads(self.state_path().read_text())
            self.counter = int(data.get("counter", 0))
            for r in data.get("last_scans", []):
                self.board.last_scans.append(ScanRecord(**r))
        except (OSError, ValueError, TypeError):
            pass

    async def next_number(self) -> int:
        """The next scan number, persisted before it is used (a number is never reused, even after a kill)."""
        self.counter += 1
        await self.save_state()
        return self.counter

    async def save_state(self) -> None:
        """Write the scan counter and the last scans (atomically, in the writer thread; a failure is logged)."""
        data = {"counter": self.counter, "last_scans": [asdict(r) for r in self.board.last_scans]}
        await self.call(self._write_state, json.dumps(data).encode())

    def _write_state(self, data: bytes) -> None:
        path = self.state_path()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(path, data)
        except (OSError, ApplianceError) as exc:
            log.warning("state file %s: %s", path, exc)

    def close(self) -> None:
        """Wait for the writer thread to finish what it has and stop it."""
        self._ex.shutdown(wait=True)
