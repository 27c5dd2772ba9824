"""Calibration health: does this scan's redundancy still agree with what the calibration promised?

Where a scan measures something twice (two cameras: the epipolar residual of matches; both projector axes:
the closest distance of the two rays; camera-camera plus camera-projector: the three-view residual), the
spread of those residuals is what the calibration's own reprojection RMS predicts. :func:`assess_health`
compares a robust RMS of this scan's residuals with that reference and with the trend of earlier scans:
``bad`` beyond the tolerance, ``drifting`` when the value leaves its own history by more than
``DRIFT_SIGMAS`` standard deviations, ``ok`` otherwise. :class:`TrendStore` keeps the last scans' values per
kind of residual in a JSON file in the state directory (written atomically).

This module is pure numerics and file I/O; the reconstruction and the service decide which residuals to
pass and where the result is shown.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError

log = logging.getLogger(__name__)

HealthStatus = Literal["ok", "drifting", "bad"]
BAD_FACTOR = 3.0
"""Without an explicit tolerance, a residual RMS beyond this many times the reference is ``bad``."""
DRIFT_SIGMAS = 3.0
"""``drifting`` when this scan's value is further than this many standard deviations from its history."""
MIN_HISTORY = 5
"""Scans of history needed before drift is judged."""
MIN_SAMPLES = 50
"""Residuals needed in a scan before it is judged (fewer: ``ok``, not recorded in the trend)."""
RELATIVE_SIGMA_FLOOR = 0.02
"""The history's standard deviation is taken as at least this share of its mean (a noiseless history, e.g.
on the virtual rig, would otherwise flag the smallest change)."""
TREND_LENGTH = 50
"""Scans kept per kind of residual."""
_GAUSS_MEDIAN_SQ = 0.4549364231195724  # median of chi-square with 1 degree of freedom


@dataclass(frozen=True)
class CalibrationHealth:
    """How well this scan's redundant measurements agree with the calibration.

    Attributes
    ----------
    status : {'ok', 'drifting', 'bad'}
        The verdict.
    kind : str
        Which residual (``epipolar``, ``ray_ray``, ``three_view``, ...).
    residual_px : float
        Robust RMS of this scan's residuals (px); NaN without samples.
    residual_mm : float or None
        The same in mm where the residual has a length (ray-ray distance), else None.
    reference_px : float
        What the calibration promised for this residual (px).
    reference_mm : float or None
        The reference in mm where known.
    limit_px : float
        Beyond this robust RMS the status is ``bad`` (px).
    n_samples : int
        Residuals in this scan.
    reason : str
        One line: why this status.
    """

    status: HealthStatus
    kind: str
    residual_px: float
    residual_mm: float | None
    reference_px: float
    reference_mm: float | None
    limit_px: float
    n_samples: int
    reason: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN as None)."""
        out = asdict(self)
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in out.items()}


def robust_rms(residuals: npt.ArrayLike) -> float:
    """RMS of residuals estimated from their median square (outliers up to half the samples do not count).

    Parameters
    ----------
    residuals : array_like, shape (N,)
        Signed or unsigned residuals (any unit); NaN ignored.

    Returns
    -------
    float
        ``sqrt(median(r^2) / 0.455)``: the RMS for Gaussian residuals (a share of outliers biases it up a
        little: about 6 % at 5 % outliers); NaN without finite samples.
    """
    r = np.asarray(residuals, np.float64).ravel()
    r = r[np.isfinite(r)]
    if r.size == 0:
        return float("nan")
    return float(np.sqrt(np.median(r * r) / _GAUSS_MEDIAN_SQ))


class TrendStore:
    """The last scans' residual RMS per kind, in a JSON file (written atomically: temp, fsync, rename).

    Parameters
    ----------
    path : Path
        The file, e.g. ``<state directory>/calibration_health.json``. A missing file is an empty history;
        an unreadable one is moved aside to ``<name>.corrupt`` (logged) and the history starts again.
    length : int
        Scans kept per kind.
    """

    def __init__(self, path: Path, length: int = TREND_LENGTH, context: str | None = None) -> None:
        if length < MIN_HISTORY + 1:
            raise CalibrationError(f"calibration health trend length {length}: must be >= {MIN_HISTORY + 1}")
        self.path = Path(path)
        self.length = length
        self.context = context
        """What the residuals depend on besides the calibration (the scanner's sequence): only the stored scans of
        the same context are the history, so a changed sequence (say period 8 added: the three-view residual falls
        from 0.157 to 0.089 px) starts a new history instead of reading as drift."""
        self._data: dict[str, list[dict[str, Any]]] = self._load()

    def _load(self) -> dict[str, list[dict[str, Any]]]:
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return {}
        except OSError as exc:
            raise CalibrationError(
                f"calibration health trend {self.path}: cannot read ({exc.strerror}); check the state directory"
            ) from exc
        try:
            raw = json.loads(text)
            kinds = raw["kinds"]
            if not isinstance(kinds, dict):
                raise TypeError("kinds is not a mapping")
            return {str(k): [e for e in v if isinstance(e, dict) and "residual_px" in e] for k, v in kinds.items()}
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            aside = self.path.with_name(self.path.name + ".corrupt")
            log.warning("calibration health trend %s is unreadable (%s): moved to %s, history restarts",
                        self.path, exc, aside)  # fmt: skip
            try:
                os.replace(self.path, aside)
            except OSError:
                pass
            return {}

    def history(self, kind: str) -> list[float]:
        """Residual RMS (px) of the stored scans of ``kind`` in this store's context, oldest first."""
        return [float(e["residual_px"]) for e in self._data.get(kind, []) if e.get("context") == self.context]

    def append(self, kind: str, residual_px: float, status: str) -> None:
        """Record one scan's value (in this store's context) and write the file."""
        entries = self._data.setdefault(kind, [])
        entry: dict[str, Any] = {"time": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                                 "residual_px": float(residual_px), "status": status}  # fmt: skip
        if self.context is not None:
            entry["context"] = self.context
        entries.append(entry)
        del entries[: max(len(entries) - self.length, 0)]
        self._write()

    def _write(self) -> None:
        doc = json.dumps({"version": 1, "kinds": self._data}, indent=1)
        folder = self.path.parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=folder)
            try:
                with os.fdopen(fd, "w", encoding="utf-8") as f:
                    f.write(doc)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
            dfd = os.open(folder, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError as exc:
            raise CalibrationError(
                f"calibration health trend {self.path}: cannot write ({exc.strerror}); check the state directory"
            ) from exc


def assess_health(
    residuals_px: npt.ArrayLike,
    reference_px: float,
    *,
    kind: str,
    residuals_mm: npt.ArrayLike | None = None,
    reference_mm: float | None = None,
    tolerance_px: float | None = None,
    trend: TrendStore | None = None,
    min_samples: int = MIN_SAMPLES,
) -> CalibrationHealth:
    """Judge one scan's redundant residuals against the calibration and the trend of earlier scans.

    Parameters
    ----------
    residuals_px : array_like, shape (N,)
        This scan's residuals of one kind (px), signed or unsigned; NaN ignored.
    reference_px : float
        The RMS the calibration promises for this residual (px), e.g. its stated reprojection RMS scaled
        for the kind of residual; > 0.
    kind : str
        Name of the residual (the trend is kept per kind).
    residuals_mm : array_like, optional
        The same residuals as lengths (mm), reported alongside.
    reference_mm : float, optional
        The reference in mm, reported alongside.
    tolerance_px : float, optional
        ``bad`` beyond this robust RMS (px); default ``BAD_FACTOR`` x ``reference_px``.
    trend : TrendStore, optional
        History of earlier scans; this scan is appended when it has enough samples.
    min_samples : int
        Fewer finite residuals are not judged (status ``ok``, not recorded).

    Returns
    -------
    CalibrationHealth

    Raises
    ------
    CalibrationError
        A reference or tolerance that is not > 0.
    """
    if not (np.isfinite(reference_px) and reference_px > 0):
        raise CalibrationError(f"calibration health ({kind}): reference {reference_px} px must be > 0")
    limit = BAD_FACTOR * reference_px if tolerance_px is None else float(tolerance_px)
    if not (np.isfinite(limit) and limit > 0):
        raise CalibrationError(f"calibration health ({kind}): tolerance {tolerance_px} px must be > 0")
    r = np.asarray(residuals_px, np.float64).ravel()
    n = int(np.isfinite(r).sum())
    value = robust_rms(r)
    value_mm = robust_rms(residuals_mm) if residuals_mm is not None else None

    def result(status: HealthStatus, reason: str) -> CalibrationHealth:
        return CalibrationHealth(status, kind, value, value_mm, float(reference_px), reference_mm, limit, n, reason)

    if n < min_samples:
        return result("ok", f"not judged: {n} samples (need >= {min_samples})")
    history = trend.history(kind) if trend is not None else []
    if value > limit:
        status: HealthStatus = "bad"
        reason = f"residual {value:.3f} px > limit {limit:.3f} px (calibration promised {reference_px:.3f} px)"
    else:
        status, reason = "ok", f"residual {value:.3f} px within {limit:.3f} px"
        if len(history) >= MIN_HISTORY:
            h = np.asarray(history)
            mean = float(h.mean())
            sigma = max(float(h.std(ddof=1)), RELATIVE_SIGMA_FLOOR * abs(mean), 1e-9)
            k = (value - mean) / sigma
            if abs(k) > DRIFT_SIGMAS:
                status = "drifting"
                reason = (f"residual {value:.3f} px is {k:+.1f} sigma from its last {len(h)} scans "
                          f"({mean:.3f} ± {sigma:.3f} px)")  # fmt: skip
            else:
                reason += f", {k:+.1f} sigma from its last {len(h)} scans"
    if trend is not None:
        trend.append(kind, value, status)
    return result(status, reason)
