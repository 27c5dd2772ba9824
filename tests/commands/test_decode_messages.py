"""``scan3d decode`` says in words when a stage rejects most candidates because the calibration no longer fits.

A two-camera capture (both axes coded) of a small virtual rig, decoded camera-camera with its exact
calibration (no warning) and with the second camera's calibration 3.5 px off the epipolar geometry: the
matcher measures the offset from the (u, v) matches, corrects it, and the report and the console say that the
calibration has drifted; with a fixed epipolar limit from a config file the stage rejects most matches and
says so.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance import cli
from appliance.config import parse_config
from appliance.geometry.calibration_file import Calibration, write_calibration
from appliance.geometry.camera import CameraModel
from appliance.patterns.from_config import build_sequence
from appliance.patterns.manifest import write_manifest
from appliance.scan import virtual_calibration
from appliance.sim.rig import VirtualRig

RIG = """
sequence: {kind: gray_phase, axes: xy, periods_px: [16]}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 380], position_mm: [60, -80, 0],
              look_at_mm: [0, 40, 580]}
  cameras:
    cam0: {width: 480, height: 384, focal_px: 700, position_mm: [0, 0, 0], look_at_mm: [0, 0, 580]}
    cam1: {width: 480, height: 384, focal_px: 700, position_mm: [150, 0, 0], look_at_mm: [0, 0, 580]}
"""


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("messages")
    cfg = parse_config(RIG, "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    seq = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    for cam in ("cam0", "cam1"):
        np.save(folder / f"{cam}.npy", rig.render(seq, cam))
    files = {"manifest": write_manifest(folder / "scan.yaml", seq, ["cam0", "cam1"],
                                        stacks={c: f"{c}.npy" for c in ("cam0", "cam1")})}  # fmt: skip
    exact = virtual_calibration(rig)
    c1 = exact.devices["cam1"]
    k = c1.K.copy()
    k[1, 2] += 3.5  # cam1's principal point 3.5 px down: every epipolar line moves
    drifted = CameraModel("cam1", k, c1.dist, c1.width, c1.height, c1.R, c1.T, 0.3)
    k50 = c1.K.copy()
    k50[1, 2] += 50.0  # a calibration of another rig: 50 px off every epipolar line
    other = CameraModel("cam1", k50, c1.dist, c1.width, c1.height, c1.R, c1.T, 0.3)
    for name, cam1 in (("exact", c1), ("drifted", drifted), ("other", other)):
        files[name] = folder / f"{name}.yaml"
        write_calibration(files[name], Calibration({"cam0": exact.devices["cam0"], "cam1": cam1}))
    files["strict"] = folder / "strict.yaml"
    files["strict"].write_text("reconstruction: {stereo_max_epipolar_px: 1.0}\n")
    files["bend"] = folder / "bend.yaml"
    files["bend"].write_text("reconstruction: {stereo_drift: correct}\n")
    files["folder"] = folder
    return files


def _decode(*args: Any) -> tuple[int, str, dict[str, Any]]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["decode", *[str(a) for a in args]])
    report = Path(str(args[args.index("--report") + 1]))
    return rc, out.getvalue(), json.loads(report.read_text()) if report.exists() else {}


def test_exact_calibration_decodes_without_warnings(capture: dict[str, Path]) -> None:
    rc, text, rep = _decode(capture["manifest"], "--calibration", capture["exact"], "--report",
                            capture["folder"] / "exact.json")  # fmt: skip
    assert rc == 0, text
    assert rep["extra"]["mode"] == "stereo"
    assert rep["warnings"] == [], rep["warnings"]
    assert rep["counts"]["points"] > 0.8 * rep["counts"]["cameras"]["cam0"]["decoded_pixels"]
    assert rep["calibration_health"]["status"] == "ok"
    both = rep["extra"]["stereo"]["both_seen"]  # the share of what both cameras see that got a point
    assert both["pixels"] > 0.5 * rep["counts"]["cameras"]["cam0"]["decoded_pixels"], both
    assert 0.95 <= both["share"] <= 1.0 and both["reconstructed"] <= both["pixels"], both


def test_drifted_calibration_is_corrected_and_said(capture: dict[str, Path]) -> None:
    rc, text, rep = _decode(capture["manifest"], "--calibration", capture["drifted"], "--report",
                            capture["folder"] / "drifted.json")  # fmt: skip
    assert rc == 0, text
    said = [w for w in rep["warnings"] if "calibration has drifted" in w]
    assert said and "recalibrate" in said[0], rep["warnings"]
    assert said[0] in text  # on the console too
    assert rep["counts"]["points"] > 0.8 * rep["counts"]["cameras"]["cam0"]["decoded_pixels"]
    assert rep["calibration_health"]["status"] == "bad"  # 3.5 px against a promised 0.3 px


def test_a_fixed_epipolar_limit_rejects_most_and_says_why(capture: dict[str, Path]) -> None:
    rc, text, rep = _decode(capture["manifest"], "--calibration", capture["drifted"], "--config", capture["strict"],
                            "--report", capture["folder"] / "strict.json")  # fmt: skip
    assert rc == 0, text
    said = [w for w in rep["warnings"] if "off the epipolar line (limit 1.0)" in w]
    assert said and "the calibration may no longer fit the rig" in said[0], rep["warnings"]
    assert rep["counts"]["points"] < 0.5 * rep["counts"]["cameras"]["cam0"]["decoded_pixels"]


def test_a_calibration_50_px_off_writes_no_cloud_and_says_what_to_do(capture: dict[str, Path]) -> None:
    out = capture["folder"] / "other.ply"
    rc, text, _rep = _decode(capture["manifest"], "--calibration", capture["other"], "--out", out, "--report",
                            capture["folder"] / "other.json")  # fmt: skip
    assert rc != 0, text
    assert not out.exists()  # no centimetre-off cloud written
    assert "Traceback" not in text
    errors = [ln for ln in text.splitlines() if ln.startswith("scan3d decode:")]
    assert len(errors) == 1, text  # one line: the offset measured (50 px of principal point: ~53 rectified px)
    assert re.search(r"off by a median -?5\d\.\d px", errors[0]), errors[0]
    assert "does not fit the rig" in errors[0] and "recalibrate" in errors[0], errors[0]


def test_stereo_drift_correct_still_bends_it_when_asked(capture: dict[str, Path]) -> None:
    rc, text, rep = _decode(capture["manifest"], "--calibration", capture["other"], "--config", capture["bend"],
                            "--report", capture["folder"] / "bend.json")  # fmt: skip
    assert rc == 0, text
    assert any("calibration has drifted" in w for w in rep["warnings"]), rep["warnings"]
    assert rep["calibration_health"]["status"] == "bad"
