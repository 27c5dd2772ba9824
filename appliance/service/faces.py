"""The line-integration faces of the service (HTTP + status page, MQTT, OPC UA) and the view they share.

Every face talks to the service only through :class:`ServiceView`: the status (the same JSON as
``scan3d status --json``), a trigger under the service's busy policy, a stream of events (state changes and
finished scans), the last scans and the files of a known scan. :class:`ServiceFaces` implements the view
over the service's :class:`~appliance.service.state.StatusBoard` and ``request_scan`` and starts and stops
the faces the configuration enables. A face whose library is missing (``aiohttp``, ``aiomqtt``,
``asyncua``) or whose start fails is disabled alone, with one line that says what to do; the service and the
other faces carry on.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import importlib
import json
import logging
import re
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from appliance import __version__
from appliance.config.schema import AppConfig
from appliance.errors import ApplianceError
from appliance.hardware.base import TriggerEvent
from appliance.service.state import ScanRecord, StatusBoard

log = logging.getLogger(__name__)

Event = dict[str, Any]
EVENT_QUEUE_MAX = 256  # per subscriber; a slow subscriber loses its oldest events, never blocks the service
CLOUD_SAMPLE_MAX_POINTS = 20000
SCAN_ID_RE = re.compile(r"^[0-9]{8}-[0-9]{6}-[A-Za-z0-9._-]{1,64}-[0-9]{6,}$")
FILE_SUFFIX = {"cloud": ".ply", "preview": ".png", "sidecar": ".json"}


class ServiceView(Protocol):
    """What a face may see and do (the whole of its dependency on the service)."""

    @property
    def serial(self) -> str:
        """The appliance serial (as configured now)."""
        ...

    async def status(self) -> dict[str, Any]:
        """The status, the same JSON as ``scan3d status --json``."""
        ...

    async def trigger(self, wait: bool, source: str) -> dict[str, Any]:
        """Start a scan under the busy policy; the control socket's reply (``ok``, ``result``, ``scan``)."""
        ...

    async def tune(self, time_budget_ms: float) -> dict[str, Any]:
        """``scan3d tune`` on the rig (the control socket's ``tune`` reply: ``ok``, ``tune`` or ``error``)."""
        ...

    async def tune_apply(self, exposures_us: list[int] | None) -> dict[str, Any]:
        """Write the last tune's choice into the configuration file and reload it (``ok``, ``applied``)."""
        ...

    def subscribe(self) -> asyncio.Queue[Event]:
        """A queue of events: ``{"type": "state", ...}`` and ``{"type": "scan", ...}``."""
        ...

    def unsubscribe(self, queue: asyncio.Queue[Event]) -> None:
        """Stop filling ``queue``."""
        ...

    def state_event(self) -> Event:
        """The current state as a ``state`` event."""
        ...

    async def scans(self, limit: int) -> list[dict[str, Any]]:
        """The last ``limit`` scans, newest first, with calibration health from their sidecars."""
        ...

    async def scan_file(self, scan_id: str, kind: str) -> Path | None:
        """The ``cloud``/``preview``/``sidecar`` file of a known scan (None: unknown id or no such file)."""
        ...

    async def cloud_sample(self, scan_id: str) -> bytes | None:
        """A downsampled cloud of a known scan: little-endian float32 x, y, z (mm) per point."""
        ...

    def configuration(self) -> dict[str, Any]:
        """The running configuration (JSON-ready), its file and the last rejected edit."""
        ...


class Face(Protocol):
    """One face: started after the control socket, closed before it."""

    async def start(self) -> None:
        """Bind / connect (raises ApplianceError or OSError when it cannot)."""
        ...

    async def close(self) -> None:
        """Release everything."""
        ...


def scan_record_dict(rec: ScanRecord) -> dict[str, Any]:
    """A scan record as the faces publish it (id, time, points, files, timings, ok, error)."""
    d = asdict(rec)
    d["id"] = rec.scan_id
    return d


def read_calibration_health(sidecar: Path) -> Any:
    """``calibration_health`` from a sidecar (None when absent or unreadable); blocking, run in a thread."""
    try:
        data = json.loads(sidecar.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    health = data.get("calibration_health")
    if health is None and isinstance(data.get("extra"), dict):
        health = data["extra"].get("calibration_health")
    return health


def downsample_cloud(ply: Path, max_points: int = CLOUD_SAMPLE_MAX_POINTS) -> bytes:
    """Every k-th point of a PLY as float32 x, y, z (little-endian, mm); blocking, run in a thread.

    Parameters
    ----------
    ply : Path
        A cloud written by :func:`appliance.output.ply.write_ply`.
    max_points : int
        At most this many points come back (an even stride over the file).

    Returns
    -------
    bytes
        ``N * 12`` bytes, ``N <= max_points``.
    """
    from appliance.output.ply import read_ply_vertices

    v = read_ply_vertices(ply)
    stride = max(1, -(-len(v) // max_points))
    sel = v[::stride]
    out = np.empty((len(sel), 3), "<f4")
    out[:, 0], out[:, 1], out[:, 2] = sel["x"], sel["y"], sel["z"]
    return out.tobytes()


def _outcome(exc: ApplianceError) -> str:
    """``refused`` (busy, not ready, nothing to apply), ``invalid`` (a bad value or file) or ``failed``."""
    from appliance.errors import ConfigError
    from appliance.service.tuning import TuneRefused

    return "refused" if isinstance(exc, TuneRefused) else "invalid" if isinstance(exc, ConfigError) else "failed"


class ServiceHost(Protocol):
    """What :class:`ServiceFaces` needs of the service (``appliance.service.daemon.Service`` has it)."""

    cfg: AppConfig
    board: StatusBoard
    config_path: Path

    def request_scan(self, event: TriggerEvent) -> tuple[str, Any]:
        """Accept, queue or refuse a trigger: (outcome, job with a ``done`` future of ScanRecord, or None)."""
        ...

    async def status_async(self) -> dict[str, Any]:
        """What ``scan3d status --json`` shows."""
        ...

    async def tune(self, time_budget_ms: float, apply: bool) -> dict[str, Any]:
        """``scan3d tune`` on the rig (raises ApplianceError when refused)."""
        ...

    async def tune_apply(self, exposures_us: list[int] | None) -> dict[str, Any]:
        """Write the last tune's choice and reload (raises ApplianceError when refused or invalid)."""
        ...

    def subscribe(self, on_state: Callable[[StatusBoard], None] | None = None,
                  on_scan: Callable[[ScanRecord], None] | None = None) -> None:
        """Follow state changes and finished scans."""
        ...

    def unsubscribe(self, on_state: Callable[[StatusBoard], None] | None = None,
                    on_scan: Callable[[ScanRecord], None] | None = None) -> None:
        """Stop following."""
        ...


class ServiceFaces:
    """The :class:`ServiceView` of a running service, and its enabled faces (a service extension).

    Parameters
    ----------
    host : ServiceHost
        The service: its configuration, status board, ``request_scan``, ``status_async`` and listeners.
    """

    def __init__(self, host: ServiceHost) -> None:
        self.host = host
        self.cfg = host.cfg
        self.board = host.board
        self.config_path = Path(host.config_path)
        self._queues: set[asyncio.Queue[Event]] = set()
        self._faces: dict[str, Face] = {}
        self._last_state: tuple[Any, ...] = ()
        self._health: dict[str, Any] = {}
        self._cloud_cache: tuple[str, bytes] | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self.disabled: dict[str, str] = {}  # face -> why it is off although configured
        self.started = asyncio.Event()  # set once every configured face is up or disabled

    # --- the view ----------------------------------------------------------------------------------

    @property
    def serial(self) -> str:
        """The appliance serial."""
        return self.cfg.serial

    async def status(self) -> dict[str, Any]:
        """The status JSON (``scan3d status --json``)."""
        return await self.host.status_async()

    async def trigger(self, wait: bool, source: str) -> dict[str, Any]:
        """Start a scan from ``source`` under the busy policy (the control socket's reply format)."""
        outcome, job = self.host.request_scan(TriggerEvent(source, time.monotonic_ns(), source))
        if job is None:
            return {"ok": False, "result": outcome, "error": f"trigger {outcome}"}
        if not wait:
            return {"ok": True, "result": outcome}
        try:
            rec: ScanRecord = await asyncio.shield(job.done)
        except ApplianceError as exc:
            return {"ok": False, "result": outcome, "error": str(exc)}
        reply: dict[str, Any] = {"ok": rec.ok, "result": outcome, "scan": scan_record_dict(rec)}
        if not rec.ok:
            reply["error"] = rec.error
        return reply

    async def tune(self, time_budget_ms: float) -> dict[str, Any]:
        """``scan3d tune`` on the rig; a refusal or failure is ``ok: false`` with its one line."""
        try:
            return {"ok": True, "tune": await self.host.tune(time_budget_ms, False)}
        except ApplianceError as exc:
            return {"ok": False, "error": str(exc), "result": _outcome(exc)}

    async def tune_apply(self, exposures_us: list[int] | None) -> dict[str, Any]:
        """Write the last tune's choice and reload; a refusal or an invalid file is ``ok: false``."""
        try:
            applied = await self.host.tune_apply(exposures_us)
        except ApplianceError as exc:
            return {"ok": False, "error": str(exc), "result": _outcome(exc)}
        ok = bool(applied.get("reloaded"))
        return {"ok": ok, "applied": applied, **({} if ok else {"error": f"reload failed: {applied.get('error')}"})}

    def subscribe(self) -> asyncio.Queue[Event]:
        """A bounded queue of events (the oldest is dropped when full)."""
        q: asyncio.Queue[Event] = asyncio.Queue(EVENT_QUEUE_MAX)
        self._queues.add(q)
        return q

    def unsubscribe(self, queue: asyncio.Queue[Event]) -> None:
        """Stop filling ``queue``."""
        self._queues.discard(queue)

    def state_event(self) -> Event:
        """The current state as an event (state, phase, detail, counters, last scan id, last error, revision)."""
        b = self.board
        err = b.last_error
        return {"type": "state", "state": str(b.state), "phase": str(b.phase), "detail": b.detail,
                "serial": self.cfg.serial, "version": __version__, "scans_done": b.counters["scans_done"],
                "counters": dict(b.counters), "queue_length": b.queue_length, "last_scan_id": b.last_scan_id(),
                "last_error": asdict(err) if err is not None else None, "config_error": b.config_error,
                "revision": b.revision, "time_utc": dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")}

    def _known(self, scan_id: str) -> ScanRecord | None:
        if not SCAN_ID_RE.match(scan_id):
            return None
        for rec in self.board.last_scans:
            if rec.scan_id == scan_id and rec.ok:
                return rec
        return None

    def _find_file(self, rec: ScanRecord, kind: str) -> Path | None:  # blocking: in a thread
        name = rec.scan_id + FILE_SUFFIX[kind]
        candidates = [Path(f) for f in rec.files if Path(f).name == name]
        out = self.cfg.output
        day = f"{rec.scan_id[0:4]}-{rec.scan_id[4:6]}-{rec.scan_id[6:8]}"
        candidates.append(Path(out.directory) / day / name)
        spool = Path(out.spool_directory)
        with contextlib.suppress(OSError):
            candidates.extend(entry / name for entry in spool.iterdir() if entry.is_dir())
        for c in candidates:
            if c.is_file():
                return c
        return None

    async def scan_file(self, scan_id: str, kind: str) -> Path | None:
        """The file of a known scan, wherever it is now (share or spool)."""
        rec = self._known(scan_id)
        if rec is None or kind not in FILE_SUFFIX:
            return None
        return await asyncio.get_running_loop().run_in_executor(None, self._find_file, rec, kind)

    async def _calibration_health(self, rec: ScanRecord) -> Any:
        if rec.scan_id in self._health:
            return self._health[rec.scan_id]
        path = await self.scan_file(rec.scan_id, "sidecar")
        health = None
        if path is not None:
            health = await asyncio.get_running_loop().run_in_executor(None, read_calibration_health, path)
            if len(self._health) > 64:
                self._health.clear()
            self._health[rec.scan_id] = health
        return health

    async def _scan_dict(self, rec: ScanRecord) -> dict[str, Any]:
        d = scan_record_dict(rec)
        health = getattr(rec, "calibration_health", None)  # the record carries it; older ones: the sidecar
        if not health and rec.ok:
            health = await self._calibration_health(rec)
        d["calibration_health"] = health or None
        return d

    async def scans(self, limit: int) -> list[dict[str, Any]]:
        """The last ``limit`` scans, newest first."""
        recs = list(self.board.last_scans)[::-1][: max(0, limit)]
        return [await self._scan_dict(r) for r in recs]

    async def cloud_sample(self, scan_id: str) -> bytes | None:
        """A downsampled cloud of a known scan (cached for the last scan asked)."""
        if self._cloud_cache is not None and self._cloud_cache[0] == scan_id:
            return self._cloud_cache[1]
        path = await self.scan_file(scan_id, "cloud")
        if path is None:
            return None
        try:
            data = await asyncio.get_running_loop().run_in_executor(None, downsample_cloud, path)
        except (OSError, ApplianceError, ValueError, KeyError) as exc:
            log.warning("cloud %s: cannot read for the status page: %s", path, exc)
            return None
        self._cloud_cache = (scan_id, data)
        return data

    def configuration(self) -> dict[str, Any]:
        """The running configuration, its file and the last rejected edit."""
        return {"path": str(self.config_path), "loaded_utc": self.board.config_loaded_utc,
                "rejected_edit": self.board.config_error, "revision": self.board.revision,
                "running": self.cfg.model_dump(mode="json")}

    # --- events ------------------------------------------------------------------------------------

    def _emit(self, event: Event) -> None:
        for q in list(self._queues):
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(event)

    def _on_board(self, board: StatusBoard) -> None:
        err = board.last_error
        key = (board.state, board.phase, board.detail, board.counters["scans_done"], board.queue_length,
               err.time_utc + err.message if err is not None else "", board.config_error)
        if key != self._last_state:
            self._last_state = key
            self._emit(self.state_event())

    def _on_scan(self, rec: ScanRecord) -> None:
        if not rec.scan_id:
            return  # refused before it had an id (the state event carries the error)
        task = asyncio.get_running_loop().create_task(self._emit_scan(rec), name="scan3d-face-scan")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _emit_scan(self, rec: ScanRecord) -> None:
        event = await self._scan_dict(rec)
        event["type"] = "scan"
        self._emit(event)

    # --- lifecycle ---------------------------------------------------------------------------------

    def _wanted(self, cfg: AppConfig) -> dict[str, Any]:
        s = cfg.service
        want: dict[str, Any] = {}
        if s.http.listen is not None:
            want["http"] = s.http
        if s.mqtt.enabled:
            want["mqtt"] = s.mqtt
        if s.opcua.enabled:
            want["opcua"] = s.opcua
        return want

    async def _make(self, name: str, section: Any) -> Face:
        # imported in a thread: asyncua and aiohttp take a while to import, the loop never waits for that
        module = await asyncio.to_thread(importlib.import_module, f"appliance.service.{name}")
        cls = {"http": "HttpFace", "mqtt": "MqttFace", "opcua": "OpcUaFace"}[name]
        face: Face = getattr(module, cls)(section, self)
        return face

    async def _start_face(self, name: str, section: Any) -> None:
        try:
            face = await self._make(name, section)
            await face.start()
        except ImportError as exc:
            pkg = {"http": "aiohttp", "mqtt": "aiomqtt", "opcua": "asyncua"}[name]
            why = f"the Python package {pkg} is not installed ({exc}); pip install '{pkg}' or scripts/setup-env"
        except (ApplianceError, OSError) as exc:
            why = str(exc)
        else:
            self._faces[name] = face
            self.disabled.pop(name, None)
            return
        self.disabled[name] = why
        log.error("%s face disabled: %s", name, why)
        self.board.error("service", f"{name} face disabled: {why}")

    async def start(self) -> None:
        """Follow the board and start the faces the configuration enables."""
        self.cfg = self.host.cfg
        self.host.subscribe(self._on_board, self._on_scan)
        for name, section in self._wanted(self.cfg).items():
            await self._start_face(name, section)
        self.started.set()

    async def apply(self, new: AppConfig) -> None:
        """Take a new configuration: restart only the faces whose section changed."""
        renamed = new.serial != self.cfg.serial  # the MQTT topics and the OPC UA application URI name it
        old, self.cfg = self._wanted(self.cfg), new
        want = self._wanted(new)
        for name in ("http", "mqtt", "opcua"):
            same = old.get(name) == want.get(name) and not (renamed and name != "http")
            if same and (name in self._faces or name not in want):
                continue
            face = self._faces.pop(name, None)
            if face is not None:
                await face.close()
            self.disabled.pop(name, None)
            if name in want:
                await self._start_face(name, want[name])

    async def close(self) -> None:
        """Close every face and stop following the board."""
        self.host.unsubscribe(self._on_board, self._on_scan)
        for face in list(self._faces.values())[::-1]:
            try:
                await face.close()
            except Exception:  # closing one face must not keep the others open
                log.exception("closing a face failed")
        self._faces.clear()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    def face(self, name: str) -> Face | None:
        """A running face by name (``http``, ``mqtt``, ``opcua``)."""
        return self._faces.get(name)
