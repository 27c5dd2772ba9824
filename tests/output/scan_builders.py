"""Small scans for the share and spool tests: a 32x24 camera's cloud and a sidecar numbered ``i``."""

from __future__ import annotations

import numpy as np

from appliance.output.sidecar import ScanMetadata
from appliance.reconstruct.types import PointCloud

SHAPES = [(24, 32)]


def cloud(n: int = 50, seed: int = 0) -> PointCloud:
    rng = np.random.default_rng(seed)
    rows, cols = rng.integers(0, 24, n).astype(np.int32), rng.integers(0, 32, n).astype(np.int32)
    return PointCloud(
        rng.uniform(-50, 50, (n, 3)).astype(np.float32) + np.float32([0, 0, 600]),
        rows,
        cols,
        np.zeros(n, np.uint8),
        rng.integers(0, 255, n).astype(np.uint8),
        rng.uniform(0, 50, n).astype(np.float32),
    )


def meta(i: int) -> ScanMetadata:
    return ScanMetadata(
        scan_id=f"20260101-000000-T-{i:06d}",
        time_utc="2026-01-01T00:00:00+00:00",
        sequence={},
        calibration_hash="x",
        counts={"points": 50},
        timings_ms={},
    )
