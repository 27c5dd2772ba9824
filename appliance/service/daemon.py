"""``scan3d run``: the appliance service, one asyncio process.

Start-up phases: load config → connect hardware → warm the numba kernels → ready (``READY=1`` to systemd).
Then a trigger (the rig's button, the control socket, ``scan3d trigger``, Enter with ``--stdin-button``)
starts a scan: ``scanning`` (projecting, frames decoded as they arrive) → ``processing`` → ``writing``
(share or spool) → ``idle``. A trigger while busy is refused or queued (``service.busy_policy``),
logged, counted and shown on the controller's lamps. Absent or failing hardware puts the service in
``fault`` and is retried with backoff; the service stays up and says so (status, STATUS=, mDNS, lamps).
SIGHUP or an edit of the file reloads the configuration; SIGTERM finishes (or aborts) the running scan
and exits 0.

The event loop never blocks: devices, numba work and file writes run in threads.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from appliance import __version__
from appliance.config import AppConfig, load_config
from appliance.errors import ApplianceError, OutputError
from appliance.hardware.base import Camera, CameraInfo, FrameCallback, TriggerEvent
from appliance.output.atomic import write_bytes_atomic
from appliance.output.share import ShareWriter, WriteOutcome, estimate_scan_bytes
from appliance.service.control import ControlServer
from appliance.service.notify import SdNotifier, watchdog_interval_s
from appliance.service.reload import ConfigWatcher
from appliance.service.state import DeviceStatus, Phase, ScanRecord, State, StatusBoard

log = logging.getLogger(__name__)

# Module-level so tests can shorten them.
RETRY_FIRST_S = 1.0  # first wait before reconnecting hardware; doubles up to service.retry_max_s
SPOOL_RETRY_S = 2.0  # how often a non-empty spool is offered to the share
REFUSED_BLINK_S = 0.5  # the fault lamp blinks this long when a trigger is refused
STATE_FILE = "service-state.json"

# Sections whose change needs the rig rebuilt (everything else is applied in place).
HARDWARE_KEYS = ("cameras", "projector", "trigger", "calibration_file", "sequence", "reconstruction",
                 "virtual_rig")


@dataclass
class _Job:
    event: TriggerEvent
    done: asyncio.Future[ScanRecord] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())


class _WatchedCamera:
    """Wraps a camera: remembers what it said at open and reports when its frames are all in."""

    def __init__(self, cam: Camera, on_captured: Callable[[], None]) -> None:
        self.cam = cam
        self.name = cam.name
        self.info: CameraInfo | None = None
        self._on_captured = on_captured

    async def open(self) -> CameraInfo:
        self.info = await self.cam.open()
        return self.info

    async def arm(self, n_frames: int, out: Any, on_frame: FrameCallback | None = None) -> None:
        await self.cam.arm(n_frames, out, on_frame)

    async def wait_frames(self, timeout_s: float) -> None:
        try:
            await self.cam.wait_frames(timeout_s)
        finally:
            self._on_captured()

    async def close(self) -> None:
        await self.cam.close()


def _today(when: dt.datetime) -> str:
    return f"{when:%Y-%m-%d}"


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
    """

    def __init__(self, config_path: Path, cfg: AppConfig | None = None, *, control_socket: Path | None = None,
                 scans: int | None = None, stdin_button: bool = False,
                 notifier: SdNotifier | None = None, ground_truth: bool = False) -> None:
        self.config_path = Path(config_path)
        self.cfg = cfg if cfg is not None else load_config(self.config_path)
        self.socket_override = control_socket
        self.max_scans = scans
        self.stdin_button = stdin_button
        self.ground_truth = ground_truth
        self.notifier = notifier if notifier is not None else SdNotifier.from_env()
        self.board = StatusBoard(self.cfg.serial, str(self.config_path))
        self.board.config_loaded_utc = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        self.writer = ShareWriter(self.cfg.output)
        self.scanner: Any = None
        self.rig: Any = None
        self.announcer: Any = None
        self.control: ControlServer | None = None
        self.watcher: ConfigWatcher | None = None
        self.counter = 0
        self._write_ex = ThreadPoolExecutor(1, thread_name_prefix="scan3d-writer")
        self._jobs: deque[_Job] = deque()
        self._job_ready = asyncio.Event()
        self._stop = asyncio.Event()
        self._hw_changed = asyncio.Event()
        self._scan_lock = asyncio.Lock()
        self._current: asyncio.Task[ScanRecord] | None = None
        self._tasks: list[asyncio.Task[Any]] = []
        self._trigger_task: asyncio.Task[None] | None = None
        self._ready_sent = False
        self._last_status = ""
        self._blink_until = 0.0
        self._lamps: tuple[bool, bool, bool] | None = None
        self._lamp_task: asyncio.Task[None] | None = None
        self.successful_scans = 0

    # --- paths -----------------------------------------------------------------------------------

    @property
    def socket_path(self) -> Path:
        """The control socket in use."""
        return self.socket_override or self.cfg.service.control_socket

    # --- lifecycle -------------------------------------------------------------------------------

    async def run(self) -> int:
        """Run until SIGTERM/SIGINT (or ``scans`` done); returns the exit status (0)."""
        loop = asyncio.get_running_loop()
        self._install_signals(loop)
        self.board.subscribe(self._publish)
        self.board.set_state(State.STARTING, "loading configuration", Phase.LOAD_CONFIG)
        self._load_state()
        await loop.run_in_executor(self._write_ex, self.writer.cleanup_incomplete)
        self.control = ControlServer(self.socket_path, self._handle)
        await self.control.start()
        self._spawn(self._start_mdns(), "mdns")  # probing takes ~2 s: never delays the start
        self.watcher = ConfigWatcher(self.config_path, self._apply_config, self._config_rejected,
                                     self.cfg.service.config_poll_s)
        self._spawn(self._watchdog_loop(), "watchdog")
        self._spawn(self.watcher.run(), "config-watcher")
        self._spawn(self._spool_loop(), "spool")
        self._spawn(self._hardware_loop(), "hardware")
        self._spawn(self._worker(), "scan-worker")
        if self.stdin_button:
            self._start_stdin_reader(loop)
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()
        return 0

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
            self._spawn(self.watcher.reload("SIGHUP"), "reload")

    def _spawn(self, coro: Any, name: str) -> asyncio.Task[Any]:
        task = asyncio.get_running_loop().create_task(coro, name=f"scan3d-{name}")
        self._tasks.append(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        with contextlib.suppress(ValueError):
            self._tasks.remove(task)
        if not task.cancelled() and task.exception() is not None:
            exc = task.exception()
            log.error("task %s failed: %r", task.get_name(), exc, exc_info=exc)
            self.board.error("service", f"internal task {task.get_name()} failed: {exc!r}")

    async def _shutdown(self) -> None:
        self.board.set_state(State.STOPPING, "stopping", Phase.STOPPING)
        self.notifier.stopping(self.board.one_line())
        for job in self._jobs:  # queued, not started: refused
            if not job.done.done():
                job.done.set_exception(ApplianceError("the service is stopping; queued trigger dropped"))
        self._jobs.clear()
        if self._current is not None and not self._current.done():
            grace = self.cfg.service.stop_grace_s
            log.info("stopping: letting scan finish (up to %.0f s)", grace)
            done, _ = await asyncio.wait({self._current}, timeout=grace)
            if not done:
                log.warning("stopping: scan not finished within %.0f s; aborting it (no file is written)",
                            grace)
                self._current.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await self._current
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._close_hardware()
        if self.announcer is not None:
            with contextlib.suppress(Exception):
                await self.announcer.close()
            self.announcer = None
        if self.control is not None:
            await self.control.close()
        if self._lamp_task is not None:
            self._lamp_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._lamp_task
        self._write_ex.shutdown(wait=True)
        self.notifier.close()
        self.board.unsubscribe(self._publish)
        log.info("stopped after %d scans", self.board.counters["scans_done"])

    # --- publishing: STATUS=, mDNS TXT, lamps ----------------------------------------------------

    def txt_record(self) -> dict[str, str]:
        """The mDNS TXT record: state, scans done, last scan id, share location, version, serial."""
        b = self.board
        txt = {"txtvers": "1", "state": str(b.state), "scans": str(b.counters["scans_done"]),
               "last": b.last_scan_id(), "share": str(self.cfg.output.directory), "version": __version__,
               "serial": self.cfg.serial}
        if b.state == State.FAULT and b.last_error is not None:
            txt["fault"] = b.last_error.message[:120]
        return txt

    def _publish(self, board: StatusBoard) -> None:
        line = board.one_line()
        if line != self._last_status:
            self._last_status = line
            self.notifier.status(line)
        if self.announcer is not None:
            self.announcer.set_txt(self.txt_record())
        self._set_lamps()

    def _set_lamps(self) -> None:
        trig = self.rig.trigger if self.rig is not None else None
        fn = getattr(trig, "set_leds", None) or getattr(trig, "set_lamps", None)
        if fn is None:
            return
        s = self.board.state
        blink = time.monotonic() < self._blink_until
        lamps = (s == State.IDLE, self.board.busy, s == State.FAULT or blink)
        if lamps == self._lamps:
            return
        self._lamps = lamps
        try:
            res = fn(*lamps)
        except ApplianceError as exc:
            log.debug("lamps: %s", exc)
            return
        if asyncio.iscoroutine(res):
            task = asyncio.get_running_loop().create_task(res)
            task.add_done_callback(lambda t: t.cancelled() or t.exception())

    def _blink_refused(self) -> None:
        self._blink_until = time.monotonic() + REFUSED_BLINK_S
        self._set_lamps()

        async def unblink() -> None:
            await asyncio.sleep(REFUSED_BLINK_S)
            self._set_lamps()

        if self._lamp_task is None or self._lamp_task.done():
            self._lamp_task = asyncio.get_running_loop().create_task(unblink())

    async def _start_mdns(self) -> None:
        m = self.cfg.service.mdns
        if not m.enabled:
            return
        from appliance.output.mdns import MdnsAnnouncer

        try:
            ann = MdnsAnnouncer(m)
            await ann.start(self.txt_record())
        except (OSError, ApplianceError) as exc:
            self.board.error("mdns", f"mDNS announcement on {list(m.interfaces)} failed: {exc}")
            log.error("mDNS disabled: %s", exc)
            return
        self.announcer = ann
        ann.set_txt(self.txt_record())  # what changed while it was probing

    # --- watchdog, spool -------------------------------------------------------------------------

    async def _watchdog_loop(self) -> None:
        interval = watchdog_interval_s()
        if interval is None or not self.cfg.service.watchdog:
            return
        while True:  # pinged from the loop itself: a blocked loop stops the pings
            self.notifier.watchdog()
            await asyncio.sleep(interval)

    async def _spool_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(SPOOL_RETRY_S)
            if self.board.busy:
                continue
            moved = await loop.run_in_executor(self._write_ex, self._flush_spool)
            if moved:
                self.board.share = await loop.run_in_executor(self._write_ex, self.writer.status)
                self.board.changed()

    def _flush_spool(self) -> list[WriteOutcome]:
        if not self.writer.spool_entries():
            return []
        moved = self.writer.flush_spool()
        dropped = self.writer.enforce_retention()
        if dropped:
            self.board.counters["spool_dropped"] += len(dropped)
        return moved

    # --- hardware --------------------------------------------------------------------------------

    def _devices_from_config(self) -> None:
        cfg = self.cfg
        devs = {f"camera:{n}": DeviceStatus("camera", n, c.type) for n, c in cfg.cameras.items()}
        devs["projector"] = DeviceStatus("projector", "projector", cfg.projector.type)
        devs["trigger"] = DeviceStatus("trigger", "trigger", cfg.trigger.type)
        self.board.devices = devs

    def _idle_state(self) -> State:
        return State.IDLE if all(d.ok for d in self.board.devices.values()) else State.FAULT

    def _make_scanner(self, cfg: AppConfig) -> tuple[Any, Any, dict[str, _WatchedCamera]]:
        """Build (not open) the rig and its scanner; runs in a thread. Tests replace it with fakes."""
        from appliance.hardware.registry import build_rig
        from appliance.scan import Scanner, load_calibration_for

        rig = build_rig(cfg)
        calibration = load_calibration_for(cfg, rig)
        watched = {n: _WatchedCamera(c, self._on_camera_captured) for n, c in rig.cameras.items()}
        rig.cameras = dict(watched)
        return rig, Scanner(cfg, rig, calibration), watched

    async def _connect(self) -> None:
        loop = asyncio.get_running_loop()
        cfg = self.cfg
        self.board.set_state(State.STARTING, "connecting hardware", Phase.CONNECT)
        rig, scanner, watched = await loop.run_in_executor(None, self._make_scanner, cfg)
        self.rig = rig
        self.board.sequence = scanner.sequence.describe()
        try:
            await scanner.open()
        except BaseException:
            with contextlib.suppress(Exception):
                await scanner.close()
            raise
        for n in cfg.cameras:
            info = watched[n].info if n in watched else None
            detail = (f"{info.model} {info.serial}, {info.width}x{info.height} {info.pixel_format}"
                      if info is not None else "open")
            self.board.devices[f"camera:{n}"] = DeviceStatus("camera", n, cfg.cameras[n].type, True, detail)
        self.board.devices["projector"] = DeviceStatus("projector", "projector", cfg.projector.type, True,
                                                       f"sequence loaded: {scanner.sequence.describe()}")
        self.scanner = scanner
        await self._open_trigger()
        self.board.set_state(State.STARTING, "warming kernels", Phase.WARM)
        t = time.perf_counter()
        await self._warm(scanner)
        log.info("kernels warm in %.1f s", time.perf_counter() - t)

    def _trigger_link(self, state: Any, reason: str) -> None:
        """The trigger backend's link state changed (backends that reconnect by themselves report here)."""
        dev = self.board.devices.get("trigger")
        if dev is None:
            return
        ok = getattr(state, "value", str(state)) == "ready"
        if ok != dev.ok:
            if not ok:
                self.board.error("hardware", f"trigger {dev.backend}: {reason}")
            dev.ok, dev.detail = ok, f"{getattr(state, 'value', state)}: {reason}"
            if not self.board.busy and self.board.state in (State.IDLE, State.FAULT) and self.scanner:
                self.board.set_state(self._idle_state(), "ready" if ok else f"trigger: {reason}")

    async def _open_trigger(self) -> None:
        trig = self.rig.trigger
        kind = self.cfg.trigger.type
        if hasattr(trig, "on_state"):
            trig.on_state = self._trigger_link
        self._lamps = None
        try:
            await trig.open()
        except (ApplianceError, OSError) as exc:
            self.board.devices["trigger"] = DeviceStatus("trigger", trig.name, kind, False, str(exc))
            self.board.error("hardware", f"trigger {kind}: {exc}")
        else:
            status = getattr(trig, "status", None)
            detail = status() if callable(status) else "open"
            self.board.devices["trigger"] = DeviceStatus("trigger", trig.name, kind, True, detail)
        self._trigger_task = self._spawn(self._trigger_loop(trig), "trigger")

    async def _warm(self, scanner: Any) -> None:
        """Compile or load every numba kernel before ready: a discarded scan on the virtual rig, else a
        decode of blank frames (no light is projected)."""
        await scanner.warm_up()
        self._on_camera_captured_count = 0

    _on_camera_captured_count = 0

    def _on_camera_captured(self) -> None:
        self._on_camera_captured_count += 1
        if self.board.state == State.SCANNING and self._on_camera_captured_count >= len(self.cfg.cameras):
            self.board.set_state(State.PROCESSING, self.board.detail)

    async def _close_hardware(self) -> None:
        if self._trigger_task is not None:
            self._trigger_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._trigger_task
            self._trigger_task = None
        if self.rig is not None:
            with contextlib.suppress(Exception):
                await self.rig.trigger.close()
        if self.scanner is not None:
            try:
                await self.scanner.close()
            except Exception as exc:
                log.warning("closing the rig: %s", exc)
        self.scanner = None

    async def _hardware_loop(self) -> None:
        delay = RETRY_FIRST_S
        failures = 0
        while True:
            self._devices_from_config()
            try:
                async with self._scan_lock:
                    await self._connect()
            except Exception as exc:  # any failure to connect is a fault to retry, never the end
                await self._close_hardware()
                failures += 1
                if not isinstance(exc, (ApplianceError, OSError)):
                    log.exception("hardware: unexpected error")
                for d in self.board.devices.values():
                    if not d.ok and d.detail == "not connected":
                        d.detail = "not connected (see last error)"
                if failures == 1:
                    log.error("hardware: %s; retrying with backoff", exc)
                self.board.error("hardware", str(exc))
                self.board.set_state(State.FAULT, f"hardware: {exc}; retry in {delay:.0f} s", Phase.CONNECT)
                self._send_ready()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._hw_changed.wait(), delay)
                self._hw_changed.clear()
                delay = min(delay * 2, self.cfg.service.retry_max_s)
                continue
            if failures:
                log.info("hardware recovered after %d failed attempt(s)", failures)
            failures, delay = 0, RETRY_FIRST_S
            self.board.set_state(self._idle_state(), "ready", Phase.READY)
            self._send_ready()
            self._job_ready.set()
            await self._hw_changed.wait()
            self._hw_changed.clear()
            async with self._scan_lock:
                await self._close_hardware()

    def _send_ready(self) -> None:
        if not self._ready_sent:
            self._ready_sent = True
            self.notifier.ready(self.board.one_line())

    async def _trigger_loop(self, trig: Any) -> None:
        delay = RETRY_FIRST_S
        key = "trigger"
        while True:
            try:
                event = await trig.next_event()
            except (ApplianceError, OSError) as exc:
                dev = self.board.devices[key]
                if dev.ok:
                    log.error("trigger %s failed: %s; retrying with backoff", trig.name, exc)
                    self.board.error("hardware", f"trigger {trig.name}: {exc}")
                dev.ok, dev.detail = False, str(exc)
                if not self.board.busy:
                    self.board.set_state(State.FAULT, f"trigger: {exc}")
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.cfg.service.retry_max_s)
                with contextlib.suppress(ApplianceError, OSError):
                    await trig.close()
                try:
                    await trig.open()
                except (ApplianceError, OSError) as exc2:
                    dev.detail = str(exc2)
                    continue
                log.info("trigger %s recovered", trig.name)
                dev.ok, dev.detail, delay = True, "open", RETRY_FIRST_S
                if not self.board.busy:
                    self.board.set_state(self._idle_state(), "ready")
                continue
            self.request_scan(event)

    # --- triggers and scans ----------------------------------------------------------------------

    def request_scan(self, event: TriggerEvent) -> tuple[str, _Job | None]:
        """Accept, queue or refuse a trigger; returns (``started``/``queued``/``refused: why``, job)."""
        b = self.board
        b.count("triggers")
        if self._stop.is_set():
            why = "the service is stopping"
        elif self.scanner is None:
            why = f"not ready ({b.state}: {b.detail})"
        elif b.busy or self._jobs:
            if self.cfg.service.busy_policy == "queue" and len(self._jobs) < self.cfg.service.queue_max:
                job = _Job(event)
                self._jobs.append(job)
                b.queue_length = len(self._jobs)
                b.count("triggers_queued")
                log.info("trigger from %s queued (%d waiting)", event.source, len(self._jobs))
                self._job_ready.set()
                return "queued", job
            why = f"busy ({b.state})" + (f", queue full ({len(self._jobs)})" if self._jobs else "")
        else:
            job = _Job(event)
            self._jobs.append(job)
            self._job_ready.set()
            return "started", job
        b.count("triggers_refused")
        log.warning("trigger from %s refused: %s", event.source, why)
        self._blink_refused()
        return f"refused: {why}", None

    async def _worker(self) -> None:
        while True:
            await self._job_ready.wait()
            self._job_ready.clear()
            while self._jobs and self.scanner is not None and not self._stop.is_set():
                job = self._jobs.popleft()
                self.board.queue_length = len(self._jobs)
                async with self._scan_lock:
                    self._current = asyncio.get_running_loop().create_task(self._scan(job.event))
                    try:
                        record = await asyncio.shield(self._current)
                    except asyncio.CancelledError:
                        me = asyncio.current_task()
                        if not self._current.done() or (me is not None and me.cancelling()):
                            raise  # the worker itself is cancelled, not (only) the scan
                        record = ScanRecord("", "", job.event.source, False, error="aborted (stopping)")
                    finally:
                        self._current = None
                if not job.done.done():
                    job.done.set_result(record)
                if self.max_scans is not None and self.successful_scans >= self.max_scans:
                    log.info("%d scans done (--scans); stopping", self.successful_scans)
                    self.request_stop()

    async def _scan(self, event: TriggerEvent) -> ScanRecord:
        from appliance.scan import scan_metadata

        loop = asyncio.get_running_loop()
        scanner, cfg, b = self.scanner, self.cfg, self.board
        shapes = [(m.height, m.width) for n, m in scanner.calibration.devices.items() if n in cfg.cameras]
        need = estimate_scan_bytes(shapes, normals=cfg.output.normals, preview=cfg.output.preview)
        problem = await loop.run_in_executor(self._write_ex, self.writer.storage_problem, need)
        started = dt.datetime.now(dt.UTC)
        if problem:
            b.count("triggers_refused")
            b.count("scans_failed")
            b.error("disk", f"scan refused: {problem}")
            self._blink_refused()
            rec = ScanRecord("", started.isoformat(), event.source, False, error=f"refused: {problem}")
            b.add_scan(rec)
            return rec
        self.counter += 1
        from appliance.output.scanfiles import make_scan_id

        scan_id = make_scan_id(cfg.serial, self.counter, started)
        self._on_camera_captured_count = 0
        b.set_state(State.SCANNING, scan_id)
        try:
            result = await asyncio.wait_for(scanner.scan(), cfg.service.scan_timeout_s)
        except Exception as exc:  # the service outlives any failed scan
            if not isinstance(exc, (ApplianceError, TimeoutError)):
                log.exception("scan %s: unexpected error", scan_id)
            msg = str(exc) or f"scan took longer than service.scan_timeout_s = {cfg.service.scan_timeout_s:g}"
            b.count("scans_failed")
            b.error("scan", f"scan {scan_id} failed: {msg}")
            rec = ScanRecord(scan_id, started.isoformat(), event.source, False, error=msg)
            b.add_scan(rec)
            b.set_state(self._idle_state(), "ready")
            if isinstance(exc, TimeoutError):
                self._hw_changed.set()  # devices in an unknown state: reconnect
            return rec
        b.set_state(State.WRITING, scan_id)
        meta = scan_metadata(scan_id, started.isoformat(), cfg, scanner, result)
        meta.extra["trigger"] = {"source": event.source, "detail": event.detail}
        t_w = time.perf_counter()
        write = loop.run_in_executor(
            self._write_ex,
            lambda: self.writer.write_scan(_today(started), meta, result.cloud, list(result.shapes.values()),
                                           normals=cfg.output.normals and result.cloud.normal is not None,
                                           preview=cfg.output.preview))
        try:
            outcome: WriteOutcome = await asyncio.shield(write)  # a started write always completes
        except OutputError as exc:
            b.count("scans_failed")
            b.error("disk", str(exc))
            rec = ScanRecord(scan_id, started.isoformat(), event.source, False, len(result.cloud),
                             error=str(exc))
            b.add_scan(rec)
            b.set_state(self._idle_state(), "ready")
            return rec
        timings = dict(result.timings_ms)
        timings["write_ms"] = (time.perf_counter() - t_w) * 1e3
        timings["trigger_to_file_ms"] = (time.monotonic_ns() - event.t_monotonic_ns) / 1e6
        rec = ScanRecord(scan_id, started.isoformat(), event.source, True, len(result.cloud),
                         outcome.location, [str(p) for p in outcome.files],
                         {k: round(v, 1) for k, v in timings.items()})
        if outcome.location == "spool":
            b.count("spooled")
            b.error("share", f"scan {scan_id} spooled: {outcome.reason}")
        self.successful_scans += 1
        b.counters["scans_done"] += 1
        b.add_scan(rec)
        b.share = await loop.run_in_executor(self._write_ex, self.writer.status)
        await loop.run_in_executor(self._write_ex, self._save_state)
        log.info("scan %s: %d points, %.0f ms trigger to file; %s: %s", scan_id, len(result.cloud),
                 timings["trigger_to_file_ms"], outcome.location, outcome.files[0] if outcome.files else "-")
        b.set_state(self._idle_state(), "ready")
        virtual = getattr(self.rig, "virtual", None)
        if self.ground_truth and virtual is not None:  # after "ready": a demonstration aid, off the loop
            from appliance.sim.accuracy import compare_to_ground_truth

            report = await loop.run_in_executor(
                self._write_ex, compare_to_ground_truth, result.cloud, virtual, list(cfg.cameras))
            log.info("scan %s: error against ground truth: %s", scan_id, report.line())
        return rec

    # --- persistent state (scan counter, last scans) --------------------------------------------

    def _state_path(self) -> Path:
        return Path(self.cfg.service.state_directory) / STATE_FILE

    def _load_state(self) -> None:
        try:
            data = json.loads(self._state_path().read_text())
            self.counter = int(data.get("counter", 0))
            for r in data.get("last_scans", []):
                self.board.last_scans.append(ScanRecord(**r))
        except (OSError, ValueError, TypeError):
            pass

    def _save_state(self) -> None:
        path = self._state_path()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            data = {"counter": self.counter, "last_scans": [asdict(r) for r in self.board.last_scans]}
            write_bytes_atomic(path, json.dumps(data).encode())
        except (OSError, ApplianceError) as exc:
            log.warning("state file %s: %s", path, exc)

    # --- configuration ---------------------------------------------------------------------------

    def _config_rejected(self, message: str) -> None:
        self.board.config_error = message
        self.board.count("reloads_rejected")
        self.board.error("config", message)

    async def _apply_config(self, new: AppConfig) -> None:
        async with self._scan_lock:  # never in the middle of a scan
            old = self.cfg
            self.cfg = new
            b = self.board
            b.config_error = ""
            b.config_loaded_utc = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
            b.serial = new.serial
            b.count("reloads")
            if new.output != old.output:
                self.writer = ShareWriter(new.output)
            if self.watcher is not None:
                self.watcher.poll_s = new.service.config_poll_s
            if self.socket_override is None and new.service.control_socket != old.service.control_socket:
                if self.control is not None:
                    await self.control.close()
                self.control = ControlServer(self.socket_path, self._handle)
                await self.control.start()
            if new.service.mdns != old.service.mdns:
                if self.announcer is not None:
                    await self.announcer.close()
                    self.announcer = None
                await self._start_mdns()
            if any(getattr(new, k) != getattr(old, k) for k in HARDWARE_KEYS):
                log.info("configuration changes the rig: reconnecting")
                # say so at once: until the rig is rebuilt, the old one must not look ready
                b.set_state(State.STARTING, "reconnecting for the new configuration", Phase.CONNECT)
                self._hw_changed.set()
            b.changed()

    # --- control socket --------------------------------------------------------------------------

    async def _handle(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req["cmd"]
        if cmd == "status":
            snap = self.board.snapshot()
            loop = asyncio.get_running_loop()
            snap["share"] = await loop.run_in_executor(self._write_ex, self.writer.status)
            snap["control_socket"] = str(self.socket_path)
            return {"ok": True, "status": snap}
        if cmd == "last_error":
            err = self.board.last_error
            return {"ok": True, "last_error": asdict(err) if err is not None else None}
        if cmd == "reload":
            if self.watcher is None:
                return {"ok": False, "error": "not started"}
            ok, msg = await self.watcher.reload("control socket")
            return {"ok": ok, "error": msg} if not ok else {"ok": True}
        if cmd == "trigger":
            ev = TriggerEvent("control", time.monotonic_ns(), str(req.get("detail", "")))
            outcome, job = self.request_scan(ev)
            if job is None:
                return {"ok": False, "result": outcome, "error": f"trigger {outcome}"}
            if not req.get("wait"):
                return {"ok": True, "result": outcome}
            try:
                rec = await job.done
            except ApplianceError as exc:
                return {"ok": False, "result": outcome, "error": str(exc)}
            return {"ok": rec.ok, "result": outcome, "scan": asdict(rec),
                    **({"error": rec.error} if not rec.ok else {})}
        return {"ok": False, "error": f"unknown command {cmd!r}; use status, trigger, reload or last_error"}

    # --- stdin button ----------------------------------------------------------------------------

    def _start_stdin_reader(self, loop: asyncio.AbstractEventLoop) -> None:
        def press() -> None:
            trig = self.rig.trigger if self.rig is not None else None
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
    cfg = load_config(config)
    if cfg.service.numba_cache_dir is not None:
        os.environ["NUMBA_CACHE_DIR"] = str(cfg.service.numba_cache_dir)
    stdin = stdin_button or bool(getattr(cfg.trigger, "stdin", False))

    async def main() -> int:
        service = Service(config, cfg, control_socket=control_socket, scans=scans, stdin_button=stdin,
                          ground_truth=ground_truth)
        return await service.run()

    return asyncio.run(main())
