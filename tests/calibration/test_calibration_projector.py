"""The local corner fit of projector calibration, on the real procam captures and on an exact homography.

The calibrate commands on the same captures are tested in test_calibrate_command.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from procam_helpers import PROCAM, procam_manifests

from appliance.calibration.boards import BoardSpec, Detection
from appliance.calibration.projector import (
    ProcamView,
    corner_projector_coords,
    procam_view,
    projector_detection,
)
from appliance.patterns import (
    read_manifest,
)

SPEC = BoardSpec(type="chessboard", cols=9, rows=7, square_mm=75)


@pytest.fixture(scope="module")
def procam_views(tmp_path_factory: pytest.TempPathFactory) -> list[ProcamView]:
    if not PROCAM.is_dir():
        pytest.skip(f"test data {PROCAM} is absent")
    views = []
    for path in procam_manifests(tmp_path_factory.mktemp("procam"))[:1]:  # the command test decodes all 5
        man = read_manifest(path)
        views.append(procam_view(man.load_stack("cam0"), man.sequence, SPEC))
    return views


def test_procam_corner_projector_coordinates(procam_views: list[ProcamView]) -> None:
    for v in procam_views:
        assert v.camera is not None and v.projector is not None and v.fit is not None
        assert len(v.projector) >= 40
        # Gray-only decoding is quantised to whole projector pixels; the local fit averages it out
        assert np.nanmedian(v.fit.residual_rms) < 0.6
        assert np.all((v.projector.image_points >= 0) & (v.projector.image_points < [1024, 768]))


def test_corner_fit_recovers_a_homography_with_outliers() -> None:
    rng = np.random.default_rng(0)
    H = np.array([[0.8, 0.05, 100.0], [-0.03, 0.75, 60.0], [2e-5, -1e-5, 1.0]])
    ys, xs = np.mgrid[0:300, 0:400].astype(np.float64)
    den = H[2, 0] * xs + H[2, 1] * ys + 1
    u = ((H[0, 0] * xs + H[0, 1] * ys + H[0, 2]) / den).astype(np.float32)
    v = ((H[1, 0] * xs + H[1, 1] * ys + H[1, 2]) / den).astype(np.float32)
    u_q, v_q = np.round(u), np.round(v)  # Gray-only quantisation
    bad = rng.random(u.shape) < 0.15  # wrong Gray bits: far-off codes
    u_q[bad] += rng.choice([-256.0, 128.0, 64.0], bad.sum())
    u_q[rng.random(u.shape) < 0.1] = np.nan
    corners = np.array([[100.3, 80.7], [250.5, 150.2], [330.1, 240.9], [-4.0, 50.0]])
    fit = corner_projector_coords(u_q, v_q, corners, radius_px=20)
    c = corners[:3]
    d = H[2, 0] * c[:, 0] + H[2, 1] * c[:, 1] + 1
    truth = np.stack([(H[0, 0] * c[:, 0] + H[0, 1] * c[:, 1] + H[0, 2]) / d,
                      (H[1, 0] * c[:, 0] + H[1, 1] * c[:, 1] + H[1, 2]) / d], axis=1)  # fmt: skip
    np.testing.assert_allclose(fit.points[:3], truth, atol=0.05)
    assert not fit.valid[3]  # beyond the image edge: only the right half of the window exists
    det = Detection(np.arange(4, dtype=np.int32), corners, np.zeros((4, 3)), (400, 300))
    pdet = projector_detection(det, fit, (1024, 768))
    assert pdet is None  # 3 valid corners are not a view
