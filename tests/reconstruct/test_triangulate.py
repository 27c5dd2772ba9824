"""Camera-projector triangulation, filters and the reconstruction pipeline against ground truth.

The scene is rendered geometrically: every camera pixel's true 3-D point is ray-cast (float64) onto a known
plane or sphere and projected into the (distorted) projector to give exact decoded codes.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt
import pytest

from appliance.config.schema import ReconstructionConfig
from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import Calibration
from appliance.geometry.camera import CameraModel, look_at
from appliance.geometry.rays import RayTable
from appliance.reconstruct.filters import (
    estimate_normals,
    filter_isolated,
    to_point_cloud,
)
from appliance.reconstruct.pipeline import Reconstructor
from appliance.reconstruct.triangulate import ProjectorTriangulator
from appliance.reconstruct.types import DecodedMaps

F64 = npt.NDArray[np.float64]
PLANE = ("plane", (np.array([0.0, 0.0, 600.0]), np.array([0.2, -0.1, -1.0])))
SPHERE = ("sphere", (np.array([10.0, -5.0, 560.0]), 60.0))
EXACT_TOL_MM = 0.005


def _camera(name: str = "cam0", pose: tuple[F64, F64] | None = None) -> CameraModel:
    r, t = pose if pose is not None else (np.eye(3), np.zeros(3))
    return CameraModel(
        name,
        [[1800, 0, 639.7], [0, 1800, 512.7], [0, 0, 1]],
        [-0.12, 0.09, 4e-4, -3e-4, -0.02],
        1280,
        1024,
        r,
        t,
    )


def _projector(
    offset: tuple[float, float, float], dist: tuple[float, ...] = (0.08, -0.05, -6e-4, 5e-4, 0.01)
) -> CameraModel:
    r, t = look_at(np.array(offset), np.array([0.0, 0.0, 575.0]))
    return CameraModel(
        "projector", [[1600, 0, 640.4], [0, 1600, 780.2], [0, 0, 1]], list(dist), 1280, 800, r, t
    )


@cache
def _rig(kind: str) -> tuple[CameraModel, CameraModel, RayTable]:
    """'h': 175 mm horizontal baseline, 'v': vertical, 'posed': camera not at the world origin."""
    if kind == "posed":
        cam = _camera("cam1", look_at(np.array([-60.0, 20.0, -10.0]), np.array([0.0, 0.0, 590.0])))
        proj = _projector((115.0, 20.0, 0.0))
    else:
        cam = _camera()
        proj = _projector((175.0, 0.0, 0.0) if kind == "h" else (0.0, 175.0, 0.0))
    return cam, proj, RayTable(cam)


def cast(cam: CameraModel, surface: tuple[str, tuple[F64, F64]]) -> F64:
    """True world point (H, W, 3) of every camera pixel on the surface (NaN where missed)."""
    dw = cam.pixel_rays_device() @ cam.R  # device -> world directions
    c = cam.center
    kind, (p, q) = surface
    if kind == "plane":
        n = q / np.linalg.norm(q)
        t = ((p - c) @ n) / (dw @ n)
    else:
        oc = c - p
        b = dw @ oc
        disc = b * b - (oc @ oc - float(q) ** 2)  # type: ignore[arg-type]
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.nan)
    return c + t[..., None] * dw  # type: ignore[no-any-return]


def codes(proj: CameraModel, xyz: F64, axes: str = "xy") -> DecodedMaps:
    """Exact decoded maps of the points seen by the projector; uncoded axes are NaN."""
    h, w = xyz.shape[:2]
    px, _ = proj.project(xyz.reshape(-1, 3))
    u, v = px[:, 0].reshape(h, w), px[:, 1].reshape(h, w)
    with np.errstate(invalid="ignore"):
        ok = (u >= -0.5) & (u <= proj.width - 0.5) & (v >= -0.5) & (v <= proj.height - 0.5)
    u32 = np.where(ok & ("x" in axes), u, np.nan).astype(np.float32)
    v32 = np.where(ok & ("y" in axes), v, np.nan).astype(np.float32)
    return DecodedMaps(u32, v32, ok, np.where(ok, 40.0, 0.0).astype(np.float32))


@cache
def _truth(kind: str, surface: str) -> F64:
    cam, _, _ = _rig(kind)
    return cast(cam, PLANE if surface == "plane" else SPHERE)


@cache
def _triangulator(kind: str, axes: str) -> ProjectorTriangulator:
    cam, proj, rays = _rig(kind)
    return ProjectorTriangulator(cam, proj, axes, rays)


@pytest.mark.parametrize("surface", ["plane", "sphere"])
@pytest.mark.parametrize(
    ("kind", "axes"), [("h", "x"), ("h", "xy"), ("v", "y"), ("posed", "x"), ("posed", "xy")]
)
def test_exact_codes_recover_the_surface(kind: str, axes: str, surface: str) -> None:
    cam, proj, _ = _rig(kind)
    truth = _truth(kind, surface)
    maps = codes(proj, truth, axes)
    tri = _triangulator(kind, axes)
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
    cam, proj, rays = _rig("h")
    truth = _truth("h", "plane")
    maps = codes(proj, truth, "x")
    naive = CameraModel("projector", proj.K, np.zeros(5), proj.width, proj.height, proj.R, proj.T)
    err = np.linalg.norm(ProjectorTriangulator(cam, naive, "x", rays).triangulate(maps) - truth, axis=2)
    assert np.nanmax(err) > 100 * EXACT_TOL_MM


@pytest.mark.parametrize("axes", ["x", "xy"])
def test_code_noise_propagates_as_the_geometry_predicts(axes: str) -> None:
    _cam, proj, _ = _rig("h")
    truth = _truth("h", "plane")
    maps = codes(proj, truth, axes)
    tri = _triangulator("h", axes)
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
    cam, proj, rays = _rig("h")
    with pytest.raises(CalibrationError, match="baseline"):
        ProjectorTriangulator(cam, proj, "y", rays)


def test_depth_range_and_buffers() -> None:
    _cam, proj, _ = _rig("h")
    truth = _truth("h", "sphere")
    maps = codes(proj, truth, "x")
    tri = _triangulator("h", "x")
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
    _cam, proj, _ = _rig("h")
    truth = _truth("h", "plane")
    return _triangulator("h", "x").triangulate(codes(proj, truth, "x")), truth


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


@cache
def _two_camera_calibration() -> Calibration:
    cam0 = _camera()
    cam1 = _camera("cam1", look_at(np.array([200.0, 5.0, 3.0]), np.array([30.0, 0.0, 575.0])))
    return Calibration({"cam0": cam0, "cam1": cam1, "projector": _projector((100.0, -30.0, 0.0))})


@pytest.mark.parametrize("mode", ["projector", "stereo"])
def test_reconstructor(mode: str) -> None:
    calib = _two_camera_calibration()
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
    calib = _two_camera_calibration()
    no_proj = Calibration({n: calib.devices[n] for n in calib.camera_names})
    with pytest.raises(CalibrationError, match="projector"):
        Reconstructor(no_proj, "x", ReconstructionConfig())
