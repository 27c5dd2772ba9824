"""Calibration health of one scan: its redundant residuals judged against the calibration and their trend.

:class:`~appliance.reconstruct.pipeline.Reconstructor` measures the residuals wherever a scan is
overdetermined (:mod:`appliance.reconstruct.residuals`); this module compares each with what the
calibration promised (the stated reprojection RMS of the devices involved, root-sum-square, at least
:data:`REFERENCE_FLOOR_PX`: the code noise of a perfect calibration, e.g. the virtual rig's) and with its own
history (:class:`~appliance.calibration.health.TrendStore`), and folds the verdicts into the one
``calibration_health`` block that sidecars, ``scan3d status``, the mDNS TXT record and ``scan3d decode
--report`` show.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from appliance.calibration.health import CalibrationHealth, TrendStore, assess_health
from appliance.geometry.calibration_file import Calibration
from appliance.reconstruct.residuals import Residual

REFERENCE_FLOOR_PX = 0.2
"""A residual's reference RMS is at least this (px): code noise and quantisation of a perfect calibration."""

TREND_FILE = "calibration_health.json"
"""Name of the trend file in the state directory."""

_RANK = {"ok": 0, "drifting": 1, "bad": 2}


def reference_px(residual: Residual, calibration: Calibration) -> float:
    """What the calibration promised for ``residual`` (px): root-sum-square of the stated RMS of its devices.

    Parameters
    ----------
    residual : Residual
        Names its devices (``'cam0/projector'``, ``'cam0/cam1'``, ...).
    calibration : Calibration
        The calibration the scan used (``rms`` of each device: NaN or 0 when not stated).

    Returns
    -------
    float
        At least :data:`REFERENCE_FLOOR_PX`.
    """
    total = 0.0
    for name in residual.devices.split("/"):
        dev = calibration.devices.get(name)
        if dev is not None and math.isfinite(dev.rms):
            total += dev.rms**2
    return max(math.sqrt(total), REFERENCE_FLOOR_PX)


def trend_for(state_directory: Path, context: str | None = None) -> TrendStore:
    """The trend store of an appliance (``<state directory>/calibration_health.json``); ``context``: what its
    residuals depend on besides the calibration (the sequence's description), see ``TrendStore.context``."""
    return TrendStore(Path(state_directory) / TREND_FILE, context=context)


def assess_scan(
    residuals: Iterable[Residual],
    calibration: Calibration,
    trend: TrendStore | None = None,
    tolerance_px: float | None = None,
) -> dict[str, Any]:
    """Judge every residual of one scan and fold them into one ``calibration_health`` block.

    Parameters
    ----------
    residuals : iterable of Residual
        The scan's residuals (``Reconstructor.residuals``).
    calibration : Calibration
        The calibration the scan used.
    trend : TrendStore, optional
        History of earlier scans (judges ``drifting``; this scan is appended).
    tolerance_px : float, optional
        ``bad`` beyond this robust RMS (px); default 3 x each residual's reference.

    Returns
    -------
    dict
        ``status`` (``ok`` | ``drifting`` | ``bad``, the worst of the checks; ``not measured`` where the scan
        had no redundancy), ``checks`` (one :class:`~appliance.calibration.health.CalibrationHealth` dict per
        residual kind, with the devices), ``samples`` (residuals in all) and ``reason`` (the worst check's).
    """
    checks: list[tuple[CalibrationHealth, Residual]] = []
    for res in residuals:
        ref = reference_px(res, calibration)
        mm = res.values_px * res.mm_per_px if math.isfinite(res.mm_per_px) else None
        kind = f"{res.kind}:{res.devices}"
        h = assess_health(res.values_px, ref, kind=kind, residuals_mm=mm,
                          reference_mm=ref * res.mm_per_px if math.isfinite(res.mm_per_px) else None,
                          tolerance_px=tolerance_px, trend=trend)  # fmt: skip
        checks.append((h, res))
    if not checks:
        return {"status": "not measured", "checks": [], "samples": 0,
                "reason": "this scan has no redundancy (one camera, one coded axis): code both axes or add a "
                          "second camera to measure it"}  # fmt: skip
    worst = max(checks, key=lambda c: _RANK[c[0].status])[0]
    return {
        "status": worst.status,
        "checks": [{**h.as_dict(), "devices": r.devices} for h, r in checks],
        "samples": sum(h.n_samples for h, _ in checks),
        "reason": f"{worst.kind}: {worst.reason}",
    }
