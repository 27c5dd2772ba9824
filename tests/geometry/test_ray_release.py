"""RayTable.release: the per-pixel table goes, the row tables stay, and it comes back the same on use."""

from __future__ import annotations

import numpy as np

from appliance.geometry.camera import CameraModel
from appliance.geometry.rays import RayTable


def test_released_table_comes_back_identical() -> None:
    k = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
    cam = CameraModel("cam0", k, np.array([-0.1, 0.05, 0.001, -0.002, 0.0]), 160, 120)
    rays = RayTable(cam)
    before = rays.normalized.copy()
    tx, _ty, err = rays.row_table()
    rays.release()
    assert rays._normalized is None  # the memory is given back
    assert rays.row_table()[0] is tx and err < 1e-6  # the row tables are kept
    np.testing.assert_array_equal(rays.normalized, before)
