"""A full scan over GigE Vision on loopback gives the same cloud as the sim backend.

The virtual rig renders a scan (sim backend); the very same frames are then served by a Python-hosted fake
GigE Vision camera (Aravis.GvFakeCamera) inside a private network namespace, captured through the real Aravis
stack by the ``aravis`` backend in a full :class:`~appliance.scan.Scanner` scan, decoded and triangulated.
Tolerance: identical (the frames travel bit-exact, so the clouds must match exactly).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gi", reason="PyGObject is not installed (scripts/test installs it)")

from gige_scan_helpers import SMALL_RIG, scan, scan_through_fake_gige

pytestmark = pytest.mark.hil


def test_gige_scan_equals_sim_scan(tmp_path: Path) -> None:
    sim = scan(SMALL_RIG)
    frames = sim.frames["cam0"].copy()
    gige = scan_through_fake_gige(SMALL_RIG, frames, tmp_path, "SCAN3D-T1")

    np.testing.assert_array_equal(gige.frames["cam0"], frames)
    a, b = sim.cloud, gige.cloud
    assert len(a) > 10_000 and len(a) == len(b)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.row, b.row)
    np.testing.assert_array_equal(a.quality, b.quality)
