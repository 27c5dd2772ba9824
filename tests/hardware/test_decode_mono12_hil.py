"""A Mono12 scan over GigE Vision decodes the same pixels as the Mono8 one.

The virtual rig renders an 8-bit scan (sim backend). The same frames, shifted to 12 bits (values << 4), are
served as ``Mono12`` by a Python-hosted fake GigE Vision camera (Aravis.GvFakeCamera) inside a private
network namespace and captured through the real Aravis stack in a full :class:`~appliance.scan.Scanner` scan.
The scan must take the camera's 12 significant bits from its pixel format: thresholds in 12-bit DN, intensity
scaled from 12 bits to 8. Tolerances: decoded share within 0.5 percentage points, >= 99.5 % equal codes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gi", reason="PyGObject is not installed (scripts/test installs it)")

from gige_scan_helpers import SMALL_RIG, scan, scan_through_fake_gige

pytestmark = pytest.mark.hil

RIG = "sequence: {kind: gray_phase, axes: x, periods_px: [16]}\n" + SMALL_RIG


def test_mono12_gige_scan_decodes_like_the_mono8_scan(tmp_path: Path) -> None:
    sim = scan(RIG)
    frames8 = sim.frames["cam0"].copy()
    assert frames8.dtype == np.uint8
    frames12 = frames8.astype(np.uint16) << 4
    gige = scan_through_fake_gige(RIG, frames12, tmp_path, "SCAN3D-M12", "pixel_format: Mono12, ")

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
