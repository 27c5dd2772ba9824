"""``scan3d decode`` of a multi-exposure capture: the same patterns at three exposures, fused per pixel.

The scene holds a bright plane (albedo 0.95, clipped at the middle exposure) and a black box (albedo 0.03, too
dark at it): one exposure gives one or the other, the three together both. The virtual rig renders each
exposure with the light (projector and ambient) scaled before noise and clipping; the truth is the rig's.
"""

from __future__ import annotations

import contextlib
import io
import json
from typing import Any

import numpy as np
import pytest

from appliance import cli
from appliance.config import parse_config
from appliance.geometry.calibration_file import write_calibration
from appliance.output.ply import read_ply_vertices
from appliance.patterns.from_config import build_sequence
from appliance.patterns.manifest import read_manifest, write_manifest
from appliance.patterns.sequence import Sequence
from appliance.reconstruct.types import PointCloud
from appliance.scan import virtual_calibration
from appliance.sim.accuracy import compare_to_ground_truth
from appliance.sim.rig import VirtualRig

RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 1280, height: 800, focal_px: 1700, position_mm: [180, 0, 0], look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 640, height: 512, focal_px: 1150, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
  scene:
    - {type: plane, point_mm: [0, 0, 640], normal: [0, 0.1, -1], albedo: 0.95}
    - {type: box, center_mm: [0, 0, 590], size_mm: [120, 90, 40], rotation_deg: [5, 15, 0], albedo: 0.03}
  imaging: {projector_gain_dn: %(gain)s, ambient_dn: %(ambient)s, seed: %(seed)s}
"""
#: relative exposures of the three passes, and the middle pass's light: the plane clips there
EXPOSURES = (0.25, 1.0, 4.0)
GAIN_1X, AMBIENT_1X = 420.0, 6.0


def _rig(scale: float, seed: int) -> VirtualRig:
    cfg = parse_config(RIG % {"gain": GAIN_1X * scale, "ambient": AMBIENT_1X * scale, "seed": seed}, "rig.yaml")
    return VirtualRig(cfg.virtual_rig)


def _decode(*args: Any) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["decode", *[str(a) for a in args]])
    return rc, out.getvalue()


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("hdr")
    cfg = parse_config(RIG % {"gain": GAIN_1X, "ambient": AMBIENT_1X, "seed": 1}, "rig.yaml")
    seq = build_sequence(cfg.sequence, 1280, 800)
    stacks, exposures, frames = [], [], []
    for k, scale in enumerate(EXPOSURES):
        stacks.append(_rig(scale, 10 + k).render(seq, "cam0"))
        exposures += [(10_000.0 * scale, 1.0)] * len(seq)
        frames += list(seq.frames)
        np.save(folder / f"single{k}.npy", stacks[-1])
        write_manifest(folder / f"single{k}.yaml", seq, ["cam0"], stacks={"cam0": f"single{k}.npy"})
    np.save(folder / "hdr.npy", np.concatenate(stacks))
    hdr_seq = Sequence(seq.width, seq.height, tuple(frames))
    write_manifest(folder / "hdr.yaml", hdr_seq, ["cam0"], stacks={"cam0": "hdr.npy"}, exposures=exposures)
    rig = _rig(1.0, 1)
    write_calibration(folder / "cal.yaml", virtual_calibration(rig))
    return {"folder": folder, "rig": rig}


def _accuracy(capture: dict[str, Any], name: str) -> tuple[int, str, Any]:
    folder = capture["folder"]
    rc, text = _decode(folder / f"{name}.yaml", "--calibration", folder / "cal.yaml", "--out",
                       folder / f"{name}.ply", "--report", folder / f"{name}.json")  # fmt: skip
    assert rc == 0, text
    v = read_ply_vertices(folder / f"{name}.ply")
    n = len(v)
    cloud = PointCloud(
        np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32), v["row"].astype(np.int32),
        v["col"].astype(np.int32), np.zeros(n, np.uint8), np.zeros(n, np.uint8), np.zeros(n, np.float32),
    )  # fmt: skip
    return rc, text, compare_to_ground_truth(cloud, capture["rig"], ["cam0"])


def test_manifest_states_exposure_per_frame(capture: dict[str, Any]) -> None:
    man = read_manifest(capture["folder"] / "hdr.yaml")
    assert man.exposures is not None and len(man.exposures) == len(man.sequence)
    assert sorted({e for e, _ in man.exposures}) == [2500.0, 10_000.0, 40_000.0]


def test_three_exposures_reconstruct_what_no_single_one_does(capture: dict[str, Any]) -> None:
    singles = [_accuracy(capture, f"single{k}")[2] for k in range(3)]
    _, text, fused = _accuracy(capture, "hdr")
    for k, rep in enumerate(singles):
        print(f"exposure {EXPOSURES[k]}x: {rep.line()}")
    print(f"fused: {fused.line()}")
    assert "3 exposure passes fused" in text
    best_single = max(r.completeness for r in singles)
    assert fused.completeness >= 0.97
    assert fused.completeness > best_single + 0.05
    assert fused.share_over_1mm <= 1e-3
    assert fused.rms_mm <= 1.3 * min(r.rms_mm for r in singles if r.points > 1000)
    rep = json.loads((capture["folder"] / "hdr.json").read_text())
    assert rep["counts"]["points"] == fused.points


def test_a_frame_without_exposure_in_a_multi_exposure_manifest_is_one_line(capture: dict[str, Any]) -> None:
    folder = capture["folder"]
    text = (folder / "hdr.yaml").read_text().replace(", exposure_us: 2500.0, intensity: 1.0}", "}", 1)
    (folder / "broken.yaml").write_text(text)
    rc, out = _decode(folder / "broken.yaml")
    assert rc != 0 and "Traceback" not in out
    assert "state no exposure_us" in out, out
