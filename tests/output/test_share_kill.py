"""SIGKILL in the middle of a write to the share: a real writer process on a real folder, killed while a
temporary file is on the share, then the start-up cleanup of the next writer.

The old cleanup only looked at the spool, so ``.tmp-<scan-id>.ply.<pid>`` stayed on the share for good.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from plyfile import PlyData

from appliance.config.schema import OutputConfig
from appliance.output.atomic import TMP_PREFIX
from appliance.output.share import ShareWriter

DAY = "2026-01-01"
N_POINTS = 2_000_000  # a ~44 MB PLY: its write and fsync take long enough to be caught in the middle

CHILD = r"""
import sys
from pathlib import Path

import numpy as np

from appliance.config.schema import OutputConfig
from appliance.output.share import ShareWriter
from appliance.output.sidecar import ScanMetadata
from appliance.reconstruct.types import PointCloud

share, spool, mode, n = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
rng = np.random.default_rng(0)
cloud = PointCloud(
    rng.uniform(-100, 100, (n, 3)).astype(np.float32), rng.integers(0, 1000, n).astype(np.int32),
    rng.integers(0, 2000, n).astype(np.int32), np.zeros(n, np.uint8), rng.integers(0, 255, n).astype(np.uint8),
    rng.uniform(0, 50, n).astype(np.float32))
w = ShareWriter(OutputConfig(directory=share, spool_directory=spool, min_free_mb=0))


def meta(i):
    return ScanMetadata(scan_id=f"20260101-000000-K-{i:06d}", time_utc="2026-01-01T00:00:00+00:00",
                        sequence={}, calibration_hash="x", counts={"points": n}, timings_ms={})


if mode == "move":  # spool three scans while the share is away, bring it back, move them over
    away = share.with_name("share-away")
    share.rename(away)
    for i in (1, 2, 3):
        assert w.write_scan("2026-01-01", meta(i), cloud, [(1000, 2000)], preview=False).location == "spool"
    away.rename(share)
    print("ready", flush=True)
    w.flush_spool()
else:
    print("ready", flush=True)
    for i in range(1, 100):
        w.write_scan("2026-01-01", meta(i), cloud, [(1000, 2000)], preview=False)
print("done", flush=True)
"""


def temp_files(folder: Path) -> list[str]:
    try:
        return [n for n in os.listdir(folder) if n.startswith(TMP_PREFIX)]
    except FileNotFoundError:
        return []


def kill_mid_write(tmp: Path, mode: str) -> tuple[Path, Path, list[str]]:
    """Start the writer, SIGKILL it while a temporary file is on the share; retried when the kill lands
    just after a rename. Returns (share, spool, the temporary files the kill left)."""
    for attempt in range(5):
        share, spool = tmp / f"share{attempt}", tmp / f"spool{attempt}"
        (share / DAY).mkdir(parents=True)
        proc = subprocess.Popen([sys.executable, "-c", CHILD, str(share), str(spool), mode, str(N_POINTS)],
                                stdout=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == "ready"
            while proc.poll() is None and time.monotonic() < deadline:
                if temp_files(share / DAY):
                    os.kill(proc.pid, signal.SIGKILL)
                    break
                time.sleep(0.001)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait(30)
        left = temp_files(share / DAY)
        if proc.returncode == -signal.SIGKILL and left:
            return share, spool, left
    pytest.fail("could not kill the writer while a temporary file was on the share in 5 attempts")


def complete_scans(folder: Path) -> list[str]:
    """The scans whose sidecar is visible, each checked complete (PLY read back with plyfile)."""
    done = []
    for side in sorted(folder.glob("*.json")):
        sid = side.stem
        assert json.loads(side.read_text())["scan_id"] == sid
        assert PlyData.read(str(folder / f"{sid}.ply"))["vertex"].count == N_POINTS
        done.append(sid)
    return done


@pytest.mark.parametrize("mode", ["write", "move"])
def test_sigkill_mid_write_leaves_nothing_after_the_start_up_cleanup(tmp_path: Path, mode: str) -> None:
    share, spool, left = kill_mid_write(tmp_path, mode)
    assert all(n.startswith(f"{TMP_PREFIX}20260101-000000-K-") for n in left)
    w = ShareWriter(OutputConfig(directory=share, spool_directory=spool, min_free_mb=0))
    assert w.cleanup_incomplete() >= len(left)
    folder = share / DAY
    assert temp_files(folder) == []
    names = os.listdir(folder)
    for n in names:  # no cloud or preview without its completion marker
        stem, ext = os.path.splitext(n)
        assert ext == ".json" or f"{stem}.json" in names, f"{n} left without {stem}.json"
    before = complete_scans(folder)
    if mode == "move":  # the next flush delivers the rest, each scan exactly once
        w.flush_spool()
        assert w.spool_entries() == []
        assert complete_scans(folder) == [f"20260101-000000-K-{i:06d}" for i in (1, 2, 3)]
        assert set(before) <= set(complete_scans(folder))
    assert temp_files(folder) == [] and not (spool / ".share-inflight.json").exists()
