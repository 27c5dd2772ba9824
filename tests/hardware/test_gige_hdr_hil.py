"""An HDR scan through the real Aravis stack: the scanner sets ``ExposureTime`` before each pass.

A fake GigE Vision camera (inside a private network namespace, opened by its 127.0.0.x address) serves the
virtual rig's one-pass rendering at 10 ms and scales each frame by ``ExposureTime / 10 ms`` (clipped at full
scale), as a sensor's signal scales with its exposure. A scan with ``sequence.exposures_us: [5000, 10000,
20000]`` must start one acquisition per pass at that pass's exposure, capture each pass's frames scaled so,
and fuse them into a cloud; an exposure outside the camera's range fails the scan in one line.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gi", reason="PyGObject is not installed (scripts/test installs it)")

from gige_scan_helpers import SMALL_RIG, scan

from appliance.config import parse_config
from appliance.errors import ScanError
from appliance.geometry.calibration_file import write_calibration
from appliance.hardware.registry import build_rig
from appliance.scan import ScanResult, scan_once, virtual_calibration

pytestmark = pytest.mark.hil

REFERENCE_US = 10_000.0
EXPOSURES_US = (5000, 10_000, 20_000)


def _hdr_scan_through_fake_gige(frames: np.ndarray, tmp_path: Path, exposures: tuple[int, ...]) -> tuple[
    ScanResult | ScanError, list[int]
]:  # fmt: skip
    """Scan SMALL_RIG with ``exposures`` through a fake camera serving ``frames`` at :data:`REFERENCE_US`;
    the result (or the scan's error) and the exposure each acquisition of the fake started with."""
    from appliance.fakes import gige as fake_gige

    calib = tmp_path / "calibration.yaml"
    write_calibration(calib, virtual_calibration(build_rig(parse_config(SMALL_RIG)).virtual))
    with fake_gige.LoopbackLab(n_addresses=1) as lab:
        address = lab.addresses[0]
        handle = lab.call(fake_gige.start_fake_camera, address, "SCAN3D-HDR", frames,
                          exposure_reference_us=REFERENCE_US)  # fmt: skip
        try:
            cfg = parse_config(SMALL_RIG + f"""
sequence: {{exposures_us: {list(exposures)}}}
cameras:
  cam0: {{type: aravis, address: "{address}", trigger: Software, software_trigger: external,
          frame_timeout_ms: 3000}}
calibration_file: {calib}
""", "hdr.yaml")  # fmt: skip

            def run() -> ScanResult | ScanError:
                try:
                    return asyncio.run(scan_once(cfg))[0]
                except ScanError as exc:
                    return exc

            result = lab.call(run)
            seen = lab.call(handle.acquisition_exposures)
        finally:
            lab.call(handle.stop)
    return result, seen


def test_exposure_time_is_set_before_each_pass(tmp_path: Path) -> None:
    one_pass = scan(SMALL_RIG).frames["cam0"].copy()  # the sim's frames at the default 10 ms
    result, seen = _hdr_scan_through_fake_gige(one_pass, tmp_path, EXPOSURES_US)
    assert isinstance(result, ScanResult), result
    assert seen == list(EXPOSURES_US)  # one acquisition per pass, each at its exposure
    got = result.frames["cam0"]
    n = len(one_pass)
    assert got.shape[0] == n * len(EXPOSURES_US)
    for k, e in enumerate(EXPOSURES_US):
        want = np.minimum(np.rint(one_pass * (e / REFERENCE_US)), 255).astype(np.uint8)
        np.testing.assert_array_equal(got[k * n:(k + 1) * n], want, err_msg=f"pass {k} ({e} µs)")
    hdr = result.capture
    assert hdr["exposures_us"] == [float(e) for e in EXPOSURES_US] and hdr["frames"] == 3 * n
    assert len(result.cloud) > 10_000


def test_an_exposure_the_camera_refuses_fails_the_scan_in_one_line(tmp_path: Path) -> None:
    one_pass = np.zeros((22, 256, 320), np.uint8)
    result, seen = _hdr_scan_through_fake_gige(one_pass, tmp_path, (10_000, 5))  # the fake's minimum: 10 µs
    assert isinstance(result, ScanError)
    msg = str(result)
    assert "\n" not in msg and "camera 'cam0' (aravis" in msg, msg
    assert "exposure 5 µs is outside the camera's ExposureTime range 10..1e+07 µs" in msg, msg
    assert "sequence.exposures_us" in msg, msg
    assert seen == [10_000]  # the first pass ran; the second was never started
