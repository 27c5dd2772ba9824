"""``scan3d run``: the appliance service, one asyncio process — its lifecycle and supervision.

Start-up phases: load config → connect hardware → warm the numba kernels → ready (``READY=1`` to systemd).
Then a trigger (the rig's button, the control socket, ``scan3d trigger``, Enter with ``--stdin-button``)
starts a scan: ``scanning`` (projecting, frames decoded as they arrive) → ``processing`` → ``writing``
(share or spool) → ``idle``. A trigger while busy is refused or queued (``service.busy_policy``),
logged, counted and shown on the controller's lamps. Absent or failing hardware puts the service in
``fault`` and is retried with backoff; the service stays up and says so (status, STATUS=, mDNS, lamps).
SIGHUP or an edit of the file reloads the configuration; SIGTERM finishes (or aborts) the running scan
and exits 0.

The parts, one module each: :mod:`~appliance.service.rig` (connecting the hardware: the one owner of the rig
and its scanner, built by the factory handed in), :mod:`~appliance.service.jobs` (the scan job queue and
worker), :mod:`~appliance.service.writing` (share, spool, persistent state), :mod:`~appliance.service.publish`
(STATUS=, mDNS TXT, lamps), :mod:`~appliance.service.health` (the watchdog's check),
:mod:`~appliance.service.tuning` (``scan3d tune`` on the rig) and :mod:`~appliance.service.handlers`
(control-socket commands). This module builds and wires them: each gets the status board and the small
protocol of :mod:`~appliance.service.parts` it needs, never the service itself.
The event loop never blocks: devices, numba work and file writes run in threads.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import datetime as dt
import functools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from appliance._numba_cache import prune_stale
from appliance.config import AppConfig, load_config
from appliance.errors import ConfigError
from appliance.hardware.base import TriggerEvent
from appliance.output.share import ShareWriter
from appliance.service.control import ControlServer
from appliance.service.faces import ServiceFaces
from appliance.service.handlers import ControlHandlers
from appliance.service.health import HealthCheck
from appliance.service.jobs import Job, ScanJobs
from appliance.service.memory import rss_mb, tune_malloc
from appliance.service.notify import SdNotifier
from appliance.service.publish import Publisher
from appliance.service.reload import ConfigWatcher
from appliance.service.rig import RigManager, build_scanner, current_threading_layer, select_threading_layer
from appliance.service.state import Phase, ScanRecord, State, StatusBoard
from appliance.service.tuning import Tuner
from appliance.service.writing import STATE_FILE, ScanOutput

__all__ = ["STATE_FILE", "Service", "TriggerEvent", "run_service"]


if TYPE_CHECKING:  # the scan machinery is imported when the rig is built, not at start-up
    from appliance.hardware.registry import Rig
    from appliance.scan import Scanner
    from appliance.service.parts import ScannerFactory

log = logging.getLogger(__name__)

AFTER_SCAN_GRACE_S = 10.0  # at stop, the last scan's bookkeeping gets this long
ABORT_WAIT_S = 5.0  # at stop, an aborted scan gets this long to unwind
WRITER_CLOSE_WAIT_S = 30.0  # at stop, the writer thread gets this long to finish its work
TRACEBACK_LOG_WAIT_S = 5.0  # at stop, a failed task's traceback gets this long to reach the log

StateListener = Callable[[StatusBoard], None]
ScanListener = Callable[[ScanRecord], None]


class Extension(Protocol):
    """Something that runs with the service (e.g. a line-integration face)."""

    async def start(self) -> None: ...

    async def apply(self, new: AppConfig) -> None: ...

    async def close(self) -> None: ...


# Sections whose change needs the rig rebuilt (everything else is applied in place).
HARDWARE_KEYS = ("cameras", "projector", "trigger", "calibration_file", "sequence", "reconstruction",
                 "virtual_rig")


class Service:
    """The appliance service.

    Parameters
    ----------
    config_path : Path
        The configuration file (watched for changes).
    cfg : AppConfig, optional
        Already loaded configuration (loaded from ``config_path`` when None).
    control_socket : Path, optional
        Overrides ``service.control_socket``.
    scans : int, optional
        Stop after this many successful scans.
    stdin_button : bool
        Enter on standard input presses the button.
    notifier : SdNotifier, optional
        sd_notify sender (from ``$NOTIFY_SOCKET`` when None).
    ground_truth : bool
        On a virtual rig, log each scan's error against the rig's ground truth (after its files are
        written, off the event loop; a demonstration aid, not for production).
    make_scanner : ScannerFactory, optional
        Builds (not opens) the rig and its scanner for a configuration, in a thread
        (:func:`~appliance.service.rig.build_scanner` when None); tests hand in fakes.
    """

    def __init__(self, config_path: Path, cfg: AppConfig | None = None, *, control_socket: Path | None = None,
                 scans: int | None = None, stdin_button: bool = False,
                 notifier: SdNotifier | None = None, ground_truth: bool = False,
                 make_scanner: ScannerFactory | None = None) -> None:
        self.config_path = Path(config_path)
        self.cfg = cfg if cfg is not None else load_config(self.config_path)
        self.socket_override = control_socket
        self.stdin_button = stdin_button
        self.notifier = notifier if notifier is not None else SdNotifier.from_env()
        self.board = StatusBoard(self.cfg.serial, str(self.config_path))
        self.board.config_loaded_utc = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        self.control: ControlServer | None = None
        self.watcher: ConfigWatcher | None = None
        select_threading_layer()  # before any parallel kernel runs
        tune_malloc()  # before the big allocations
        self.scan_lock = asyncio.Lock()  # held by a scan and by every change of the rig
        # the parts: each gets the board and a protocol of what it may call (appliance.service.parts)
        self.output = ScanOutput(self.board, self.cfg)
        self.hardware = RigManager(self.board, self, make_scanner or build_scanner, self.scan_lock)
        self.publisher = Publisher(self.board, self, self.notifier, self.hardware)
        self.jobs = ScanJobs(self.board, self, self.hardware, self.output, self.publisher, self.scan_lock,
                             max_scans=scans, ground_truth=ground_truth)
        self.tuner = Tuner(self.board, self, self.hardware, self.jobs, self.scan_lock)
        self.handlers = ControlHandlers(self.board, self)
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._traceback_logs: set[asyncio.Future[None]] = set()  # tracebacks still being written
        self._ready_sent = False
        self._scan_listeners: list[ScanListener] = []
        self.health = HealthCheck(self.board, self, self.notifier, self.jobs, self.hardware, self.output)
        self.exit_status = 0
        self._extensions: list[Extension] = []
        self.faces = ServiceFaces(self)  # HTTP + status page, MQTT, OPC UA: each off unless configured
        self.add_extension(self.faces)

    # --- the public surface ----------------------------------------------------------------------

    @property
    def socket_path(self) -> Path:
        """The control socket in use."""
        return self.socket_override or self.cfg.service.control_socket

    @property
    def writer(self) -> ShareWriter:
        """The share writer in use."""
        return self.output.writer

    @property
    def rig(self) -> Rig | None:
        """The rig built last (owned by the rig part)."""
        return self.hardware.rig

    @property
    def scanner(self) -> Scanner | None:
        """The connected rig's scanner (None while not connected; owned by the rig part)."""
        return self.hardware.scanner

    @property
    def successful_scans(self) -> int:
        """Scans that ended with their files written (since start)."""
        return self.jobs.successful_scans

    @property
    def control_path(self) -> Path | None:
        """The control socket being served (None while none is)."""
        return self.control.path if self.control is not None else None

    @property
    def stopping(self) -> bool:
        """True once a stop was requested."""
        return self._stop.is_set()

    def request_scan(self, event: TriggerEvent) -> tuple[str, Job | None]:
        """Accept, queue or refuse a trigger; returns (``started``/``queued``/``refused: why``, job)."""
        return self.jobs.request(event)

    def status(self) -> dict[str, Any]:
        """What ``scan3d status --json`` shows (the share as last seen; :meth:`status_async` looks again)."""
        snap = self.board.snapshot()
        snap["control_socket"] = str(self.socket_path)
        snap["rss_mb"] = rss_mb()
        snap["numba_threading_layer"] = current_threading_layer() or "(no parallel kernel run yet)"
        return snap

    def subscribe(self, on_state: StateListener | None = None, on_scan: ScanListener | None = None) -> None:
        """Follow the service: ``on_state(board)`` after every change, ``on_scan(record)`` after every finished
        (or failed) scan. Listeners run on the event loop and must not block; one that raises is logged."""
        if on_state is not None:
            self.board.subscribe(on_state)
        if on_scan is not None:
            self._scan_listeners.append(on_scan)

    def unsubscribe(self, on_state: StateListener | None = None, on_scan: ScanListener | None = None) -> None:
        """Stop calling the listeners given to :meth:`subscribe`."""
        if on_state is not None:
            self.board.unsubscribe(on_state)
        if on_scan is not None and on_scan in self._scan_listeners:
            self._scan_listeners.remove(on_scan)

    def add_extension(self, ext: Extension) -> None:
        """Run ``ext`` with the service: ``start()`` once the control socket is up, ``apply(cfg)`` after each
        applied reload, ``close()`` at shutdown (before the control socket closes). Call before :meth:`run`."""
        self._extensions.append(ext)

    def scan_finished(self, record: ScanRecord) -> None:
        """Tell the scan listeners (called by the scan worker)."""
        for fn in list(self._scan_listeners):
            try:
                fn(record)
            except Exception:  # a broken listener must not stop the service
                log.exception("scan listener %r failed", fn)

    def txt_record(self) -> dict[str, str]:
        """The mDNS TXT record (see :meth:`Publisher.txt_record`)."""
        return self.publisher.txt_record()

    async def status_async(self) -> dict[str, Any]:
        """What ``scan3d status --json`` shows, with a fresh look at the share."""
        snap = self.status()
        snap["share"] = await asyncio.to_thread(self.writer.status)  # any thread; waits for neither share nor writer
        return snap

    async def reload(self, why: str) -> tuple[bool, str]:
        """Load the configuration file now and apply it when valid: (applied, error message)."""
        if self.watcher is None:
            return False, "not started"
        return await self.watcher.reload(why)

    async def tune(self, time_budget_ms: float, apply: bool) -> dict[str, Any]:
        """``scan3d tune`` on the rig: probe, choose the exposures and, with ``apply``, write and reload them."""
        return await self.tuner.tune(time_budget_ms, apply)

    async def tune_apply(self, exposures_us: list[int] | None) -> dict[str, Any]:
        """Write the last tune's choice into the configuration file and reload it."""
        return await self.tuner.apply(exposures_us)

    # --- what the rig part reports (appliance.service.parts.RigHost) ------------------------------

    def rig_ready(self) -> None:
        """The rig is connected and warm: the scan worker looks at its queue."""
        self.jobs.wake()

    def rig_lost(self, reason: str) -> None:
        """Connecting the rig failed: the queued triggers are dropped with the reason."""
        self.jobs.drop_queued(f"scan not started: hardware: {reason}")

    def trigger_opening(self) -> None:
        """A trigger device is about to open: the next change sets all its lamps."""
        self.publisher.reset_lamps()

    # --- lifecycle -------------------------------------------------------------------------------

    async def run(self) -> int:
        """Run until SIGTERM/SIGINT (or ``scans`` done); returns the exit status.

        0 after a requested stop; 1 when a part of the service ended unexpectedly (state ``fault`` with the
        reason; systemd's ``Restart=on-failure`` starts it again).
        """
        loop = asyncio.get_running_loop()
        self._install_signals(loop)
        self.board.subscribe(self.publisher.publish)
        self.board.set_state(State.STARTING, "loading configuration", Phase.LOAD_CONFIG)
        try:
            from appliance.config.loader import prepare_service_folders  # a state folder that is a file: no start
            await asyncio.to_thread(prepare_service_folders, self.cfg, str(self.config_path))
            await self.output.start()
            self.control = ControlServer(self.socket_path, self.handlers.handle)
            await self.control.start()
        except BaseException:  # e.g. another service on the socket: nothing may be left running
            self.control = None
            await asyncio.to_thread(self.output.close)
            self.board.unsubscribe(self.publisher.publish)
            raise
        self.spawn(self.publisher.start_mdns(), "mdns", critical=False)  # probing takes ~2 s: never delays the start
        self.spawn(self._prune_kernel_cache(), "kernel-cache", critical=False)  # once a process, off the loop
        self.watcher = ConfigWatcher(self.config_path, self._apply_config, self._config_rejected,
                                     self.cfg.service.config_poll_s)
        self.spawn(self.health.run(), "health")
        self.spawn(self.watcher.run(), "config-watcher")
        self.spawn(self.output.spool_loop(), "spool")
        self.spawn(self.hardware.loop(), "hardware")
        self.spawn(self.jobs.worker(), "scan-worker")
        for ext in self._extensions:
            await ext.start()
        if self.stdin_button:
            self._start_stdin_reader(loop)
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()
        return self.exit_status

    @staticmethod
    async def _prune_kernel_cache() -> None:
        """Delete the compiled kernels of older versions (see ``prune_stale``), once at start."""
        gone = await asyncio.to_thread(prune_stale)
        if gone:
            log.info("deleted the compiled kernels of %d older version(s) from %s", len(gone), gone[0].parent)

    def request_stop(self) -> None:
        """Begin a clean shutdown (what SIGTERM does)."""
        self._stop.set()

    def _install_signals(self, loop: asyncio.AbstractEventLoop) -> None:
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(signal.SIGTERM, self.request_stop)
            loop.add_signal_handler(signal.SIGINT, self.request_stop)
            loop.add_signal_handler(signal.SIGHUP, self._sighup)

    def _sighup(self) -> None:
        if self.watcher is not None:
            self.spawn(self.watcher.reload("SIGHUP"), "reload", critical=False)

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str, *, critical: bool = True) -> asyncio.Task[Any]:
        """Run ``coro`` as a task of the service (cancelled at shutdown).

        A critical task runs for the life of the service: if it ends other than by cancellation, the service
        reports ``fault`` with the reason and stops with exit status 1 (see :meth:`fail`).
        """
        task = asyncio.get_running_loop().create_task(coro, name=f"scan3d-{name}")
        self._tasks.append(task)
        task.add_done_callback(functools.partial(self._task_done, critical))
        return task

    def _task_done(self, critical: bool, task: asyncio.Task[Any]) -> None:
        with contextlib.suppress(ValueError):
            self._tasks.remove(task)
        if task.cancelled():
            return  # only the service cancels its tasks
        exc = task.exception()
        name = task.get_name()
        if not critical:
            if exc is not None:
                log.error(f"task {name} failed: {exc!r}")
                self.board.error("service", f"internal task {name} failed: {exc!r}")
                self._log_traceback(f"task {name}", exc)
            return
        if self.stopping and exc is None:
            return
        self.fail(f"internal task {name} " + (f"failed: {exc!r}" if exc is not None else "ended unexpectedly"),
                  exc)

    def fail(self, reason: str, exc: BaseException | None = None) -> None:
        """A part of the service is gone: publish ``fault`` with ``reason``, stop, exit with status 1."""
        # one preformatted line on the loop; the traceback from a thread (see _log_traceback)
        log.critical(f"{reason}; stopping with exit status 1 (systemd restarts the service)")
        self.exit_status = 1
        self.board.error("service", reason)
        self.board.set_state(State.FAULT, reason)
        self.request_stop()
        if exc is not None:
            self._log_traceback(reason, exc)

    def _log_traceback(self, what: str, exc: BaseException) -> None:
        """Log ``exc``'s traceback from a short-lived thread; :meth:`_shutdown` waits for it.

        Formatting a traceback reads the source files and parses their lines: 5-30 ms of CPU the first time
        in a process, which the event loop must not carry (triggers, the watchdog and the status page wait
        behind it). The line saying what failed is logged on the loop first, so the order in the log is
        the failure, then its traceback.
        """
        written: concurrent.futures.Future[None] = concurrent.futures.Future()

        def write() -> None:
            try:
                log.error("traceback of %s:", what, exc_info=exc)
            finally:
                written.set_result(None)

        threading.Thread(target=write, name="scan3d-log-traceback", daemon=True).start()
        logged = asyncio.wrap_future(written)
        self._traceback_logs.add(logged)
        logged.add_done_callback(self._traceback_logs.discard)

    def send_ready(self) -> None:
        """``READY=1`` to systemd, once (ready for triggers, or in fault but up)."""
        if not self._ready_sent:
            self._ready_sent = True
            self.notifier.ready(self.board.one_line())

    async def _shutdown(self) -> None:
        if self.board.state != State.FAULT or self.exit_status == 0:
            self.board.set_state(State.STOPPING, "stopping", Phase.STOPPING)
        self.notifier.stopping(self.board.one_line())
        self.jobs.drop_queued("the service is stopping; queued trigger dropped")
        current = self.jobs.current
        if current is not None and not current.done():
            grace = self.cfg.service.stop_grace_s
            log.info("stopping: letting scan finish (up to %.0f s)", grace)
            done, _ = await asyncio.wait({current}, timeout=grace)
            if not done:
                log.warning("stopping: scan not finished within %.0f s; aborting it (no file is written)",
                            grace)
                aborted = self.jobs.abort(f"aborted: the service is stopping and the scan did not finish within "
                                          f"service.stop_grace_s = {grace:g} s; no file was written")
                if aborted is not None:  # a wedged driver call may never return
                    await asyncio.wait({aborted}, timeout=ABORT_WAIT_S)
        self.jobs.abort_active(self.jobs.abort_reason)  # the waiting client gets its reply
        if self.jobs.after_scan:  # the last scan's state file (and ground-truth line) are still being written
            await asyncio.wait(set(self.jobs.after_scan), timeout=AFTER_SCAN_GRACE_S)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.hardware.close()
        await self.publisher.close()
        for ext in reversed(self._extensions):
            try:
                await ext.close()
            except Exception:  # one extension must not keep the others (or the socket) open
                log.exception("closing %r failed", ext)
        if self.control is not None:
            await self.control.close()
        closing = asyncio.ensure_future(asyncio.to_thread(self.output.close))  # a started write completes
        closed, _ = await asyncio.wait({closing}, timeout=WRITER_CLOSE_WAIT_S)
        if not closed:
            log.error("stopping: the writer thread has not finished within %.0f s (a hung share?)",
                      WRITER_CLOSE_WAIT_S)
        self.notifier.close()
        self.board.unsubscribe(self.publisher.publish)
        if self._traceback_logs:  # a fault's traceback reaches the journal before the exit
            await asyncio.wait(self._traceback_logs, timeout=TRACEBACK_LOG_WAIT_S)
        log.info("stopped after %d scans", self.board.counters["scans_done"])

    # --- configuration ---------------------------------------------------------------------------

    def _config_rejected(self, message: str) -> None:
        self.board.config_error = message
        self.board.count("reloads_rejected")
        self.board.error("config", message)

    async def _apply_config(self, new: AppConfig) -> None:
        async with self.scan_lock:  # never in the middle of a scan
            old = self.cfg
            self.cfg = new
            b = self.board
            b.config_error = ""
            b.config_loaded_utc = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
            b.serial = new.serial
            b.count("reloads")
            self.output.configure(old, new)
            if self.watcher is not None:
                self.watcher.set_period(new.service.config_poll_s)
            if self.socket_override is None and new.service.control_socket != old.service.control_socket:
                if self.control is not None:
                    await self.control.close()
                self.control = ControlServer(self.socket_path, self.handlers.handle)
                await self.control.start()
            if new.service.mdns != old.service.mdns:
                await self.publisher.stop_mdns()
                await self.publisher.start_mdns()
            if any(getattr(new, k) != getattr(old, k) for k in HARDWARE_KEYS):
                log.info("configuration changes the rig: reconnecting")
                # say so at once: until the rig is rebuilt, the old one must not look ready
                b.set_state(State.STARTING, "reconnecting for the new configuration", Phase.CONNECT)
                self.hardware.reconnect()
            for ext in self._extensions:
                await ext.apply(new)
            b.changed()

    # --- stdin button ----------------------------------------------------------------------------

    def _start_stdin_reader(self, loop: asyncio.AbstractEventLoop) -> None:
        def press() -> None:
            trig = self.hardware.trigger
            if trig is not None and hasattr(trig, "press"):
                trig.press("stdin")  # the simulated button
            else:
                self.request_scan(TriggerEvent("stdin", time.monotonic_ns(), "Enter"))

        def read() -> None:  # a daemon thread: a blocked readline never holds up the exit
            for _line in sys.stdin:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(press)

        threading.Thread(target=read, name="scan3d-stdin", daemon=True).start()
        print("press Enter to scan; Ctrl-C stops", file=sys.stderr, flush=True)


def run_service(config: Path, *, control_socket: Path | None = None, scans: int | None = None,
                stdin_button: bool = False, ground_truth: bool = False) -> int:
    """Run the service in the foreground until SIGTERM (or ``scans`` scans); returns the exit status.

    Parameters
    ----------
    config : Path
        Configuration file (reloaded on SIGHUP and on change).
    control_socket : Path, optional
        Overrides ``service.control_socket``.
    scans : int, optional
        Exit 0 after this many successful scans.
    stdin_button : bool
        Enter on standard input presses the (simulated) button.
    ground_truth : bool
        On a virtual rig, log each scan's error against ground truth.
    """
    if scans is not None and scans < 1:  # 0 or -1 would mean "for ever" without saying so
        raise ConfigError(f"run: --scans {scans}: must be at least 1 (or left out to run until stopped)")
    tune_malloc()
    cfg = load_config(config)
    if cfg.service.numba_cache_dir is not None:
        os.environ["NUMBA_CACHE_DIR"] = str(cfg.service.numba_cache_dir)
    stdin = stdin_button or bool(getattr(cfg.trigger, "stdin", False))

    async def main() -> int:
        service = Service(config, cfg, control_socket=control_socket, scans=scans, stdin_button=stdin,
                          ground_truth=ground_truth)
        return await service.run()

    return asyncio.run(main())
