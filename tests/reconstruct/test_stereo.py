"""Camera-camera triangulation by projector codes, against ray-cast ground truth."""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt
import pytest

from appliance.geometry.camera import CameraModel, look_at
from appliance.reconstruct.stereo import StereoTriangulator, triangulate_stereo
from appliance.reconstruct.types import DecodedMaps

F64 = npt.NDArray[np.float64]
SPHERE_C = np.array([10.0, -5.0, 560.0])
SURFACES = {
    "plane": ("plane", (np.array([0.0, 0.0, 600.0]), np.array([0.2, -0.1, -1.0]))),
    "sphere": ("sphere", (SPHERE_C, 60.0)),
}
TOL_MM = 0.05


@cache
def _rig() -> tuple[CameraModel, CameraModel, CameraModel]:
    cam0 = CameraModel(
        "cam0", [[1800, 0, 639.7], [0, 1800, 512.7], [0, 0, 1]], [-0.12, 0.09, 4e-4, -3e-4, -0.02], 1280, 1024
    )
    r1, t1 = look_at(np.array([200.0, 5.0, 3.0]), np.array([30.0, 0.0, 575.0]))
    cam1 = CameraModel(
        "cam1",
        [[1750, 0, 630], [0, 1752, 515], [0, 0, 1]],
        [-0.1, 0.07, -2e-4, 3e-4, -0.01],
        1280,
        1024,
        r1,
        t1,
    )
    rp, tp = look_at(np.array([100.0, -30.0, 0.0]), np.array([0.0, 0.0, 575.0]))
    proj = CameraModel(
        "projector",
        [[1600, 0, 640.4], [0, 1600, 780.2], [0, 0, 1]],
        [0.08, -0.05, -6e-4, 5e-4, 0.01],
        1280,
        800,
        rp,
        tp,
    )
    return cam0, cam1, proj


@cache
def _matchers() -> tuple[StereoTriangulator, StereoTriangulator]:
    cam0, cam1, proj = _rig()
    plain = StereoTriangulator(cam0, cam1)
    return plain, StereoTriangulator(cam0, cam1, plain.rays0, projector=proj)


def _cast(cam: CameraModel, surface: str) -> F64:
    dw = cam.pixel_rays_device() @ cam.R
    c = cam.center
    kind, (p, q) = SURFACES[surface]
    if kind == "plane":
        n = q / np.linalg.norm(q)
        t = ((p - c) @ n) / (dw @ n)
    else:
        oc = c - p
        b = dw @ oc
        disc = b * b - (oc @ oc - float(q) ** 2)  # type: ignore[arg-type]
        t = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.nan)
    return c + t[..., None] * dw  # type: ignore[no-any-return]


def _codes(proj: CameraModel, xyz: F64, axes: str) -> DecodedMaps:
    h, w = xyz.shape[:2]
    px, _ = proj.project(xyz.reshape(-1, 3))
    u, v = px[:, 0].reshape(h, w), px[:, 1].reshape(h, w)
    with np.errstate(invalid="ignore"):
        ok = (u >= -0.5) & (u <= proj.width - 0.5) & (v >= -0.5) & (v <= proj.height - 0.5)
    u32 = np.where(ok, u, np.nan).astype(np.float32)
    v32 = np.where(ok & ("y" in axes), v, np.nan).astype(np.float32)
    return DecodedMaps(u32, v32, ok, np.where(ok, 40.0, 0.0).astype(np.float32))


@cache
def _scene(surface: str) -> tuple[F64, F64, F64]:
    """Truth seen by cam0 and cam1, and for cam0 pixels whether cam1 sees the point too (not at grazing)."""
    cam0, cam1, _ = _rig()
    x0, x1 = _cast(cam0, surface), _cast(cam1, surface)
    px, _ = cam1.project(x0.reshape(-1, 3))
    px = px.reshape(*x0.shape[:2], 2)
    with np.errstate(invalid="ignore"):
        inside = (
            (px[..., 0] > 2)
            & (px[..., 0] < cam1.width - 3)
            & (px[..., 1] > 2)
            & (px[..., 1] < cam1.height - 3)
        )
    if surface == "sphere":  # visible from cam1: the surface faces it; cos of incidence in both views
        n = (x0 - SPHERE_C) / 60.0
        v0 = -x0 / np.linalg.norm(x0, axis=2, keepdims=True)
        v1 = cam1.center - x0
        v1 /= np.linalg.norm(v1, axis=2, keepdims=True)
        cos = np.minimum(np.sum(n * v0, 2), np.sum(n * v1, 2))
    else:
        cos = np.ones(x0.shape[:2])
    return x0, x1, np.where(inside, cos, np.nan)


@pytest.mark.parametrize("axes", ["x", "xy"])
@pytest.mark.parametrize("surface", ["plane", "sphere"])
def test_stereo_exact_codes(surface: str, axes: str) -> None:
    cam0, _cam1, proj = _rig()
    x0, x1, cos = _scene(surface)
    m0, m1 = _codes(proj, x0, axes), _codes(proj, x1, axes)
    plain, _ = _matchers()
    out = np.empty((cam0.height, cam0.width, 3), np.float32)
    xyz = plain.triangulate(m0, m1, out)
    assert xyz is out
    err = np.linalg.norm(xyz - x0, axis=2)
    assert np.all(np.isnan(xyz[~m0.mask]))
    ok = np.isfinite(err)
    # nearly every pixel coded in cam0 and seen by cam1 at a sane angle is matched
    seen = m0.mask & (cos > 0.35)
    assert ok[seen].mean() > 0.97
    # error < 0.05 mm where both views see the surface within 75 deg of its normal; 99% of all matches too
    good = ok & (cos > np.cos(np.radians(75)))
    assert np.max(err[good]) < TOL_MM, f"max {np.max(err[good]):.3g} mm"
    assert np.percentile(err[ok], 99) < TOL_MM
    if surface == "plane":
        assert np.max(err[ok]) < 0.005


def test_stereo_function_matches_class() -> None:
    cam0, cam1, proj = _rig()
    x0, x1, _ = _scene("plane")
    m0, m1 = _codes(proj, x0, "x"), _codes(proj, x1, "x")
    a = triangulate_stereo(m0, m1, cam0, cam1, max_epipolar_px=1.5, min_depth_mm=590.0, max_depth_mm=610.0)
    b = _matchers()[0].triangulate(m0, m1, min_depth_mm=590.0, max_depth_mm=610.0)
    np.testing.assert_array_equal(a, b)
    z = a[..., 2]
    assert np.isfinite(z).sum() > 1000 and np.nanmin(z) >= 590.0 and np.nanmax(z) <= 610.0


def _corrupt(m: DecodedMaps, r: int, c: int, half: int, shift: float) -> DecodedMaps:
    u = m.u.copy()
    u[r - half : r + half, c - half : c + half] += np.float32(shift)
    return DecodedMaps(u, m.v, m.mask, m.quality)


def test_left_right_check_rejects_codes_seen_twice() -> None:
    """A narrow patch with codes shifted far: each wrong code also exists at its true place on the row."""
    _cam0, _cam1, proj = _rig()
    x0, x1, _ = _scene("plane")
    m0, m1 = _codes(proj, x0, "x"), _codes(proj, x1, "x")
    rows, cols = np.nonzero(m0.mask)
    r, c = int(np.median(rows)), int(np.median(cols))
    bad = _corrupt(m0, r, c, 8, 60.0)
    xyz = _matchers()[0].triangulate(bad, m1)
    patch = xyz[r - 8 : r + 8, c - 8 : c + 8]
    assert np.all(np.isnan(patch))
    err = np.linalg.norm(xyz - x0, axis=2)
    assert np.nanmax(err) < 0.005  # nothing wrong anywhere else
    # the true owners of the duplicated codes are ambiguous now: rejected too, and nothing more than that
    assert np.isfinite(err).sum() > m0.mask.sum() - 3 * 16 * 16 - 0.01 * m0.mask.sum()


@pytest.mark.parametrize("where", ["cam0", "cam1"])
def test_projector_check_rejects_a_corrupted_patch(where: str) -> None:
    _cam0, _cam1, proj = _rig()
    x0, x1, _ = _scene("plane")
    m0, m1 = _codes(proj, x0, "x"), _codes(proj, x1, "x")
    target = m0 if where == "cam0" else m1
    rows, cols = np.nonzero(target.mask)
    r, c = int(np.median(rows)), int(np.median(cols))
    bad = _corrupt(target, r, c, 20, 30.0)  # wide patch, shift smaller than its width
    plain, checked = _matchers()
    args = (bad, m1) if where == "cam0" else (m0, bad)
    err_plain = np.linalg.norm(plain.triangulate(*args) - x0, axis=2)
    err = np.linalg.norm(checked.triangulate(*args) - x0, axis=2)
    assert np.nansum(err_plain > 1.0) > 100  # without the projector some wrong matches survive ...
    assert np.nanmax(err) < 0.005  # ... with the three-view check none do
    assert np.isfinite(err).sum() > 0.95 * np.isfinite(err_plain).sum()


def test_v_consistency_rejects_matches_off_the_epipolar_line() -> None:
    _cam0, _cam1, proj = _rig()
    x0, x1, _ = _scene("plane")
    m0, m1 = _codes(proj, x0, "xy"), _codes(proj, x1, "xy")
    rows, cols = np.nonzero(m0.mask)
    r, c = int(np.median(rows)), int(np.median(cols))
    v = m0.v.copy()
    v[r - 10 : r + 10, c - 10 : c + 10] += np.float32(5.0)  # rows wrong by 5 projector px (~5 camera px)
    xyz = _matchers()[0].triangulate(DecodedMaps(m0.u, v, m0.mask, m0.quality), m1)
    assert np.all(np.isnan(xyz[r - 10 : r + 10, c - 10 : c + 10]))
    assert np.isfinite(xyz[r - 40 : r - 20, c - 10 : c + 10, 2]).all()


@pytest.mark.parametrize("k3", [-0.02, 9.5])  # the test rig's lens; a strong one (k3 of the real two-camera set)
def test_knot_maps_stay_within_their_tolerance_of_opencv(k3: float) -> None:
    """The rectification maps keep a knot every few pixels (memory); interpolated, they match OpenCV's own
    projection (rectified grid -> camera pixel) and undistortion (camera pixel -> rectified grid) within
    ``MAP_TOLERANCE_PX`` plus float32 rounding, everywhere the camera sees."""
    import cv2

    from appliance.reconstruct import _stereo_kernels as C
    from appliance.reconstruct.stereo import MAP_TOLERANCE_PX

    base0, cam1, _ = _rig()
    dist = np.array([-0.12, 0.09, 4e-4, -3e-4, k3])
    cam0 = CameraModel("cam0", base0.K, dist, 1280, 1024)
    tri = StereoTriangulator(cam0, cam1)
    a0min, _, bmin, step, _ = tri._geom
    hr, wr0, _ = tri.rect_shape
    rng = np.random.default_rng(3)

    # rectified grid -> cam0 pixel, against cv2.projectPoints of the grid's directions
    grid = C.sample_map(tri._map0, tri._knot0, 1, hr, wr0)
    ys, xs = rng.integers(0, hr, 20000), rng.integers(0, wr0, 20000)
    dirs = (tri._rot0.T @ np.stack([a0min + xs * step, bmin + ys * step, np.ones(xs.size)])).T
    front = dirs[:, 2] > 0
    want, _ = cv2.projectPoints(dirs[front], np.zeros(3), np.zeros(3), cam0.K, dist)
    want = want.reshape(-1, 2)
    got = grid[ys[front], xs[front]].astype(np.float64)
    seen = (want[:, 0] >= 0) & (want[:, 0] <= 1279) & (want[:, 1] >= 0) & (want[:, 1] <= 1023)
    assert seen.sum() > 5000
    err = np.hypot(*(got[seen] - want[seen]).T)
    assert err.max() <= MAP_TOLERANCE_PX + 2e-3, (tri._knot0, err.max())

    # cam0 pixel -> rectified grid, against cv2.undistortPoints iterated to convergence and the rectifying rotation
    px = np.stack([rng.uniform(0, 1279, 20000), rng.uniform(0, 1023, 20000)], 1)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    norm = cv2.undistortPoints(px.reshape(-1, 1, 2), cam0.K, dist, None, None, None, crit).reshape(-1, 2)
    rect = (tri._rot0 @ np.column_stack([norm, np.ones(len(norm))]).T).T
    want_r = np.stack([(rect[:, 0] / rect[:, 2] - a0min) / step, (rect[:, 1] / rect[:, 2] - bmin) / step], 1)
    full = C.sample_map(tri._rect0, tri._knot_r0, 1, 1024, 1280)
    ix, iy = np.floor(px[:, 0]).astype(int), np.floor(px[:, 1]).astype(int)
    tx, ty = (px[:, 0] - ix)[:, None], (px[:, 1] - iy)[:, None]
    got_r = ((1 - ty) * ((1 - tx) * full[iy, ix] + tx * full[iy, ix + 1])
             + ty * ((1 - tx) * full[iy + 1, ix] + tx * full[iy + 1, ix + 1]))  # fmt: skip
    # the map is exact at pixels; between pixels its own bilinear step adds the curvature over one pixel
    err_r = np.hypot(*(got_r - want_r).T)
    assert np.median(err_r) <= MAP_TOLERANCE_PX and err_r.max() <= MAP_TOLERANCE_PX + 0.01, (tri._knot_r0, err_r.max())
    assert tri._map0.nbytes < 0.5 * hr * wr0 * 8 or tri._knot0 == 1  # kept coarse where the lens allows
