"""The JSON metadata written beside each cloud."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance import __version__
from appliance.output.atomic import write_bytes_atomic


@dataclass
class ScanMetadata:
    """What a downstream machine needs to know about a cloud.

    Attributes
    ----------
    scan_id : str
        Unique id, also the file stem (``YYYYmmdd-HHMMSS-<serial>-<n>``).
    time_utc : str
        ISO 8601 start time of the scan (UTC).
    sequence : dict
        ``describe`` text, frame count and projector size.
    calibration_hash : str
        Short hash of the calibration content used.
    counts : dict
        ``points``, per-camera ``decoded_pixels`` and ``points``.
    timings_ms : dict
        Per-stage wall times (ms).
    stages : list of dict
        Per camera, the candidates left after each reconstruction stage and the rejections per stage
        (:meth:`appliance.reconstruct.types.StageCounts.as_dict`).
    warnings : list of str
        Plain-words warnings of the reconstruction (a stage that rejected most of its candidates).
    calibration_health : dict
        Whether this scan's redundant measurements still fit the calibration: ``status`` (ok | drifting |
        bad | not measured), per residual kind the robust RMS (px, mm), the reference the calibration
        promised, the limit and the number of samples (:func:`appliance.calibration.scan_health.assess_scan`).
    """

    scan_id: str
    time_utc: str
    sequence: dict[str, Any]
    calibration_hash: str
    counts: dict[str, Any]
    timings_ms: dict[str, float]
    appliance_serial: str = ""
    software_version: str = __version__
    cameras: list[str] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    stages: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    calibration_health: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        """Pretty JSON text."""
        d = {k: v for k, v in self.__dict__.items()}
        d["timings_ms"] = {k: round(float(v), 3) for k, v in self.timings_ms.items()}
        return json.dumps(d, indent=2, sort_keys=False) + "\n"


def write_sidecar(path: str | Path, meta: ScanMetadata) -> Path:
    """Write ``meta`` as JSON to ``path`` atomically."""
    return write_bytes_atomic(Path(path), meta.to_json().encode())
