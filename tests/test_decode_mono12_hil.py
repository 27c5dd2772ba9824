"""A Mono12 scan over GigE Vision decodes the same pixels as the Mono8 one.

The virtual rig renders an 8-bit scan (sim backend). The same frames, shifted to 12 bits (values << 4), are
served as ``Mono12`` by a Python-hosted fake GigE Vision camera (Aravis.GvFakeCamera) inside a private
network namespace and captured through the real Aravis stack in a full :class:`~appliance.scan.Scanner` scan.
The scan must take the camera's 12 significant bits from its pixel format: thresholds in 12-bit DN, intensity
scaled from 12 bits to 8. Tolerances: decoded share within 0.5 percentage points, >= 99.5 % equal codes.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gi", reason="PyGObject is not installed (scripts/test installs it)")

from appliance.config import parse_config
from appliance.geometry.calibration_file import write_calibration
from appliance.hardware.registry import build_rig
from appliance.scan import ScanResult, scan_once, virtual_calibration

pytestmark = pytest.mark.hil

RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 200], position_mm: [190, 0, 0],
              look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 520, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
reconstruction: {min_depth_mm: 300, max_depth_mm: 900}
"""


def _scan(cfg_text: str) -> ScanResult:
    cfg = parse_config(cfg_text, "test.yaml")

    return asyncio.run(scan_once(cfg))[0]


def test_mono12_gige_scan_decodes_like_the_mono8_scan(tmp_path: Path) -> None:
    from appliance.fakes import gige as fake_gige

    sim = _scan(RIG)
    frames8 = sim.frames["cam0"].copy()
    assert frames8.dtype == np.uint8
    frames12 = frames8.astype(np.uint16) << 4
    calib = tmp_path / "calibration.yaml"
    write_calibration(calib, virtual_calibration(build_rig(parse_config(RIG)).virtual))

    with fake_gige.LoopbackLab(n_addresses=1) as lab:
        address = lab.addresses[0]
        handle = lab.call(fake_gige.start_fake_camera, address, "SCAN3D-M12", frames12)
        try:
            gige_cfg = RIG + f"""
cameras:
  cam0: {{type: aravis, address: "{address}", pixel_format: Mono12, trigger: Software,
          software_trigger: external, frame_timeout_ms: 3000}}
calibration_file: {calib}
"""
            gige = lab.call(_scan, gige_cfg)
        finally:
            lab.call(handle.stop)

    got = gige.frames["cam0"]
    assert got.dtype == np.uint16 and int(got.max()) <= 4095
    np.testing.assert_array_equal(got, frames12)
    a, b = sim.maps["cam0"], gige.maps["cam0"]
    print(f"decoded Mono8 {a.mask.mean():.2%}, Mono12 {b.mask.mean():.2%}; points {len(sim.cloud)} / "
          f"{len(gige.cloud)}")  # fmt: skip
    assert a.mask.mean() > 0.3
    assert abs(a.mask.mean() - b.mask.mean()) <= 0.005
    both = a.mask & b.mask
    assert np.mean(np.abs(a.u[both] - b.u[both]) < 1e-3) >= 0.995
    assert abs(len(sim.cloud) - len(gige.cloud)) <= 0.01 * len(sim.cloud)
    # intensity: 12-bit white scaled to 8 bits equals the 8-bit white (x16 >> 4), not a 16-bit scale (0..15)
    assert abs(float(np.median(gige.cloud.intensity)) - float(np.median(sim.cloud.intensity))) <= 1.0
