"""Camera-projector triangulation, filters and the reconstruction pipeline against ground truth.

The scene is rendered geometrically: every camera pixel's true 3-D point is ray-cast (float64) onto a known
plane or sphere and projected into the (distorted) projector to give exact decoded codes.
"""

from __future__ import annotations

import numpy as np
import pytest
from procam_geometry import (
    EXACT_TOL_MM,
    F64,
    PLANE,
    cast,
    codes,
    procam_rig,
    triangulator,
    true_points,
    two_camera_calibration,
)

from appliance.config.schema import ReconstructionConfig
from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import Calibration
from appliance.geometry.camera import CameraModel
from appliance.reconstruct.filters import (
    estimate_normals,
    filter_isolated,
    to_point_cloud,
)
from appliance.reconstruct.pipeline import Reconstructor
from appliance.reconstruct.triangulate import EPIPOLAR_FLOOR_PX, EPIPOLAR_SIGMAS, ProjectorTriangulator
from appliance.reconstruct.types import DecodedMaps, Reason
from appliance.reconstruct.uncertainty import CodeNoise


@pytest.mark.parametrize("surface", ["plane", "sphere"])
@pytest.mark.parametrize(
    ("kind", "axes"), [("h", "x"), ("h", "xy"), ("v", "y"), ("posed", "x"), ("posed", "xy")]
)
def test_exact_codes_recover_the_surface(kind: str, axes: str, surface: str) -> None:
    cam, proj, _ = procam_rig(kind)
    truth = true_points(kind, surface)
    maps = codes(proj, truth, axes)
    tri = triangulator(kind, axes)
    out = np.full((cam.height, cam.width, 3), 7.0, np.float32)
    xyz = tri.triangulate(maps, out)
    assert xyz is out
    err = np.linalg.norm(xyz - truth, axis=2)
    coded = maps.mask
    assert coded.sum() > 20000
    assert np.all(np.isnan(xyz[~coded]))
    assert np.isfinite(err[coded]).mean() > 0.999  # every coded pixel triangulates
    assert np.nanmax(err) < EXACT_TOL_MM, f"{axes} {surface}: max error {np.nanmax(err):.2e} mm"
    assert tri.table_error < 1e-7


def test_projector_distortion_matters() -> None:
    """The same codes with the projector's distortion ignored are off by far more than the tolerance."""
    cam, proj, rays = procam_rig("h")
    truth = true_points("h", "plane")
    maps = codes(proj, truth, "x")
    naive = CameraModel("projector", proj.K, np.zeros(5), proj.width, proj.height, proj.R, proj.T)
    err = np.linalg.norm(ProjectorTriangulator(cam, naive, "x", rays).triangulate(maps) - truth, axis=2)
    assert np.nanmax(err) > 100 * EXACT_TOL_MM


@pytest.mark.parametrize("axes", ["x", "xy"])
def test_code_noise_propagates_as_the_geometry_predicts(axes: str) -> None:
    _cam, proj, _ = procam_rig("h")
    truth = true_points("h", "plane")
    maps = codes(proj, truth, axes)
    tri = triangulator("h", axes)
    base = tri.triangulate(maps).astype(np.float64)
    delta = 0.01
    shifted = DecodedMaps(maps.u + np.float32(delta), maps.v, maps.mask, maps.quality)
    jac = (tri.triangulate(shifted).astype(np.float64) - base) / delta  # d xyz / d u (mm/px)
    rng = np.random.default_rng(7)
    noise = rng.normal(0.0, 0.05, maps.u.shape).astype(np.float32)
    noisy = DecodedMaps(maps.u + noise, maps.v, maps.mask, maps.quality)
    err = tri.triangulate(noisy).astype(np.float64) - truth
    ok = np.isfinite(err[..., 2]) & np.isfinite(jac[..., 2])
    predicted = jac[ok] * noise[ok, None]
    # linear error propagation holds per point
    assert np.max(np.abs(err[ok] - predicted)) < 2e-3
    rms = np.sqrt(np.mean(np.sum(err[ok] ** 2, axis=1)))
    expected = 0.05 * np.sqrt(np.mean(np.sum(jac[ok] ** 2, axis=1)))
    assert abs(rms / expected - 1) < 0.05
    # and the sensitivity is the textbook one: dz/du ~ z^2 / (f_proj * baseline), in the frame of the ray
    z = truth[ok, 2]
    dz = np.abs(jac[ok, 2])
    # (xy too: with a horizontal baseline v hardly depends on depth, so u carries the depth alone)
    assert np.median(dz / (z**2 / (1600 * 175))) == pytest.approx(1.0, rel=0.25)


def test_rows_with_horizontal_baseline_is_refused() -> None:
    cam, proj, rays = procam_rig("h")
    with pytest.raises(CalibrationError, match="baseline"):
        ProjectorTriangulator(cam, proj, "y", rays)


def test_depth_range_and_buffers() -> None:
    _cam, proj, _ = procam_rig("h")
    truth = true_points("h", "sphere")
    maps = codes(proj, truth, "x")
    tri = triangulator("h", "x")
    xyz = tri.triangulate(maps, min_depth_mm=520.0, max_depth_mm=540.0)
    z = xyz[..., 2]
    assert np.isfinite(z).sum() > 1000
    assert np.nanmin(z) >= 520.0 and np.nanmax(z) <= 540.0
    expect = maps.mask & (truth[..., 2] >= 520.001) & (truth[..., 2] <= 539.999)
    assert np.all(np.isfinite(z[expect]))
    with pytest.raises(ValueError, match="out"):
        tri.triangulate(maps, np.empty((10, 10, 3), np.float32))
    with pytest.raises(ValueError, match="decoded maps"):
        tri.triangulate(DecodedMaps(maps.u[:10], maps.v[:10], maps.mask[:10], maps.quality[:10]))


# --- filters -------------------------------------------------------------------------------------------


def _plane_cloud() -> tuple[np.ndarray, F64]:
    _cam, proj, _ = procam_rig("h")
    truth = true_points("h", "plane")
    return triangulator("h", "x").triangulate(codes(proj, truth, "x")), truth


def test_filter_isolated_removes_specks_and_spikes() -> None:
    xyz, _ = _plane_cloud()
    valid = np.isfinite(xyz[..., 2])
    rows, cols = np.nonzero(valid)
    inner = (rows > 400) & (rows < 600) & (cols > 500) & (cols < 700)
    spikes = (rows[inner][::997], cols[inner][::997])
    xyz[spikes] += np.float32(10.0)  # 10 mm depth spikes inside the surface
    empty = ~valid[:-2, :-2] & ~valid[1:-1, :-2] & ~valid[2:, :-2] & ~valid[:-2, 1:-1] & ~valid[1:-1, 1:-1]
    empty &= ~valid[2:, 1:-1] & ~valid[:-2, 2:] & ~valid[1:-1, 2:] & ~valid[2:, 2:]
    er, ec = np.nonzero(empty)
    pick = np.linspace(0, len(er) - 1, 3).astype(int)
    specks = (er[pick] + 1, ec[pick] + 1)  # lone points where the surface is not seen
    xyz[specks] = np.float32(600.0)
    n_before = np.isfinite(xyz[..., 2]).sum()
    removed = filter_isolated(xyz, 3, 2.0)
    assert np.all(np.isnan(xyz[spikes])) and np.all(np.isnan(xyz[specks]))
    # the spikes' neighbours keep >= 7 good neighbours; only specks, spikes and a thin border go
    assert removed == n_before - np.isfinite(xyz[..., 2]).sum()
    assert removed < len(spikes[0]) + 3 + 0.01 * n_before
    assert filter_isolated(xyz, 0, 2.0) == 0


def test_point_cloud_from_an_organised_cloud() -> None:
    xyz, truth = _plane_cloud()
    q = np.random.default_rng(1).uniform(0, 100, xyz.shape[:2]).astype(np.float32)
    normals = estimate_normals(xyz)
    xyz[q < 20] = np.nan  # holes: only the finite points become points
    inten = (np.arange(xyz.shape[0] * xyz.shape[1]) % 251).astype(np.uint8).reshape(xyz.shape[:2])
    cloud = to_point_cloud(xyz, q, inten, 2, normals)
    assert len(cloud) == np.isfinite(xyz[..., 2]).sum()
    np.testing.assert_array_equal(cloud.xyz, xyz[cloud.row, cloud.col])
    np.testing.assert_array_equal(cloud.intensity, inten[cloud.row, cloud.col])
    np.testing.assert_array_equal(cloud.quality, q[cloud.row, cloud.col])
    assert np.all(cloud.quality >= 20) and np.all(cloud.camera == 2)
    assert np.all(np.diff(cloud.row.astype(np.int64) * 10000 + cloud.col) > 0)  # row-major order
    assert np.max(np.linalg.norm(cloud.xyz - truth[cloud.row, cloud.col], axis=1)) < EXACT_TOL_MM
    # normals of the plane, facing the camera at the origin
    n = PLANE[1][1] / np.linalg.norm(PLANE[1][1])  # (0.2, -0.1, -1): towards the origin
    assert cloud.normal is not None
    good = np.isfinite(cloud.normal[:, 0])
    assert good.mean() > 0.99
    assert np.min(cloud.normal[good] @ n) > 0.9999


# --- pipeline ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["projector", "stereo"])
def test_reconstructor(mode: str) -> None:
    calib = two_camera_calibration()
    proj = calib.projector
    assert proj is not None
    truth = {n: cast(calib.devices[n], PLANE) for n in calib.camera_names}
    maps = {n: codes(proj, truth[n], "x") for n in calib.camera_names}
    white = {n: np.full((1024, 1280), 1234, np.uint16) for n in calib.camera_names}
    cfg = ReconstructionConfig(mode=mode, min_depth_mm=400, max_depth_mm=800, normals=True)  # type: ignore[arg-type]
    rec = Reconstructor(calib, "x", cfg)
    out = rec.run(maps, white)
    cloud, timings = out.cloud, out.timings_ms
    del out
    assert set(timings) >= {"triangulate_ms", "filter_ms"} and all(v >= 0 for v in timings.values())
    cams = [0, 1] if mode == "projector" else [0]
    assert sorted(set(cloud.camera.tolist())) == cams
    for i in cams:
        sel = cloud.camera == i
        t = truth[calib.camera_names[i]][cloud.row[sel], cloud.col[sel]]
        tol = EXACT_TOL_MM if mode == "projector" else 0.05
        assert np.max(np.linalg.norm(cloud.xyz[sel] - t, axis=1)) < tol
        assert sel.sum() > 0.9 * maps[calib.camera_names[i]].mask.sum()
    grey = round(1234 * 255 / 65535)  # uint16 without stated bits: full scale 65535 -> 255, rounded
    assert np.all(cloud.intensity == grey)
    assert cloud.normal is not None and cloud.normal.shape == (len(cloud), 3)
    again = rec.run(maps, None).cloud  # buffers are reused, clouds are not
    assert len(again) == len(cloud) and np.all(again.intensity == 0)
    assert np.all(cloud.intensity == grey)


def test_reconstructor_needs_a_projector() -> None:
    calib = two_camera_calibration()
    no_proj = Calibration({n: calib.devices[n] for n in calib.camera_names})
    with pytest.raises(CalibrationError, match="projector"):
        Reconstructor(no_proj, "x", ReconstructionConfig())


# --- the epipolar check (both axes) ----------------------------------------------------------------------


def _mirrored_codes(proj: CameraModel, truth: F64, point: F64, normal: F64) -> tuple[F64, F64]:
    """Codes a mirror (plane through ``point``, ``normal``) puts on each true point: the real projector pixel
    whose ray, reflected by the mirror, reaches it, i.e. the projection of the point mirrored in that plane."""
    n = normal / np.linalg.norm(normal)
    flat = truth.reshape(-1, 3)
    mirrored = flat - 2.0 * ((flat - point) @ n)[:, None] * n
    px, _ = proj.project(mirrored)
    return px[:, 0].reshape(truth.shape[:2]), px[:, 1].reshape(truth.shape[:2])


def _epipolar_residual(proj: CameraModel, cam: CameraModel, truth: F64, u: F64, v: F64) -> F64:
    """Exact distance (projector px) of codes (u, v) from each pixel's epipolar line (through its true point)."""
    flat = truth.reshape(-1, 3)
    ray = flat - cam.center
    near, _ = proj.project(flat)
    far, _ = proj.project(flat + 50.0 * ray / np.linalg.norm(ray, axis=1, keepdims=True))
    d = far - near
    with np.errstate(invalid="ignore"):
        across = ((u.ravel() - near[:, 0]) * d[:, 1] - (v.ravel() - near[:, 1]) * d[:, 0]) / np.linalg.norm(d, axis=1)
    return np.abs(across).reshape(truth.shape[:2])  # type: ignore[no-any-return]


def test_a_mirrored_copy_of_the_pattern_is_dropped_off_the_epipolar_line() -> None:
    # the plane's left half receives a second copy of the pattern from a mirror (the codes of the mirrored
    # projector); every pixel carries code noise of the modelled sigma (quality 40 DN: ~0.2 px per axis)
    cam, proj, _ = procam_rig("h")
    truth = true_points("h", "plane")
    maps = codes(proj, truth, "xy")
    noise = CodeNoise(16 * np.sqrt(2 / 4) / np.pi, 0.0, 2.0, 25.0)
    sigma_u = float(noise.sigma_px(40.0))
    gu, gv = _mirrored_codes(proj, truth, np.array([-40.0, 0.0, 640.0]), np.array([1.0, 0.25, -0.8]))
    h, w = maps.shape
    ghost = maps.mask & (np.arange(w)[None, :] < w // 2) & np.isfinite(gu) & np.isfinite(gv)
    ghost &= (gu >= 0) & (gu <= proj.width - 1) & (gv >= 0) & (gv <= proj.height - 1)
    rng = np.random.default_rng(3)
    u = np.where(ghost, gu, maps.u) + rng.normal(0.0, sigma_u, (h, w))
    v = np.where(ghost, gv, maps.v) + rng.normal(0.0, sigma_u, (h, w))
    noisy = DecodedMaps(u.astype(np.float32), v.astype(np.float32), maps.mask, maps.quality,
                        reason=np.where(maps.mask, 0, int(Reason.SHADOW)).astype(np.uint8))  # fmt: skip
    tri = triangulator("h", "xy")
    stats = np.empty((h, 6), np.int64)
    depth, _counts = tri.triangulate_depth(noisy, noise=noise, stats=stats, reason_out=noisy.reason)
    reason = noisy.reason
    assert reason is not None
    off = _epipolar_residual(proj, cam, truth, gu, gv)
    limit = np.hypot(EPIPOLAR_SIGMAS * sigma_u, EPIPOLAR_FLOOR_PX)
    clean = maps.mask & ~ghost
    # no direct (clean) pixel is lost to the check; a ghost well off its line never becomes a point
    assert not (reason[clean] == Reason.EPIPOLAR).any()
    assert np.isfinite(depth[clean]).mean() > 0.999
    far_off = ghost & (off > limit + 5 * sigma_u)
    assert far_off.sum() > 0.9 * ghost.sum()  # this mirror is tilted out of the epipolar planes
    assert (reason[far_off] == Reason.EPIPOLAR).all() and not np.isfinite(depth[far_off]).any()
    # the ghosts kept lie on their epipolar line by geometry, within the limit: nothing can tell them apart
    kept_ghost = ghost & np.isfinite(depth)
    assert (off[kept_ghost] <= limit + 5 * sigma_u).all()
    # every pixel has one reason; decoded ones without a point say which stage; the counts add up
    assert set(np.unique(reason[maps.mask]).tolist()) <= {Reason.DECODED, Reason.EPIPOLAR, Reason.OUT_OF_RANGE,
                                                          Reason.FILTERED}  # fmt: skip
    assert np.array_equal(reason == Reason.DECODED, np.isfinite(depth))
    s = stats.sum(axis=0)
    assert s[1] - s[2] == int((reason == Reason.EPIPOLAR).sum())
    # one coded axis has nothing to check: the same ghosts become points
    xmaps = DecodedMaps(noisy.u, np.full_like(noisy.v, np.nan), maps.mask, maps.quality)
    xdepth, _ = triangulator("h", "x").triangulate_depth(xmaps, noise=noise)
    assert np.isfinite(xdepth[far_off]).mean() > 0.99


def test_the_epipolar_floor_absorbs_a_small_calibration_error() -> None:
    # the projector's true principal point is 0.3 px lower than the calibration says: residuals of ~0.3 px
    # across every epipolar line, beyond 5 sigma of a high-contrast pixel (sigma 0.03 px) but under the floor
    _cam, proj, _ = procam_rig("h")
    truth = true_points("h", "plane")
    k = proj.K.copy()
    k[1, 2] += 0.3
    real = CameraModel("projector", k, proj.dist, proj.width, proj.height, proj.R, proj.T)
    maps = codes(real, truth, "xy")
    maps = DecodedMaps(maps.u, maps.v, maps.mask, np.where(maps.mask, 250.0, 0.0).astype(np.float32))
    noise = CodeNoise(16 * np.sqrt(2 / 4) / np.pi, 0.0, 2.0, 25.0)
    depth, _ = triangulator("h", "xy").triangulate_depth(maps, noise=noise)
    assert np.isfinite(depth[maps.mask]).mean() > 0.999


def test_a_calibration_off_everywhere_is_not_taken_for_reflections() -> None:
    # the projector's principal point is 4 px lower than the calibration says: every pixel misses its line by
    # ~4 px. The check would drop the whole scan and leave the calibration health nothing to judge; instead the
    # points are kept, the health residual shows the error, and the warning names the calibration
    from appliance.calibration.scan_health import assess_scan

    cam, proj, _ = procam_rig("h")
    truth = true_points("h", "plane")
    k = proj.K.copy()
    k[1, 2] += 4.0
    real = CameraModel("projector", k, proj.dist, proj.width, proj.height, proj.R, proj.T)
    maps = codes(real, truth, "xy")
    maps.reason = np.where(maps.mask, 0, int(Reason.SHADOW)).astype(np.uint8)
    calib = Calibration({"cam0": cam, "projector": proj})
    cfg = ReconstructionConfig(min_depth_mm=400, max_depth_mm=800)
    rec = Reconstructor(calib, "xy", cfg, noise=CodeNoise(16 * np.sqrt(2 / 4) / np.pi, 0.0, 2.0, 25.0)).run(
        {"cam0": maps}, None
    )
    assert len(rec.cloud) > 0.9 * maps.mask.sum()
    assert not (maps.reason == Reason.EPIPOLAR).any()
    assert any("calibration may no longer fit" in w for w in rec.warnings), rec.warnings
    (res,) = [r for r in rec.residuals if r.kind == "ray_ray"]
    assert res.abs_median_px > 2.0
    assert assess_scan(rec.residuals, calib, None, 0.6)["status"] == "bad"
