"""The health check behind systemd's watchdog: the scan worker, the writer thread and the control socket are
alive and making progress.

The watchdog is pinged only when the check passes, so a wedged service (a scan or a write past its deadline,
a writer thread stuck on a hung share, a control socket that no longer answers, a blocked event loop) stops
the pings and systemd restarts it (``WatchdogSec=``, ``Restart=on-failure``). The check runs every half
watchdog period (``$WATCHDOG_USEC``), or every :data:`HEALTH_PERIOD_S` without systemd; a failure is
published (state ``fault``, last error) when it starts and when it ends.

- scan worker: idle, it heartbeats every :data:`~appliance.service.jobs.HEARTBEAT_S`; busy, its job has a
  deadline (``service.scan_timeout_s`` plus :data:`~appliance.service.jobs.WRITE_DEADLINE_S`).
- writer: a no-op handed to the writer thread comes back within :data:`WRITER_DEADLINE_S`.
- control socket: a ``ping`` through the socket itself is answered within :data:`CONTROL_DEADLINE_S`.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from concurrent.futures import Future

from appliance.service.notify import SdNotifier, watchdog_interval_s
from appliance.service.parts import Files, HealthHost, RigView, Worker
from appliance.service.state import State, StatusBoard

log = logging.getLogger(__name__)

# Module-level so tests can shorten them.
HEALTH_PERIOD_S = 2.0  # check this often when systemd's watchdog is off
WORKER_STALE_S = 10.0  # an idle scan worker silent this long is dead
WRITER_DEADLINE_S = 120.0  # the writer thread must pick up a no-op within this (it may be finishing a write)
CONTROL_DEADLINE_S = 5.0  # the control socket must answer a ping within this


class HealthCheck:
    """Checks one service and pings the watchdog while it is healthy.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (a failure is published there).
    host : HealthHost
        The configuration (``service.watchdog``) and the control socket to probe.
    notifier : SdNotifier
        Where the watchdog pings go.
    worker : Worker
        The scan worker's signs of life.
    rig : RigView
        The rig part (the state to go back to when the check passes again).
    files : Files
        The writer thread (probed with a no-op).
    """

    def __init__(self, board: StatusBoard, host: HealthHost, notifier: SdNotifier, worker: Worker, rig: RigView,
                 files: Files) -> None:
        self.board = board
        self.host = host
        self.notifier = notifier
        self.worker = worker
        self.rig = rig
        self.files = files
        self.problem = ""  # '' while healthy
        self.last_ok = time.monotonic()
        self._probe: Future[float] | None = None
        self._probe_sent = 0.0

    def _worker_problem(self, now: float) -> str:
        jobs = self.worker
        if jobs.active is not None:
            if jobs.deadline is not None and now > jobs.deadline:
                return (f"scan worker: scan {jobs.scan_id or '(starting)'} is {now - jobs.deadline:.0f} s past its "
                        "deadline (service.scan_timeout_s + writing)")
            return ""
        if now - jobs.heartbeat > WORKER_STALE_S:
            return f"scan worker: no heartbeat for {now - jobs.heartbeat:.0f} s"
        return ""

    def _writer_problem(self, now: float) -> str:
        if self._probe is None or self._probe.done():
            try:
                self._probe = self.files.submit(time.monotonic)
            except RuntimeError as exc:  # the executor was shut down
                return f"writer thread: {exc}"
            self._probe_sent = now
            return ""
        waited = now - self._probe_sent
        if waited > WRITER_DEADLINE_S:
            return f"writer thread: no answer for {waited:.0f} s (a write to the share hangs?)"
        return ""

    async def _control_problem(self) -> str:
        control = self.host.control_path
        if control is None:
            return "control socket: not listening"
        path = str(control)
        try:
            async with asyncio.timeout(CONTROL_DEADLINE_S):
                reader, writer = await asyncio.open_unix_connection(path)
                try:
                    writer.write(b'{"cmd": "ping"}\n')
                    await writer.drain()
                    line = await reader.readline()
                finally:
                    writer.close()
            reply = json.loads(line) if line else {}
        except TimeoutError:
            return f"control socket {path}: no answer within {CONTROL_DEADLINE_S:g} s"
        except (OSError, ValueError) as exc:
            return f"control socket {path}: {exc}"
        if not isinstance(reply, dict) or not reply.get("ok"):
            return f"control socket {path}: unexpected reply {reply!r}"
        return ""

    async def check(self) -> str:
        """One check; returns what is wrong ('' when healthy)."""
        now = time.monotonic()
        problems = [p for p in (self._worker_problem(now), self._writer_problem(now)) if p]
        control = await self._control_problem()
        if control:
            problems.append(control)
        return "; ".join(problems)

    async def run(self) -> None:
        """Check, publish changes, ping the watchdog while healthy (until cancelled)."""
        interval = watchdog_interval_s() if self.host.cfg.service.watchdog else None
        while True:
            problem = await self.check()
            if not problem:
                self.last_ok = time.monotonic()
                if interval is not None:
                    self.notifier.watchdog()
            if problem != self.problem:
                self._changed(problem)
            await asyncio.sleep(interval if interval is not None else HEALTH_PERIOD_S)

    def _changed(self, problem: str) -> None:
        b = self.board
        if problem:
            log.error("health check failed: %s; the watchdog is no longer pinged", problem)
            b.error("service", f"not healthy: {problem}; systemd restarts the service when its watchdog "
                               "runs out")
            b.set_state(State.FAULT, f"not healthy: {problem}")
        else:
            log.info("health check passes again (was: %s)", self.problem)
            if b.state == State.FAULT:
                b.set_state(self.rig.idle_state(), "ready" if self.rig.ready else b.detail)
        self.problem = problem
