"""scripts/mode_errors.py (what scripts/run prints after its scans): each reconstruction mode's error against
the virtual rig's ground truth on one scan, on a small two-camera rig fused as the default configuration is."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]

SMALL_TWO_CAMERAS = {
    "projector": {"width": 320, "height": 200, "focal_px": 400, "principal_px": [160, 190],
                  "position_mm": [175, 0, 0], "look_at_mm": [0, 40, 580]},
    "cameras": {"cam0": {"width": 320, "height": 256, "focal_px": 450, "position_mm": [0, 0, 0],
                         "look_at_mm": [0, 0, 580]},
                "cam1": {"width": 320, "height": 256, "focal_px": 450, "position_mm": [-120, 0, 0],
                         "look_at_mm": [0, 0, 580]}},
}  # fmt: skip


def test_every_mode_is_measured_against_ground_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = yaml.safe_load((REPO / "config" / "appliance.yaml").read_text())
    assert list(doc["cameras"]) == ["cam0", "cam1"] and doc["reconstruction"]["mode"] == "both"
    doc["virtual_rig"].update(SMALL_TWO_CAMERAS)
    doc["service"]["state_directory"] = str(tmp_path / "state")
    config = tmp_path / "appliance.yaml"
    config.write_text(yaml.safe_dump(doc, sort_keys=False))
    spec = importlib.util.spec_from_file_location("mode_errors", REPO / "scripts" / "mode_errors.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    assert module.main(config) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    print("\n".join(lines))
    heads = [line.split(":")[0] for line in lines]
    assert heads[:5] == ["mode projector, cam0", "mode projector, cam1", "mode stereo (cam0 + cam1)",
                         "mode both (fused, cam0, cam1)",
                         "calibration health from all three checks (one more scan, both projector axes coded)"]
    # the exact calibration: ok from the three-view, both ray-ray and the epipolar check
    health = lines[5]
    assert health.startswith("calibration health ok: "), health
    kinds = re.findall(r"(three_view|ray_ray|epipolar):(\S+) ok", health)
    assert sorted(k for k, _ in kinds) == ["epipolar", "ray_ray", "ray_ray", "three_view"], health
    lines = lines[:4]
    figures = [re.search(r": (\d+) points: RMS ([0-9.]+) mm", line) for line in lines]
    assert all(f is not None for f in figures), lines
    points = [int(f.group(1)) for f in figures if f]
    rms = [float(f.group(2)) for f in figures if f]
    # the small rig's pixels are 1.3 mm wide at 580 mm (measured: 0.50, 0.29, 0.79 and 0.30 mm)
    assert min(points) > 1000 and max(rms) < 1.0, lines
    assert points[3] > max(points[0], points[2])  # fused: both cameras' points
    assert rms[3] < rms[0] and rms[3] < rms[2]  # fusing beats cam0 with the projector and the camera pair alone
