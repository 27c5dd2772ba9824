"""A scan and an offline decode of recorded frames run the same code from the decoded maps on.

``scan3d scan`` (frames from the virtual rig's cameras) and ``scan3d decode`` (frames from a manifest) are run
through ``cli.main`` with the replay module's shared steps wrapped: both must go through the same reconstruction
call (:func:`appliance.replay.reconstruct`), the same sidecar content (:func:`appliance.replay.scan_metadata`)
and the same "result -> files" step (:func:`appliance.replay.result_files`).
"""

from __future__ import annotations

import contextlib
import io
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance import cli, replay

SMALL = """
cameras: {cam0: {type: sim}}
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
reconstruction: {min_depth_mm: 300, max_depth_mm: 900}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 380], position_mm: [175, 0, 0],
              look_at_mm: [0, 40, 580]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 450, position_mm: [0, 0, 0], look_at_mm: [0, 0, 580]}
"""

SHARED = ("reconstruct", "scan_metadata", "result_files")


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> Counter[str]:
    """Counts the calls of the replay module's shared steps (each still does its work)."""
    seen: Counter[str] = Counter()

    def wrap(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def counted(*a: Any, **k: Any) -> Any:
            seen[name] += 1
            return fn(*a, **k)

        return counted

    for name in SHARED:
        monkeypatch.setattr(replay, name, wrap(name, getattr(replay, name)))
    return seen


def _cli(*args: object) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = cli.main([str(a) for a in args])
    return rc, out.getvalue()


def test_scan_and_decode_run_the_same_steps(tmp_path: Path, calls: Counter[str]) -> None:
    from appliance.config import parse_config
    from appliance.geometry.calibration_file import write_calibration
    from appliance.hardware.registry import build_rig
    from appliance.patterns import write_manifest
    from appliance.patterns.from_config import build_sequence
    from appliance.scan import virtual_calibration

    cfg_path = tmp_path / "small.yaml"
    cfg_path.write_text(SMALL)
    rc, out = _cli("scan", "--config", cfg_path, "--out", tmp_path / "scans")
    assert rc == 0, out
    assert calls == Counter({"reconstruct": 1, "scan_metadata": 1, "result_files": 1}), calls
    scan_ply = next((tmp_path / "scans").glob("*/*.ply"))

    # the same rig's frames, recorded, decoded offline
    calls.clear()
    cfg = parse_config(SMALL, "small.yaml")
    rig = build_rig(cfg)
    assert rig.virtual is not None
    seq = build_sequence(cfg.sequence, rig.virtual.projector.width, rig.virtual.projector.height)
    np.save(tmp_path / "cam0.npy", rig.virtual.render(seq, "cam0"))
    man = write_manifest(tmp_path / "rec.yaml", seq, ["cam0"], stacks={"cam0": "cam0.npy"})
    write_calibration(tmp_path / "calib.yaml", virtual_calibration(rig.virtual))
    rc, out = _cli("decode", man, "--calibration", tmp_path / "calib.yaml", "--config", cfg_path,
                   "--out", tmp_path / "rec.ply", "--report", tmp_path / "rec.json")  # fmt: skip
    assert rc == 0, out
    assert calls == Counter({"reconstruct": 1, "scan_metadata": 1, "result_files": 1}), calls
    assert (tmp_path / "rec.ply").stat().st_size > 1000 and scan_ply.stat().st_size > 1000
