"""Publishing the service's state: systemd's STATUS line, the mDNS TXT record and the controller's lamps.

Subscribed to the :class:`~appliance.service.state.StatusBoard`: every change of state is published, not just
logged. Lamps: ready (idle), busy (scanning/processing/writing), fault (fault, or a short blink when a trigger
is refused).
"""

from __future__ import annotations

import asyncio
import importlib
import logging
import time
from typing import Any

from appliance import __version__
from appliance.errors import ApplianceError
from appliance.service.notify import SdNotifier
from appliance.service.parts import Configured, RigView
from appliance.service.state import State, StatusBoard

log = logging.getLogger(__name__)

# Module-level so tests can shorten it.
REFUSED_BLINK_S = 0.5  # the fault lamp blinks this long when a trigger is refused


class Publisher:
    """STATUS=, mDNS TXT and lamps of one service.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (read only; :meth:`publish` is subscribed to it).
    host : Configured
        The running configuration (mDNS section, share, serial).
    notifier : SdNotifier
        Where the STATUS= line goes.
    rig : RigView
        The rig part: its trigger device has the lamps.
    """

    def __init__(self, board: StatusBoard, host: Configured, notifier: SdNotifier, rig: RigView) -> None:
        self.board = board
        self.host = host
        self.notifier = notifier
        self.rig = rig
        self.announcer: Any = None
        self._last_status = ""
        self._blink_until = 0.0
        self._lamps: tuple[bool, bool, bool] | None = None
        self._lamp_task: asyncio.Task[None] | None = None
        self._lamp_writes: set[asyncio.Task[Any]] = set()

    def txt_record(self) -> dict[str, str]:
        """The mDNS TXT record: state, scans done, last scan id, share location, version, serial, and the last
        scan's calibration health (``calibration``: ok | drifting | bad | not measured)."""
        b, cfg = self.board, self.host.cfg
        txt = {"txtvers": "1", "state": str(b.state), "scans": str(b.counters["scans_done"]),
               "last": b.last_scan_id(), "share": str(cfg.output.directory), "version": __version__,
               "serial": cfg.serial}
        health = b.calibration_health()
        if health:
            txt["calibration"] = str(health.get("status", ""))
        if b.state == State.FAULT and b.last_error is not None:
            txt["fault"] = b.last_error.message[:120]
        return txt

    def publish(self, board: StatusBoard) -> None:
        """The board changed: send what differs."""
        line = board.one_line()
        if line != self._last_status:
            self._last_status = line
            self.notifier.status(line)
        if self.announcer is not None:
            self.announcer.set_txt(self.txt_record())
        self.set_lamps()

    def reset_lamps(self) -> None:
        """Forget what the lamps show (a new trigger device): the next change sets all three."""
        self._lamps = None

    def set_lamps(self) -> None:
        """Show ready/busy/fault on the trigger device's lamps (when it has any)."""
        trig = self.rig.trigger
        if trig is None or not trig.has_lamps:
            return
        b = self.board
        blink = time.monotonic() < self._blink_until
        lamps = (b.state == State.IDLE, b.busy, b.state == State.FAULT or blink)
        if lamps == self._lamps:
            return
        self._lamps = lamps
        task = asyncio.get_running_loop().create_task(trig.set_leds(*lamps))
        self._lamp_writes.add(task)
        task.add_done_callback(self._lamp_written)

    def _lamp_written(self, task: asyncio.Task[Any]) -> None:
        self._lamp_writes.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.debug("lamps: %s", task.exception())

    def blink_refused(self) -> None:
        """Blink the fault lamp for :data:`REFUSED_BLINK_S` (a refused trigger)."""
        self._blink_until = time.monotonic() + REFUSED_BLINK_S
        self.set_lamps()

        async def unblink() -> None:
            await asyncio.sleep(REFUSED_BLINK_S)
            self.set_lamps()

        if self._lamp_task is None or self._lamp_task.done():
            self._lamp_task = asyncio.get_running_loop().create_task(unblink())

    async def start_mdns(self) -> None:
        """Announce the service over mDNS (when enabled); a failure is published, never raised."""
        m = self.host.cfg.service.mdns
        if not m.enabled:
            return
        mdns = await asyncio.to_thread(importlib.import_module, "appliance.output.mdns")  # zeroconf: slow import
        try:
            ann = mdns.MdnsAnnouncer(m)
            await ann.start(self.txt_record())
        except (OSError, ApplianceError) as exc:
            self.board.error("mdns", f"mDNS announcement on {list(m.interfaces)} failed: {exc}")
            log.error("mDNS disabled: %s", exc)
            return
        self.announcer = ann
        ann.set_txt(self.txt_record())  # what changed while it was probing

    async def stop_mdns(self) -> None:
        """Withdraw the mDNS announcement."""
        if self.announcer is not None:
            ann, self.announcer = self.announcer, None
            try:
                await ann.close()
            except Exception as exc:  # withdrawing is best effort (the network may be gone)
                log.debug("mDNS close: %s", exc)

    async def close(self) -> None:
        """Stop mDNS and the lamp tasks."""
        await self.stop_mdns()
        tasks = [t for t in (self._lamp_task, *self._lamp_writes) if t is not None]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
