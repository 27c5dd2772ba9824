"""A full scan over GigE Vision on loopback gives the same cloud as the sim backend.

The virtual rig renders a scan (sim backend); the very same frames are then served by a Python-hosted fake
GigE Vision camera (Aravis.GvFakeCamera) inside a private network namespace, captured through the real Aravis
stack by the ``aravis`` backend in a full :class:`~appliance.scan.Scanner` scan, decoded and triangulated.
Tolerance: identical (the frames travel bit-exact, so the clouds must match exactly).
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


def test_gige_scan_equals_sim_scan(tmp_path: Path) -> None:
    from appliance.fakes import gige as fake_gige

    sim = _scan(RIG)
    frames = sim.frames["cam0"].copy()
    calib = tmp_path / "calibration.yaml"
    rig = build_rig(parse_config(RIG))
    write_calibration(calib, virtual_calibration(rig.virtual))

    with fake_gige.LoopbackLab(n_addresses=1) as lab:
        address = lab.addresses[0]
        handle = lab.call(fake_gige.start_fake_camera, address, "SCAN3D-T1", frames)
        try:
            gige_cfg = RIG + f"""
cameras:
  cam0: {{type: aravis, address: "{address}", trigger: Software, software_trigger: external,
          frame_timeout_ms: 3000}}
calibration_file: {calib}
"""
            gige = lab.call(_scan, gige_cfg)
        finally:
            lab.call(handle.stop)

    np.testing.assert_array_equal(gige.frames["cam0"], frames)
    a, b = sim.cloud, gige.cloud
    assert len(a) > 10_000 and len(a) == len(b)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.row, b.row)
    np.testing.assert_array_equal(a.quality, b.quality)
