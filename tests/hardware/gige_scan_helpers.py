"""A small virtual rig scanned by the sim backend, and the same frames scanned through a fake GigE camera.

Shared by the GigE Vision scan tests; the fake camera runs inside a private network namespace
(:class:`appliance.fakes.gige.LoopbackLab`) and is opened by its 127.0.0.x address only.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import numpy.typing as npt

from appliance.config import parse_config
from appliance.geometry.calibration_file import write_calibration
from appliance.hardware.registry import build_rig
from appliance.scan import ScanResult, scan_once, virtual_calibration

SMALL_RIG = """
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 200], position_mm: [190, 0, 0],
              look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 520, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
reconstruction: {min_depth_mm: 300, max_depth_mm: 900}
"""


def scan(cfg_text: str) -> ScanResult:
    """One scan of the configuration given as YAML text."""
    return asyncio.run(scan_once(parse_config(cfg_text, "test.yaml")))[0]


def scan_through_fake_gige(
    rig: str, frames: npt.NDArray[np.generic], tmp_path: Path, serial: str, camera_keys: str = ""
) -> ScanResult:
    """Scan ``rig`` with cam0 an Aravis camera on a fake GigE camera serving ``frames`` (F, H, W).

    ``camera_keys`` adds to cam0's settings (e.g. ``"pixel_format: Mono12, "``); the rig's exact calibration is
    written to ``tmp_path`` and used.
    """
    from appliance.fakes import gige as fake_gige

    calib = tmp_path / "calibration.yaml"
    write_calibration(calib, virtual_calibration(build_rig(parse_config(rig)).virtual))
    with fake_gige.LoopbackLab(n_addresses=1) as lab:
        address = lab.addresses[0]
        handle = lab.call(fake_gige.start_fake_camera, address, serial, frames)
        try:
            cfg = rig + f"""
cameras:
  cam0: {{type: aravis, address: "{address}", {camera_keys}trigger: Software, software_trigger: external,
          frame_timeout_ms: 3000}}
calibration_file: {calib}
"""
            result: ScanResult = lab.call(scan, cfg)
        finally:
            lab.call(handle.stop)
    return result
