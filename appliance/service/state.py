"""The service's state machine and everything ``scan3d status`` shows.

States: ``starting`` (phases load config → connect hardware → warm kernels), ``idle``, ``scanning``
(projecting and capturing), ``processing`` (decode finish, triangulation), ``writing`` (files to the share or
spool), ``tuning`` (``scan3d tune`` probing the scene on the rig; triggers are refused), ``fault`` (hardware
absent or failed; retried with backoff), ``stopping``. Every change notifies the listeners (sd_notify STATUS,
mDNS TXT, controller lamps), so the state is published, not just logged.
"""

from __future__ import annotations

import datetime as dt
import enum
import logging
import re
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from appliance import __version__

log = logging.getLogger(__name__)

LAST_SCANS_KEPT = 10


class State(enum.StrEnum):
    """What the service is doing."""

    STARTING = "starting"
    IDLE = "idle"
    SCANNING = "scanning"
    PROCESSING = "processing"
    WRITING = "writing"
    TUNING = "tuning"
    FAULT = "fault"
    STOPPING = "stopping"


class Phase(enum.StrEnum):
    """Start-up phase (published while ``starting`` and ``fault``)."""

    LOAD_CONFIG = "load config"
    CONNECT = "connect hardware"
    WARM = "warm kernels"
    READY = "ready"
    STOPPING = "stopping"


BUSY_STATES = frozenset({State.SCANNING, State.PROCESSING, State.WRITING, State.TUNING})


@dataclass
class DeviceStatus:
    """One device as the service last saw it."""

    role: str  # camera / projector / trigger
    name: str
    backend: str
    ok: bool = False
    detail: str = "not connected"


@dataclass
class ScanRecord:
    """One finished (or failed) scan."""

    scan_id: str
    started_utc: str
    trigger: str
    ok: bool
    points: int = 0
    location: str = ""  # share / spool
    files: list[str] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)
    error: str = ""
    calibration_health: dict[str, Any] = field(default_factory=dict)
    # camera-camera scans: of the reference camera's pixels both cameras see, how many got a point
    # ({"pixels", "reconstructed", "share"}, the sidecar's extra.stereo.both_seen); empty otherwise
    both_seen: dict[str, Any] = field(default_factory=dict)
    # why pixels have no point: per camera the sidecar's reason_shares ({reason: share of the image, 0..1})
    reasons: dict[str, dict[str, float]] = field(default_factory=dict)
    # per camera the share of the image lit by two copies of the pattern (a mirror) whose direct code was taken
    # apart, so that they have a point (the sidecar's counts.cameras.<cam>.separated / pixels); empty: none
    separated: dict[str, float] = field(default_factory=dict)
    # the sidecar's plain-words warnings (a dominant reason with what to do, a stage that dropped most)
    warnings: list[str] = field(default_factory=list)
    # multi-exposure scans: {"exposures_us": [...], "cameras": {cam: [{exposure_us, decoded_share,
    # pixel_share}, ...]}} (the sidecar's extra.hdr, darkest pass first); empty without sequence.exposures_us
    hdr: dict[str, Any] = field(default_factory=dict)


def scan_findings(counts: dict[str, Any], warnings: list[str], extra: dict[str, Any]) -> dict[str, Any]:
    """What a scan's sidecar says of its missing pixels, as :class:`ScanRecord` fields (``reasons``,
    ``warnings``, ``hdr``, ``separated``).

    Parameters
    ----------
    counts : dict
        The sidecar's ``counts`` (``cameras.<cam>.reason_shares``, ``separated`` and ``pixels``).
    warnings : list of str
        The sidecar's ``warnings``.
    extra : dict
        The sidecar's ``extra`` (``hdr``: the exposures and, per camera, what each pass gave).
    """
    cams = counts.get("cameras", {}) if isinstance(counts.get("cameras"), dict) else {}
    reasons = {str(n): {str(k): float(v) for k, v in c.get("reason_shares", {}).items()}
               for n, c in cams.items() if isinstance(c, dict)}
    hdr: dict[str, Any] = {}
    block = extra.get("hdr")
    if isinstance(block, dict) and block.get("exposures_us"):
        per = block.get("cameras", {}) if isinstance(block.get("cameras"), dict) else {}
        keep = ("exposure_us", "decoded_share", "pixel_share")
        hdr = {"exposures_us": [float(e) for e in block["exposures_us"]],
               "cameras": {str(n): [{k: p.get(k) for k in keep} for p in c.get("passes", []) if isinstance(p, dict)]
                           for n, c in per.items() if isinstance(c, dict)}}  # fmt: skip
    separated = {str(n): round(float(c["separated"]) / max(float(c.get("pixels", 0) or 0), 1.0), 6)
                 for n, c in cams.items()
                 if isinstance(c, dict) and isinstance(c.get("separated"), (int, float)) and c["separated"] > 0}
    return {"reasons": reasons, "warnings": [str(w) for w in warnings], "hdr": hdr, "separated": separated}


@dataclass
class ErrorRecord:
    """The last error: when, where, what and what to do."""

    time_utc: str
    where: str
    message: str
    advice: str


_DEVICE_RE = re.compile(
    r"\b(?:camera '[^']*' \((?P<cam>[\w-]+)|trigger (?P<trig>[\w-]+)|(?P<proj>projector|lightcrafter))", re.IGNORECASE)

_CAMERA_ADVICE = {
    "sim": "the virtual rig's simulated camera failed: a software fault, not a cable; look at the log "
           "(journalctl -u scan3d -e); the next trigger tries again",
    "aravis": "check the camera's power and cable (a network cable: ping its address; scan3d devices); the "
              "service retries by itself",
    "uvc": "check the camera's USB cable (ls /dev/video*; scan3d devices); the service retries by itself",
}
_TRIGGER_ADVICE = {
    "serial": "check the trigger controller's USB cable (ls /dev/serial/by-id/); the service retries by itself",
    "gpio": "check the button's wiring and trigger.chip / trigger.line (gpioinfo); the service retries by itself",
    "sim": "the virtual rig's simulated button failed: a software fault, not a cable; look at the log "
           "(journalctl -u scan3d -e)",
}


def _disk_advice(m: str) -> str:
    if "read-only" in m or "errno 30" in m:
        return ("the folder is on a read-only filesystem: remount it read-write (mount; dmesg for disk errors) "
                "or point output.spool_directory / output.directory at a writable folder")
    if "permission denied" in m or "errno 13" in m or "not writable" in m:
        return ("the service user has no permission to write there: fix the folder's owner and mode (ls -ld; "
                "chown scan3d) or the unit's ReadWritePaths=")
    if "inode" in m:
        return "the filesystem has no free inodes left (df -i): remove old files"
    return "free space on the share / spool disk (df -h), or lower output.min_free_mb"


def advice_for(where: str, message: str) -> str:
    """What a person should do about an error (one line), by where it happened, the device and backend it
    names (``camera 'left' (aravis, ...)``, ``trigger serial``) and the cause in the message."""
    m = message.lower()
    if where == "config":
        return ("fix the file (scan3d validate-config FILE shows the problem); the last good configuration "
                "keeps running until then")
    if where == "share":
        return ("check that the share is mounted and writable (mount, df -h); scans are kept in the spool "
                "and moved over automatically when it is back")
    if where == "disk":
        return _disk_advice(m)
    found = _DEVICE_RE.search(message)
    if found is not None:
        if found["cam"] is not None:
            return _CAMERA_ADVICE.get(found["cam"].lower(), "check the camera's power and cable (scan3d devices); "
                                      "the service retries by itself")
        if found["trig"] is not None:
            return _TRIGGER_ADVICE.get(found["trig"].lower(), "check the trigger device and its cable "
                                       "(scan3d devices); the service retries by itself")
        if "(sim" in m or "projector sim" in m:
            return "the virtual rig's simulated projector failed: a software fault; look at the log"
        if "display" in m and "lightcrafter" not in m:
            return "check the projector's video cable (HDMI/DP) and that its output is on; the service retries"
        return "check the projector's power and USB cable (scan3d devices); the service retries by itself"
    if where == "scan":
        return "look at the log (journalctl -u scan3d); the next trigger tries again"
    return "look at the log (journalctl -u scan3d -e)"


def _now_utc() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


Listener = Callable[["StatusBoard"], None]


class StatusBoard:
    """The published state of the service: state, phase, devices, counters, last scans, last error."""

    def __init__(self, serial: str = "", config_path: str = "") -> None:
        self.state = State.STARTING
        self.phase = Phase.LOAD_CONFIG
        self.detail = ""
        self.serial = serial
        self.config_path = config_path
        self.config_error = ""
        self.config_loaded_utc = ""
        self.devices: dict[str, DeviceStatus] = {}
        self.counters: dict[str, int] = {
            "triggers": 0, "scans_done": 0, "scans_failed": 0, "triggers_refused": 0, "triggers_queued": 0,
            "spooled": 0, "spool_dropped": 0, "reloads": 0, "reloads_rejected": 0,
        }
        self.last_scans: deque[ScanRecord] = deque(maxlen=LAST_SCANS_KEPT)
        self.last_error: ErrorRecord | None = None
        self.share: dict[str, Any] = {}
        self.queue_length = 0
        self.started_monotonic = time.monotonic()
        self.started_utc = _now_utc()
        self.sequence = ""
        self.revision = 0  # +1 at every change: a reader can tell an older copy of the board from a newer one
        self._listeners: list[Listener] = []

    def subscribe(self, listener: Listener) -> None:
        """Call ``listener(board)`` after every change."""
        self._listeners.append(listener)

    def unsubscribe(self, listener: Listener) -> None:
        """Stop calling ``listener``."""
        if listener in self._listeners:
            self._listeners.remove(listener)

    def changed(self) -> None:
        """Count a new :attr:`revision` and tell the listeners (a failing listener is logged, never raised)."""
        self.revision += 1
        for fn in list(self._listeners):
            try:
                fn(self)
            except Exception:  # a broken listener must not stop the service
                log.exception("status listener %r failed", fn)

    def set_state(self, state: State, detail: str = "", phase: Phase | None = None) -> None:
        """Move to ``state``; logged when it changes."""
        if state != self.state or (phase is not None and phase != self.phase):
            log.info("state %s -> %s%s", self.state, state, f" ({detail})" if detail else "")
        self.state = state
        self.detail = detail
        if phase is not None:
            self.phase = phase
        self.changed()

    def count(self, key: str, n: int = 1) -> None:
        """Add ``n`` to counter ``key``."""
        self.counters[key] = self.counters.get(key, 0) + n
        self.changed()

    def error(self, where: str, message: str) -> ErrorRecord:
        """Record the last error (and the advice for it)."""
        self.last_error = ErrorRecord(_now_utc(), where, message, advice_for(where, message))
        self.changed()
        return self.last_error

    def add_scan(self, record: ScanRecord) -> None:
        """Remember a finished or failed scan."""
        self.last_scans.append(record)
        self.changed()

    @property
    def busy(self) -> bool:
        """True while a scan runs (scanning, processing or writing) or a tune probes the rig."""
        return self.state in BUSY_STATES

    def last_scan_id(self) -> str:
        """The id of the last successful scan ('' before the first)."""
        for rec in reversed(self.last_scans):
            if rec.ok:
                return rec.scan_id
        return ""

    def one_line(self) -> str:
        """A short line for systemd's STATUS and the log."""
        text = f"{self.state}"
        if self.state in (State.STARTING, State.FAULT):
            text += f" ({self.phase})"
        if self.detail:
            text += f": {self.detail}"
        text += f"; {self.counters['scans_done']} scans"
        if self.last_scan_id():
            text += f", last {self.last_scan_id()}"
        return text

    def calibration_health(self) -> dict[str, Any]:
        """The calibration health of the last scan that measured it (``{}`` before any)."""
        for r in reversed(self.last_scans):
            if r.ok and r.calibration_health:
                return {"scan_id": r.scan_id, **r.calibration_health}
        return {}

    def snapshot(self) -> dict[str, Any]:
        """Everything, as JSON-ready data (what ``scan3d status --json`` prints)."""
        return {
            "state": str(self.state),
            "phase": str(self.phase),
            "detail": self.detail,
            "version": __version__,
            "serial": self.serial,
            "revision": self.revision,
            "uptime_s": round(time.monotonic() - self.started_monotonic, 1),
            "started_utc": self.started_utc,
            "config": {"path": self.config_path, "loaded_utc": self.config_loaded_utc,
                       "error": self.config_error},
            "sequence": self.sequence,
            "devices": [asdict(d) for d in self.devices.values()],
            "counters": dict(self.counters),
            "queue_length": self.queue_length,
            "share": dict(self.share),
            "last_scans": [asdict(r) for r in self.last_scans],
            "calibration_health": self.calibration_health(),
            "last_error": asdict(self.last_error) if self.last_error is not None else None,
        }
