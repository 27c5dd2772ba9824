"""Every pixel without a point says why, after the whole reconstruction: ``scan3d decode --report --maps`` in
each mode (camera-projector, camera-camera, both fused) on a two-camera virtual rig. The sidecar's reasons sum
to the image's pixels, reason 0 ("decoded") is exactly the pixels with a point, the decoded pixels without one
carry a later stage's reason, and ``--maps <cam>_reason`` is the same map."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from plyfile import PlyData

from appliance import cli
from appliance.config import parse_config
from appliance.geometry.calibration_file import Calibration, write_calibration
from appliance.patterns.manifest import write_manifest
from appliance.reconstruct.types import REASON_NAMES, Reason
from appliance.scan import build_sequence, virtual_calibration
from appliance.sim.rig import VirtualRig

# a narrow depth range cuts the plane behind the objects (out of range) and leaves edges to the filters
RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 380], position_mm: [175, 0, 0],
              look_at_mm: [0, 40, 580]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 450, position_mm: [0, 0, 0], look_at_mm: [0, 0, 580]}
    cam1: {width: 320, height: 256, focal_px: 450, position_mm: [-120, 0, 0], look_at_mm: [0, 0, 580]}
"""
LATER = {Reason.NOT_MATCHED, Reason.OUT_OF_RANGE, Reason.FILTERED, Reason.EPIPOLAR, Reason.HIDDEN}


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("reasons")
    cfg = parse_config(RIG, "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    seq = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    for cam in ("cam0", "cam1"):
        np.save(folder / f"{cam}.npy", rig.render(seq, cam, seed=4))
    man = write_manifest(folder / "scan.yaml", seq, ["cam0", "cam1"], stacks={c: f"{c}.npy" for c in ("cam0", "cam1")})
    full = virtual_calibration(rig)
    files = {"manifest": man}
    for name, keep in (("procam", ("cam0", "cam1", "projector")), ("stereo", ("cam0", "cam1"))):
        files[name] = folder / f"{name}.yaml"
        write_calibration(files[name], Calibration({n: full.devices[n] for n in keep}))
    files["config"] = folder / "narrow.yaml"
    files["config"].write_text(RIG + "reconstruction: {min_depth_mm: 450, max_depth_mm: 610}\n")
    return files


def _decode(*args: Any) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["decode", *[str(a) for a in args]])
    return rc, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("mode", ["projector", "stereo", "both"])
def test_every_pixel_without_a_point_has_one_reason(capture: dict[str, Path], tmp_path: Path, mode: str) -> None:
    calib = capture["stereo" if mode == "stereo" else "procam"]
    rc, out, err = _decode(capture["manifest"], "--calibration", calib, "--mode", mode, "--config",
                           capture["config"], "--out", tmp_path / "c.ply", "--report", tmp_path / "r.json",
                           "--maps", tmp_path / "m.npz")  # fmt: skip
    assert rc == 0, err + out
    report = json.loads((tmp_path / "r.json").read_text())
    maps = np.load(tmp_path / "m.npz")
    ply = PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    names = ply.data.dtype.names
    cam_of_point = np.asarray(ply["camera"]) if "camera" in names else np.zeros(len(ply), np.int64)
    # camera-camera: the cloud is organised on cam0 (cam1's pixels give points through it)
    outputs = ("cam0",) if mode == "stereo" else ("cam0", "cam1")
    seen: set[int] = set()
    for i, name in enumerate(outputs):
        cam = report["counts"]["cameras"][name]
        reasons = cam["reasons"]
        assert sum(reasons.values()) == cam["pixels"]
        assert reasons["decoded"] == cam["points"] == int(np.sum(cam_of_point == i)) > 1000
        reason = maps[f"{name}_reason"]
        counts = np.bincount(reason.ravel(), minlength=len(REASON_NAMES))
        assert {REASON_NAMES[k]: int(c) for k, c in enumerate(counts) if c} == reasons
        # reason 0 is exactly the pixels with a point
        has = np.zeros(reason.shape, bool)
        sel = cam_of_point == i
        has[np.asarray(ply["row"])[sel], np.asarray(ply["col"])[sel]] = True
        assert np.array_equal(reason == Reason.DECODED, has)
        decoded = maps[f"{name}_mask"]
        lost = np.unique(reason[decoded & ~has]).tolist()
        assert set(lost) <= LATER, [REASON_NAMES[k] for k in lost]
        seen |= set(lost)
    # the narrow depth range and the filters leave their marks
    want = {Reason.NOT_MATCHED} if mode == "stereo" else {Reason.OUT_OF_RANGE, Reason.FILTERED}
    assert want <= seen, [REASON_NAMES[k] for k in seen]
