"""The fused reconstruction path (depth map + neighbour filter in one pass, then the kept points) against the
organised path (triangulate, filter_isolated, to_point_cloud) and ground truth; pooled result buffers."""

from __future__ import annotations

import gc
import tracemalloc

import numpy as np
import pytest
from procam_geometry import (
    EXACT_TOL_MM,
    PLANE,
    cast,
    codes,
    procam_rig,
    triangulator,
    true_points,
    two_camera_calibration,
)

from appliance.config.schema import ReconstructionConfig
from appliance.patterns import BlackFrame, Sequence, WhiteFrame, gray_code_frames, phase_shift_frames
from appliance.reconstruct.decode import StreamingDecoder, decode
from appliance.reconstruct.filters import filter_isolated, to_point_cloud
from appliance.reconstruct.pipeline import Reconstructor
from appliance.reconstruct.types import DecodedMaps, PointCloud

#: float32 rounding of world points (mm) at ~600 mm (rays interpolated between table rows are exact to ~3e-8).
SAME_POINT_MM = 5e-4


@pytest.mark.parametrize("surface", ["plane", "sphere"])
@pytest.mark.parametrize(("kind", "axes"), [("h", "x"), ("h", "xy"), ("v", "y"), ("posed", "x"), ("posed", "xy")])
def test_depth_map_is_the_organised_cloud(kind: str, axes: str, surface: str) -> None:
    cam, proj, rays = procam_rig(kind)
    truth = true_points(kind, surface)
    maps = codes(proj, truth, axes)
    tri = triangulator(kind, axes)
    organised = tri.triangulate(maps, None, 400.0, 800.0)
    depth, counts = tri.triangulate_depth(maps, None, 400.0, 800.0)
    assert rays.row_table()[2] < 1e-7  # the coarse ray table interpolates to ~float32 precision
    np.testing.assert_array_equal(np.isfinite(depth), np.isfinite(organised[..., 2]))
    assert counts[0] == 0 and counts.sum() == np.isfinite(depth).sum() > 20000
    np.testing.assert_array_equal(counts[1:], np.isfinite(depth).sum(axis=1))
    from_depth = tri.organised_from_depth(depth)
    assert np.nanmax(np.abs(from_depth - organised)) < SAME_POINT_MM
    assert np.nanmax(np.linalg.norm(from_depth - truth, axis=2)) < EXACT_TOL_MM
    # depth is the camera-frame z of the world point
    z_cam = (truth @ cam.R[2] + cam.T[2])[np.isfinite(depth)]
    assert np.max(np.abs(depth[np.isfinite(depth)] - z_cam)) < EXACT_TOL_MM


@pytest.mark.parametrize("min_neighbours", [3, 8])
def test_fused_filter_equals_filter_isolated(min_neighbours: int) -> None:
    _, proj, _ = procam_rig("posed")
    truth = true_points("posed", "sphere")
    maps = codes(proj, truth, "x")
    rng = np.random.default_rng(3)
    rows, cols = np.nonzero(maps.mask)
    pick = rng.choice(rows.size, 300, replace=False)
    maps.u[rows[pick], cols[pick]] += np.float32(40.0)  # code outliers: depth spikes inside the surface
    tri = triangulator("posed", "x")
    xyz = tri.triangulate(maps, None, 100.0, 2000.0)
    removed = filter_isolated(xyz, min_neighbours, 2.0)
    depth, counts = tri.triangulate_depth(maps, None, 100.0, 2000.0, min_neighbours, 2.0)
    assert removed > 300
    kept_ref, kept = np.isfinite(xyz[..., 2]), np.isfinite(depth)
    # equal up to points whose neighbour distance is within float rounding of the threshold
    assert np.sum(kept_ref != kept) <= 1e-4 * kept_ref.sum()
    assert not kept[rows[pick], cols[pick]].any()
    assert counts.sum() == kept.sum()


def test_write_points_matches_to_point_cloud() -> None:
    _, proj, _ = procam_rig("posed")
    truth = true_points("posed", "plane")
    maps = codes(proj, truth, "x")
    maps.quality[...] = np.random.default_rng(0).uniform(10, 90, maps.quality.shape).astype(np.float32)
    inten = (np.arange(maps.u.size) % 253).astype(np.uint8).reshape(maps.u.shape)
    tri = triangulator("posed", "x")
    xyz = tri.triangulate(maps)
    filter_isolated(xyz, 8, 2.0)
    ref = to_point_cloud(xyz, maps.quality, inten, 1)
    depth, counts = tri.triangulate_depth(maps, None, 1e-6, np.inf, 8, 2.0)
    n, start = int(counts.sum()), 5
    cloud = PointCloud(
        np.full((n + 9, 3), -1, np.float32), np.full(n + 9, -1, np.int32), np.full(n + 9, -1, np.int32),
        np.zeros(n + 9, np.uint8), np.zeros(n + 9, np.uint8), np.full(n + 9, -1, np.float32),
    )  # fmt: skip
    assert tri.write_points(depth, counts, maps.quality, inten, cloud, start) == n == len(ref)
    part = cloud.select(np.arange(n + 9) - start < n)
    part = part.select(np.arange(len(part)) >= start)
    np.testing.assert_array_equal(part.row, ref.row)
    np.testing.assert_array_equal(part.col, ref.col)
    np.testing.assert_array_equal(part.quality, ref.quality)
    np.testing.assert_array_equal(part.intensity, ref.intensity)
    assert np.max(np.abs(part.xyz - ref.xyz)) < SAME_POINT_MM
    assert np.all(cloud.row[:start] == -1) and np.all(cloud.row[start + n :] == -1)  # nothing else written
    with pytest.raises(ValueError, match="cannot write"):
        tri.write_points(depth, counts, maps.quality, inten, cloud, 10)


def test_reconstructor_fused_path_and_pooled_clouds() -> None:
    calib = two_camera_calibration()
    proj = calib.projector
    assert proj is not None
    truth = {n: cast(calib.devices[n], PLANE) for n in calib.camera_names}
    maps = {n: codes(proj, truth[n], "x") for n in calib.camera_names}
    white = {n: np.full((1024, 1280), 77, np.uint8) for n in calib.camera_names}
    rec = Reconstructor(calib, "x", ReconstructionConfig(min_depth_mm=400, max_depth_mm=800))
    out = rec.run(maps, white)
    cloud, timings = out.cloud, out.timings_ms
    del out  # the record holds nothing the reconstructor reuses; the cloud is kept below
    assert timings["triangulate_ms"] > 0 and timings["filter_ms"] == 0.0
    assert sorted(set(cloud.camera.tolist())) == [0, 1]
    for i, name in enumerate(calib.camera_names):
        sel = cloud.camera == i
        t = truth[name][cloud.row[sel], cloud.col[sel]]
        assert np.max(np.linalg.norm(cloud.xyz[sel] - t, axis=1)) < EXACT_TOL_MM
        assert sel.sum() > 0.9 * maps[name].mask.sum()
        org = rec.organised(name)
        np.testing.assert_array_equal(org[cloud.row[sel], cloud.col[sel]], cloud.xyz[sel])
        assert np.isfinite(org[..., 2]).sum() == sel.sum()
    assert np.all(cloud.intensity == 77)
    # a cloud the caller keeps is never reused; a dropped one is
    kept = {f: getattr(cloud, f).copy() for f in ("xyz", "row", "col", "camera", "intensity", "quality")}
    other = rec.run(maps, None).cloud
    assert np.all(other.intensity == 0)
    for f, before in kept.items():
        np.testing.assert_array_equal(getattr(cloud, f), before)
    # a dropped cloud's memory serves the next runs: they allocate no new result memory (tracemalloc sees
    # numpy's allocations; without the pool each run allocates ~3 clouds' worth), and nothing an earlier run
    # left in it shows (intensity 0 without a white image, 77 with it)
    del other
    gc.collect()
    tracemalloc.start()
    try:
        for k in range(3):
            again = rec.run(maps, None if k % 2 else white).cloud
            assert np.all(again.intensity == (0 if k % 2 else 77))
            del again
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < cloud.xyz.nbytes / 4, f"{peak / 1e6:.1f} MB allocated by runs after dropped clouds"
    again = rec.run(maps, white).cloud
    assert len(again) == len(cloud)
    np.testing.assert_array_equal(again.row, cloud.row)
    np.testing.assert_array_equal(again.intensity, cloud.intensity)


def test_uncoded_axis_map_is_a_shared_read_only_nan_map() -> None:
    seq = Sequence(64, 8, (WhiteFrame(), BlackFrame(), *gray_code_frames(64, "x", stripe=4, inverses=True),
                           *phase_shift_frames("x", 8, 4)))  # fmt: skip
    frames = np.stack([np.full((30, 40), 200 if i == 0 else 10, np.uint8) for i in range(len(seq))])
    maps = decode(frames, seq)
    assert not maps.v.flags.writeable and np.all(np.isnan(maps.v)) and maps.v.shape == (30, 40)
    with pytest.raises(ValueError):
        maps.v[0, 0] = 1.0
    stream = StreamingDecoder(seq, (30, 40))
    for i, f in enumerate(frames):
        stream.push(i, f)
    done = stream.finish()
    assert done.v is maps.v
    out = DecodedMaps(*(np.full((30, 40), 3, dt) for dt in (np.float32, np.float32, np.bool_, np.float32)))
    decode(frames, seq, out=out)
    assert np.all(np.isnan(out.v))  # a caller's buffer is still filled
