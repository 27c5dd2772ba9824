"""PLY, sidecar and preview writers; atomic writes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from appliance.errors import OutputError
from appliance.output.atomic import write_bytes_atomic
from appliance.output.ply import read_ply_vertices, write_ply
from appliance.output.preview import render_preview
from appliance.output.scanfiles import make_scan_id, write_scan_files
from appliance.output.sidecar import ScanMetadata
from appliance.reconstruct.types import PointCloud

REPO = Path(__file__).resolve().parents[2]


def _cloud(n: int = 500, cameras: int = 2, normals: bool = False) -> PointCloud:
    rng = np.random.default_rng(3)
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return PointCloud(
        xyz=(rng.normal(size=(n, 3)) * 50 + [0, 0, 600]).astype(np.float32),
        row=rng.integers(0, 1024, n).astype(np.int32),
        col=rng.integers(0, 1280, n).astype(np.int32),
        camera=rng.integers(0, cameras, n).astype(np.uint8),
        intensity=rng.integers(0, 256, n).astype(np.uint8),
        quality=rng.random(n).astype(np.float32) * 100,
        normal=nrm if normals else None,
    )


@pytest.mark.parametrize("normals", [False, True])
def test_ply_read_back_by_independent_reader(tmp_path: Path, normals: bool) -> None:
    cloud = _cloud(normals=normals)
    path = write_ply(tmp_path / "c.ply", cloud, normals=normals, comments=["test"])
    ply = PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    v = ply["vertex"]
    assert v.count == len(cloud)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], axis=1), cloud.xyz)
    np.testing.assert_array_equal(v["row"], cloud.row)
    np.testing.assert_array_equal(v["col"], cloud.col)
    np.testing.assert_array_equal(v["camera"], cloud.camera)
    np.testing.assert_array_equal(v["intensity"], cloud.intensity)
    np.testing.assert_array_equal(v["quality"], cloud.quality)
    assert v["x"].dtype == np.float32 and v["intensity"].dtype == np.uint8
    if normals:
        assert cloud.normal is not None
        np.testing.assert_array_equal(np.stack([v["nx"], v["ny"], v["nz"]], axis=1), cloud.normal)
    # our own reader agrees
    np.testing.assert_array_equal(read_ply_vertices(path)["z"], cloud.xyz[:, 2])


def test_single_camera_has_no_camera_property(tmp_path: Path) -> None:
    path = write_ply(tmp_path / "c.ply", _cloud(cameras=1))
    names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    assert "camera" not in names and names[:3] == ["x", "y", "z"]


def test_empty_cloud(tmp_path: Path) -> None:
    path = write_ply(tmp_path / "e.ply", PointCloud.empty())
    assert PlyData.read(str(path))["vertex"].count == 0


_WRITE_INTO = """
import os, sys
from pathlib import Path
from appliance.errors import OutputError
from appliance.output.atomic import write_bytes_atomic
try:
    write_bytes_atomic(Path(sys.argv[1]) / "x.bin", b"abc")
except OutputError as exc:
    print("refused:", exc)
print("left:", sorted(os.listdir(sys.argv[1])))
"""


def test_atomic_write_leaves_nothing_on_failure(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o500)
    try:
        if not os.access(ro, os.W_OK):
            with pytest.raises(OutputError, match="cannot be written"):
                write_bytes_atomic(ro / "x.bin", b"abc")
            assert list(ro.iterdir()) == []
        else:  # root writes through the mode bits: a read-only tmpfs in a mount namespace of the writer's own
            os.chmod(ro, 0o700)
            cmd = f"mount -t tmpfs -o ro tmpfs '{ro}' && exec '{sys.executable}' -c \"$0\" '{ro}'"
            done = subprocess.run(["unshare", "-m", "sh", "-c", cmd, _WRITE_INTO], capture_output=True, text=True,
                                  timeout=60, cwd=REPO, check=False)  # fmt: skip
            if done.returncode != 0 and "unshare" in done.stderr + done.stdout:
                pytest.skip(f"no private read-only mount here: {done.stderr.strip()[:200]}")
            assert done.returncode == 0, done.stderr
            out = done.stdout.splitlines()
            assert out[0].startswith("refused:") and "cannot be written" in out[0], done.stdout
            assert out[1] == "left: []", done.stdout  # no temporary file left on the read-only filesystem
    finally:
        os.chmod(ro, 0o700)
    with pytest.raises(OutputError, match="cannot be written"):
        write_bytes_atomic(tmp_path / "missing" / "x.bin", b"abc")


def test_scan_files(tmp_path: Path) -> None:
    cloud = _cloud()
    sid = make_scan_id("SN1", 7)
    meta = ScanMetadata(sid, "2026-11-22T00:00:00+00:00", {"frames": 28}, "abc123", {"points": len(cloud)},
                        {"decode_ms": 12.5}, "SN1", cameras=["cam0", "cam1"])
    files = write_scan_files(tmp_path, meta, cloud, [(1024, 1280), (1024, 1280)])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"{sid}{s}" for s in (".json", ".ply", ".png"))
    doc = json.loads(files.sidecar.read_text())
    assert doc["scan_id"] == sid and doc["counts"]["points"] == len(cloud)
    assert doc["files"]["cloud"] == f"{sid}.ply" and doc["software_version"]
    import cv2

    img = cv2.imread(str(files.preview))
    assert img is not None and img.shape[1] > 100


def test_preview_scale_bar_spans_depth_range() -> None:
    d = np.full((100, 120), np.nan, np.float32)
    d[20:80, 20:100] = np.linspace(500, 600, 80, dtype=np.float32)[None, :]
    img = render_preview([d], "t")
    assert img.dtype == np.uint8 and img.shape[0] == 100 and img.shape[1] > 120
    # the depth tile uses many colours (a ramp), empty pixels are dark grey
    tile = img[:, :120]
    assert len(np.unique(tile[30, 20:100].reshape(-1, 3), axis=0)) > 20
    assert tuple(tile[50, 5]) == (40, 40, 40)  # (the top-left corner holds the title)
    # the scale bar's top (labelled with the nearest depth) has the colour of the nearest pixels
    bar_x = 120 + 4 + 8 + 5  # tile, its 4-px gap, the bar's margin, a few px into the bar
    bar_h = int(0.8 * 100)
    y0 = (100 - bar_h) // 2
    top, bottom = img[y0, bar_x].astype(int), img[y0 + bar_h - 1, bar_x].astype(int)
    assert np.abs(top - tile[30, 20].astype(int)).sum() < 40  # nearest depth: top of the bar
    assert np.abs(bottom - tile[30, 99].astype(int)).sum() < 40  # farthest: bottom


def test_scan_ply_packed_in_chunks_reads_back_whole(tmp_path: Path) -> None:
    """The share writer's PLY is packed a chunk at a time: across chunk boundaries (and a short last chunk)
    the file is byte for byte the one-piece packing, its size and SHA-256 are those of its bytes, and an
    independent reader gets every point back."""
    import hashlib

    from appliance.output.ply import RECORDS_PER_CHUNK, cloud_to_records
    from appliance.output.scanfiles import scan_file_contents

    n = 2 * RECORDS_PER_CHUNK + 17
    cloud = _cloud(n=n)
    meta = ScanMetadata("s", "2026-11-22T00:00:00+00:00", {}, "abc", {"points": n}, {}, "SN1")
    ply = scan_file_contents(meta, cloud, [(1024, 1280)] * 2, preview=False)[0]
    chunks = [bytes(c) for c in ply.chunks()]
    assert len(chunks) == 1 + 3  # the header, then three record chunks
    data = b"".join(chunks)
    assert ply.size == len(data) and ply.sha256() == hashlib.sha256(data).hexdigest()
    records = cloud_to_records(cloud, camera_field=True, normals=False)
    assert data.endswith(records.tobytes())
    with (tmp_path / "c.ply").open("wb") as f:
        ply.write_to(f)
    v = PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    assert v.count == n
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], axis=1), cloud.xyz)
    np.testing.assert_array_equal(v["camera"], cloud.camera)
    np.testing.assert_array_equal(v["quality"], cloud.quality)
