"""The scan job queue: triggers accepted, queued or refused (``service.busy_policy``), and the worker that runs
one scan after another: capture and reconstruction on the rig, then the files through the writer.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import importlib
import logging
import time
from collections import deque
from collections.abc import Coroutine
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from appliance import replay
from appliance.errors import ApplianceError, OutputError, ScanError
from appliance.hardware.base import TriggerEvent
from appliance.output.scanfiles import make_scan_id
from appliance.output.share import WriteOutcome, estimate_scan_bytes
from appliance.service.parts import Files, JobsHost, Lamps, RigView
from appliance.service.state import ScanRecord, State, StatusBoard, scan_findings

if TYPE_CHECKING:
    from appliance.reconstruct.types import PointCloud
    from appliance.sim.rig import VirtualRig

log = logging.getLogger(__name__)

# Module-level so tests can shorten them.
HEARTBEAT_S = 1.0  # an idle worker shows it is alive this often
WRITE_DEADLINE_S = 120.0  # a scan may take service.scan_timeout_s, its files this much longer


@dataclass
class Job:
    """One accepted trigger; ``done`` resolves with its scan's record."""

    event: TriggerEvent
    done: asyncio.Future[ScanRecord] = field(
        default_factory=lambda: asyncio.get_running_loop().create_future())


def _today(when: dt.datetime) -> str:
    return f"{when:%Y-%m-%d}"


class ScanJobs:
    """The queue of accepted triggers and the scan worker of one service.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (this part writes the state during a scan, ``queue_length``, the scan
        counters and the last scans).
    host : JobsHost
        The configuration, the service's tasks and stop, and where finished scans go.
    rig : RigView
        The rig part: ready or not, its scanner.
    files : Files
        The writer thread: scan numbers, the files, the state file.
    lamps : Lamps
        The refused-trigger blink.
    scan_lock : asyncio.Lock
        Held by a scan and by every change of the rig.
    max_scans : int, optional
        Stop the service after this many successful scans.
    ground_truth : bool
        On a virtual rig, log each scan's error against ground truth (after its files).
    """

    def __init__(self, board: StatusBoard, host: JobsHost, rig: RigView, files: Files, lamps: Lamps,
                 scan_lock: asyncio.Lock, *, max_scans: int | None = None, ground_truth: bool = False) -> None:
        self.board = board
        self.host = host
        self.rig = rig
        self.files = files
        self.lamps = lamps
        self.scan_lock = scan_lock
        self.max_scans = max_scans
        self.ground_truth = ground_truth
        self.successful_scans = 0
        self.queue: deque[Job] = deque()
        self.ready = asyncio.Event()
        self.current: asyncio.Task[ScanRecord] | None = None
        self.active: Job | None = None  # taken from the queue, not finished (waiting for the lock included)
        self.scan_id = ""  # of the running scan
        self.abort_reason = "aborted (stopping)"
        self.after_scan: set[asyncio.Task[None]] = set()  # bookkeeping of finished scans, still running
        self.heartbeat = time.monotonic()  # the worker's last sign of life (idle: every HEARTBEAT_S)
        self.deadline: float | None = None  # monotonic time by which the running job must be done

    @property
    def busy(self) -> bool:
        """True while a job is queued, waiting for the scan lock or running (the hand-over included)."""
        return bool(self.queue) or self.active is not None or self.board.busy

    def request(self, event: TriggerEvent) -> tuple[str, Job | None]:
        """Accept, queue or refuse a trigger; returns (``started``/``queued``/``refused: why``, job)."""
        b, service = self.board, self.host.cfg.service
        b.count("triggers")
        if self.host.stopping:
            why = "the service is stopping"
        elif not self.rig.ready:
            why = f"not ready ({b.state}: {b.detail})"
        elif b.state == State.TUNING:  # never queued: a scan behind a tune would use the settings it replaces
            why = "tuning (scan3d tune is measuring the scene on the rig); trigger again when it is done"
        elif self.busy:
            if service.busy_policy == "queue" and len(self.queue) < service.queue_max:
                job = Job(event)
                self.queue.append(job)
                b.queue_length = len(self.queue)
                b.count("triggers_queued")
                log.info("trigger from %s queued (%d waiting)", event.source, len(self.queue))
                self.ready.set()
                return "queued", job
            state = b.state if b.busy else "a scan is starting"
            why = f"busy ({state})" + (f", queue full ({len(self.queue)})" if self.queue else "")
        else:
            job = Job(event)
            self.queue.append(job)
            self.ready.set()
            return "started", job
        b.count("triggers_refused")
        log.warning("trigger from %s refused: %s", event.source, why)
        self.lamps.blink_refused()
        return f"refused: {why}", None

    def wake(self) -> None:
        """Look at the queue now (the rig is ready again)."""
        self.ready.set()

    def drop_queued(self, why: str) -> None:
        """Fail every queued (not started) job with ``why``."""
        for job in self.queue:
            if not job.done.done():
                job.done.set_exception(ApplianceError(why))
        self.queue.clear()
        self.board.queue_length = 0

    def abort(self, why: str) -> asyncio.Task[ScanRecord] | None:
        """Cancel the running scan (stopping, past its grace): its record says ``why``, no file is written.
        Returns the scan's task to wait for (None when no scan runs)."""
        current = self.current
        if current is None or current.done():
            return None
        self.abort_reason = why
        current.cancel()
        return current

    def abort_active(self, why: str) -> None:
        """Resolve the job in hand (if any) as failed with ``why`` (shutdown: its client gets a reply)."""
        job = self.active
        if job is not None and not job.done.done():
            job.done.set_result(ScanRecord(self.scan_id, "", job.event.source, False, error=why))

    async def worker(self) -> None:
        """Run queued scans one after another (until cancelled); heartbeats while idle."""
        host, b = self.host, self.board
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.ready.wait(), HEARTBEAT_S)
            self.ready.clear()
            self.heartbeat = time.monotonic()
            while self.queue and self.rig.ready and not host.stopping:
                job = self.queue.popleft()
                b.queue_length = len(self.queue)
                self.active = job
                self.deadline = time.monotonic() + host.cfg.service.scan_timeout_s + WRITE_DEADLINE_S
                try:
                    record = await self._run(job)
                finally:
                    self.active = None
                    self.deadline = None
                    self.heartbeat = time.monotonic()
                if record is None:  # the rig went away while it waited: back in front, until it is back
                    self.queue.appendleft(job)
                    b.queue_length = len(self.queue)
                    break
                if not job.done.done():
                    job.done.set_result(record)
                host.scan_finished(record)
                if self.max_scans is not None and self.successful_scans >= self.max_scans:
                    log.info("%d scans done (--scans); stopping", self.successful_scans)
                    host.request_stop()

    async def _run(self, job: Job) -> ScanRecord | None:
        """One job under the scan lock; None when the rig is not (or no longer) ready."""
        async with self.scan_lock:
            if not self.rig.ready:  # a reload changed the rig while this job waited for the lock
                log.info("trigger from %s waits: the rig is being reconnected", job.event.source)
                return None
            self.current = asyncio.get_running_loop().create_task(self._scan_guarded(job.event))
            try:
                return await asyncio.shield(self.current)
            except asyncio.CancelledError:
                me = asyncio.current_task()
                if not self.current.done() or (me is not None and me.cancelling()):
                    raise  # the worker itself is cancelled, not (only) the scan
                return ScanRecord(self.scan_id, "", job.event.source, False, error=self.abort_reason)
            finally:
                self.current = None

    async def _scan_guarded(self, event: TriggerEvent) -> ScanRecord:
        """:meth:`_scan`, where any exception is a failed scan with its message and the state goes back to idle."""
        self.scan_id = ""
        started = dt.datetime.now(dt.UTC)
        try:
            return await self._scan(event, started)
        except Exception as exc:  # the service outlives any failed scan, whatever failed
            b = self.board
            if not isinstance(exc, ApplianceError):
                log.exception("scan %s: unexpected error", self.scan_id or "(before start)")
            msg = str(exc) or type(exc).__name__
            what = f"scan {self.scan_id}" if self.scan_id else "scan"
            b.count("scans_failed")
            b.error("scan", f"{what} failed: {msg}")
            rec = ScanRecord(self.scan_id, started.isoformat(), event.source, False, error=msg)
            b.add_scan(rec)
            b.set_state(self.rig.idle_state(), "ready")
            return rec

    async def _scan(self, event: TriggerEvent, started: dt.datetime) -> ScanRecord:
        out = self.files
        scanner, cfg, b = self.rig.scanner, self.host.cfg, self.board
        if scanner is None:  # checked under the scan lock before; a rig that went since fails this scan
            raise ScanError("the rig is not connected (reconnecting); the next trigger tries again")
        shapes = [(m.height, m.width) for n, m in scanner.calibration.devices.items() if n in cfg.cameras]
        need = estimate_scan_bytes(shapes, normals=cfg.output.normals, preview=cfg.output.preview)
        problem = await out.call(out.writer.storage_problem, need)
        if problem:
            b.count("triggers_refused")
            b.count("scans_failed")
            b.error("disk", f"scan refused: {problem}")
            self.lamps.blink_refused()
            rec = ScanRecord("", started.isoformat(), event.source, False, error=f"refused: {problem}")
            b.add_scan(rec)
            return rec
        scan_id = self.scan_id = make_scan_id(cfg.serial, await out.next_number(), started)
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
            b.set_state(self.rig.idle_state(), "ready")
            if isinstance(exc, TimeoutError):
                self.rig.reconnect()  # devices in an unknown state
            return rec
        b.set_state(State.WRITING, scan_id)
        meta = replay.scan_metadata(scan_id, started.isoformat(), scanner.sequence, scanner.calibration,
                                    list(cfg.cameras), result, serial=cfg.serial)  # fmt: skip
        meta.extra["trigger"] = {"source": event.source, "detail": event.detail}
        t_w = time.perf_counter()
        writer = out.writer
        write = out.call(
            lambda: writer.write_scan(_today(started), meta, result.cloud, list(result.shapes.values()),
                                      normals=cfg.output.normals and result.cloud.normal is not None,
                                      preview=cfg.output.preview, reasons=replay.reason_maps(result)))
        try:
            outcome: WriteOutcome = await asyncio.shield(write)  # a started write always completes
        except OutputError as exc:
            b.count("scans_failed")
            b.error("disk", str(exc))
            rec = ScanRecord(scan_id, started.isoformat(), event.source, False, len(result.cloud),
                             error=str(exc))
            b.add_scan(rec)
            b.set_state(self.rig.idle_state(), "ready")
            return rec
        timings = dict(result.timings_ms)
        timings["write_ms"] = (time.perf_counter() - t_w) * 1e3
        timings["trigger_to_file_ms"] = (time.monotonic_ns() - event.t_monotonic_ns) / 1e6
        rec = ScanRecord(scan_id, started.isoformat(), event.source, True, len(result.cloud),
                         outcome.location, [str(p) for p in outcome.files],
                         {k: round(v, 1) for k, v in timings.items()},
                         calibration_health=_health_summary(result.calibration_health),
                         both_seen=seen if isinstance(seen := (result.stereo or {}).get("both_seen"), dict) else {},
                         **scan_findings(meta.counts, meta.warnings, meta.extra))
        if outcome.location == "spool":
            b.count("spooled")
            b.error("share", f"scan {scan_id} spooled: {outcome.reason}")
        self.successful_scans += 1
        b.counters["scans_done"] += 1
        b.add_scan(rec)
        log.info("scan %s: %d points, %.0f ms trigger to file; %s: %s", scan_id, len(result.cloud),
                 timings["trigger_to_file_ms"], outcome.location, outcome.files[0] if outcome.files else "-")
        if len(cfg.cameras) > 1:  # what each camera took
            per_cam = ", ".join(f"{n} capture {timings.get(f'capture_{n}_ms', 0):.0f} ms + decode "
                                f"{timings.get(f'decode_finish_{n}_ms', 0):.0f} ms" for n in cfg.cameras)
            log.info("scan %s: %s; reconstruct %.0f ms (mode %s)", scan_id, per_cam, timings.get("reconstruct_ms", 0),
                     cfg.reconstruction.mode)
        for cam, share in rec.separated.items():  # a mirror lit part of the scene twice: what was taken apart
            log.info("scan %s: %s: %.1f %% of the image lit by two copies of the pattern (a mirror), the direct copy "
                     "taken apart", scan_id, cam, 100.0 * share)
        seen = rec.both_seen
        if isinstance(seen.get("share"), (int, float)):  # camera-camera: what both cameras see that got a point
            log.info("scan %s: camera-camera: %.1f %% of the %d pixels both cameras see got a point", scan_id,
                     100.0 * float(seen["share"]), int(seen.get("pixels", 0)))
        health = rec.calibration_health  # what the scan's redundant views say of the calibration
        if health:
            checks = ", ".join(f"{c['kind']} {c['status']}" for c in health.get("checks", []))
            log.info("scan %s: calibration health %s (%s)", scan_id, health.get("status"), checks or "no check")
        b.set_state(self.rig.idle_state(), "ready")
        # the bookkeeping goes on beside the next scan (the writer thread keeps the order of the files)
        virtual = self.rig.virtual
        cloud = result.cloud if self.ground_truth and virtual is not None else None
        self._after(self._bookkeeping(scan_id, cloud, virtual, list(cfg.cameras)))
        return rec

    def _after(self, coro: Coroutine[Any, Any, None]) -> None:
        task = self.host.spawn(coro, "after-scan", critical=False)
        self.after_scan.add(task)
        task.add_done_callback(self.after_scan.discard)

    async def _bookkeeping(self, scan_id: str, cloud: PointCloud | None, virtual: VirtualRig | None,
                           cameras: list[str]) -> None:
        """After a scan: the share's state, the state file, and (a demonstration aid) the ground-truth error."""
        out = self.files
        await out.scan_written()
        if cloud is not None and virtual is not None:
            accuracy = await asyncio.to_thread(importlib.import_module, "appliance.sim.accuracy")
            report = await out.call(accuracy.compare_to_ground_truth, cloud, virtual, cameras)
            log.info("scan %s: error against ground truth: %s", scan_id, report.line())


def _health_summary(health: dict[str, object]) -> dict[str, Any]:
    """A scan's calibration health without the per-check detail beyond its figures (kept in the status)."""
    keep = ("status", "kind", "devices", "residual_px", "residual_mm", "reference_px", "limit_px", "n_samples")
    checks = health.get("checks", [])
    return {"status": health.get("status", ""), "reason": health.get("reason", ""),
            "checks": [{k: c.get(k) for k in keep} for c in checks if isinstance(c, dict)]
            if isinstance(checks, list) else []} if health else {}  # fmt: skip
