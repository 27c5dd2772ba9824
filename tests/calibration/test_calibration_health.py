"""Calibration health: robust residual RMS against the calibration's promise and against its own trend."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from appliance.calibration.health import (
    MIN_HISTORY,
    TrendStore,
    assess_health,
    robust_rms,
)
from appliance.errors import CalibrationError


def scan(rng: np.random.Generator, sigma_px: float, n: int = 5000, outliers: float = 0.05) -> np.ndarray:
    r = rng.normal(0, sigma_px, n)
    bad = rng.random(n) < outliers
    r[bad] = rng.uniform(-50, 50, bad.sum())  # wrong matches: must not move the figure
    return r


@pytest.mark.parametrize("sigma", [0.05, 0.3, 2.0])
def test_robust_rms_ignores_outliers(sigma: float) -> None:
    rng = np.random.default_rng(1)
    # 5 % wrong matches bias the median-based figure by about 6 %; an ordinary RMS would be 100x off
    assert robust_rms(scan(rng, sigma, 20000, outliers=0.05)) == pytest.approx(sigma, rel=0.1)
    assert np.isnan(robust_rms([np.nan, np.nan]))


def test_exact_calibration_reads_ok_every_scan(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    store = TrendStore(tmp_path / "state" / "calibration_health.json")
    for _ in range(12):
        h = assess_health(scan(rng, 0.1), 0.1, kind="epipolar", trend=store)
        assert h.status == "ok", h.reason
        assert h.residual_px == pytest.approx(0.1, rel=0.15) and h.n_samples == 5000
    assert len(store.history("epipolar")) == 12
    d = h.as_dict()
    assert d["status"] == "ok" and d["reference_px"] == 0.1 and d["residual_mm"] is None


def test_beyond_the_tolerance_is_bad() -> None:
    rng = np.random.default_rng(3)
    h = assess_health(scan(rng, 0.5), 0.1, kind="epipolar", residuals_mm=scan(rng, 0.2), reference_mm=0.05)
    assert h.status == "bad" and h.limit_px == pytest.approx(0.3)
    assert h.residual_mm == pytest.approx(0.2, rel=0.15) and "> limit" in h.reason
    assert assess_health(scan(rng, 0.5), 0.1, kind="epipolar", tolerance_px=1.0).status == "ok"


def test_a_step_beyond_three_sigma_of_the_history_is_drifting(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    store = TrendStore(tmp_path / "health.json")
    for _ in range(8):
        assert assess_health(scan(rng, 0.10), 0.1, kind="ray_ray", trend=store).status == "ok"
    # a projector turned a little: residuals grow by 30 %, still well inside the tolerance (0.3 px)
    h = assess_health(scan(rng, 0.13), 0.1, kind="ray_ray", trend=store)
    assert h.status == "drifting" and "sigma from its last 8 scans" in h.reason
    # the trend is per kind: another residual has no history yet
    assert assess_health(scan(rng, 0.13), 0.1, kind="epipolar", trend=store).status == "ok"


def test_a_changed_sequence_starts_a_new_history_instead_of_drifting(tmp_path: Path) -> None:
    # the residuals depend on the code as well as the calibration: period 8 added to period 16 takes the default
    # rig's three-view residual from 0.157 to 0.089 px, which against the old history read as drifting (-19.8 sigma)
    rng = np.random.default_rng(5)
    path = tmp_path / "health.json"
    old = TrendStore(path, context="P16")
    for _ in range(8):
        assert assess_health(scan(rng, 0.16), 0.1, kind="three_view", trend=old).status == "ok"
    new = TrendStore(path, context="P16 P8")
    h = assess_health(scan(rng, 0.09), 0.1, kind="three_view", trend=new)
    assert h.status == "ok" and "sigma from" not in h.reason, h.reason
    assert len(new.history("three_view")) == 1 and len(TrendStore(path, context="P16").history("three_view")) == 8
    # the file keeps both (the window is per kind); entries written before contexts existed are no one's history
    doc = json.loads(path.read_text())
    assert [e["context"] for e in doc["kinds"]["three_view"]] == ["P16"] * 8 + ["P16 P8"]
    assert TrendStore(path).history("three_view") == []
    # back on the old sequence its history holds: the same step is drifting there
    assert assess_health(scan(rng, 0.09), 0.1, kind="three_view", trend=TrendStore(path, context="P16")).status == (
        "drifting")


def test_too_few_samples_are_not_judged_or_recorded(tmp_path: Path) -> None:
    store = TrendStore(tmp_path / "health.json")
    h = assess_health(np.full(10, 5.0), 0.1, kind="epipolar", trend=store)
    assert h.status == "ok" and h.reason.startswith("not judged: 10 samples")
    assert store.history("epipolar") == []


def test_trend_file_survives_a_restart_and_keeps_the_last_scans(tmp_path: Path) -> None:
    path = tmp_path / "health.json"
    store = TrendStore(path, length=MIN_HISTORY + 2)
    for k in range(10):
        store.append("epipolar", 0.1 + k / 100, "ok")
    again = TrendStore(path, length=MIN_HISTORY + 2)
    assert again.history("epipolar") == pytest.approx([0.1 + k / 100 for k in range(3, 10)])
    assert json.loads(path.read_text())["version"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["health.json"]  # no temporary file left behind


def test_unreadable_trend_file_is_moved_aside(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "health.json"
    path.write_text("{not json")
    store = TrendStore(path)
    assert store.history("epipolar") == []
    assert (tmp_path / "health.json.corrupt").read_text() == "{not json"
    assert "unreadable" in caplog.text
    store.append("epipolar", 0.1, "ok")
    assert TrendStore(path).history("epipolar") == [0.1]


def test_bad_reference_is_an_error() -> None:
    with pytest.raises(CalibrationError, match=r"reference 0\.0 px must be > 0"):
        assess_health(np.zeros(100), 0.0, kind="epipolar")
