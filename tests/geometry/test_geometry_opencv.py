"""The camera model's projection and undistortion against OpenCV's, over random models.

The truth of the accuracy tests is rendered with the same distortion formula the reconstruction inverts, so
an error in that formula would cancel out there. Here every implementation of it (``CameraModel.project``,
the virtual rig's projection kernel, the triangulation's distortion kernel, ``CameraModel.undistort_pixels``
and the no-distortion fast path) is compared with ``cv2.projectPoints`` / ``cv2.undistortPoints`` on random
intrinsics and distortion (k1..k6, p1 p2 and, where the code supports them, s1..s4), within the range where
the distortion is invertible (the distorted radius grows with the radius).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from appliance.geometry._distortion_kernels import distort_jac
from appliance.geometry.camera import CameraModel
from appliance.sim._sim_kernels import project_points

F64 = npt.NDArray[np.float64]
PROJECT_TOL_PX = 1e-6
UNDISTORT_TOL_PX = 1e-5
R_MAX = 0.55  # normalised radius of the points (about a 57 degree field of view)
MODELS = 40


def random_model(rng: np.random.Generator, n_dist: int) -> CameraModel:
    """A random camera: focal 400..3000 px, principal point near the centre, a random pose, n_dist coefficients.

    Redrawn until the distortion is monotone out to ``R_MAX`` (where calibrations are valid).
    """
    w, h = int(rng.integers(320, 2500)), int(rng.integers(240, 2000))
    f = rng.uniform(400, 3000)
    K = np.array([[f, 0, w / 2 + rng.uniform(-30, 30)], [0, f * rng.uniform(0.98, 1.02), h / 2 + rng.uniform(-30, 30)],
                  [0, 0, 1]])
    scale = np.array([0.4, 0.2, 0.01, 0.01, 0.1, 0.2, 0.1, 0.05, 0.005, 0.002, 0.005, 0.002])
    while True:
        dist = rng.uniform(-1, 1, n_dist) * scale[:n_dist]
        r = np.linspace(0, R_MAX * 1.5, 400)
        model = CameraModel("cam", K, dist, w, h, *_random_pose(rng))
        xd, yd = _cv2_distort(model, r, np.zeros_like(r))
        if np.all(np.diff(np.hypot(xd, yd)) > 0):
            return model


def _random_pose(rng: np.random.Generator) -> tuple[F64, F64]:
    rvec = rng.uniform(-0.5, 0.5, 3)
    R, _ = cv2.Rodrigues(rvec)
    return R, rng.uniform(-200, 200, 3)


def points_in_view(model: CameraModel, rng: np.random.Generator, n: int = 500) -> F64:
    """World points (n, 3) in front of the device, normalised radius <= R_MAX, 200..3000 mm deep."""
    r = R_MAX * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(200, 3000, n)
    dev = np.stack([r * np.cos(phi) * z, r * np.sin(phi) * z, z], axis=1)
    return (dev - model.T) @ model.R  # type: ignore[no-any-return]


def _cv2_distort(model: CameraModel, xn: F64, yn: F64) -> tuple[F64, F64]:
    """OpenCV's distortion of normalised coordinates (identity camera matrix)."""
    pts = np.stack([xn, yn, np.ones_like(xn)], axis=1).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), model.dist)
    return out[:, 0, 0], out[:, 0, 1]


def cv2_project(model: CameraModel, xyz: F64) -> F64:
    rvec, _ = cv2.Rodrigues(model.R)
    out, _ = cv2.projectPoints(xyz.reshape(-1, 1, 3), rvec, model.T, model.K, model.dist)
    return out.reshape(-1, 2)  # type: ignore[no-any-return]


def project_error_px(model: CameraModel, xyz: F64) -> float:
    px, _ = model.project(xyz)
    return float(np.max(np.abs(px - cv2_project(model, xyz))))


def sim_project(model: CameraModel, xyz: F64) -> F64:
    uv = np.empty((len(xyz), 2))
    project_points(np.ascontiguousarray(xyz), model.R, model.T, model.K, model.dist_padded(8), uv,
                   np.empty(len(xyz)))
    return uv


def undistort_error_px(model: CameraModel, xyz: F64, undistort: Callable[[F64], F64]) -> float:
    """Distort with OpenCV, undistort with ``undistort``: the error against the true direction (px)."""
    dev = model.to_device(xyz)
    truth = dev[:, :2] / dev[:, 2:]
    n = undistort(cv2_project(model, xyz))
    return float(np.max(np.abs(n - truth)) * model.K[0, 0])


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8])
def test_project_matches_opencv(n_dist: int) -> None:
    rng = np.random.default_rng(100 + n_dist)
    worst = 0.0
    for _ in range(MODELS):
        model = random_model(rng, n_dist)
        xyz = points_in_view(model, rng)
        worst = max(worst, project_error_px(model, xyz))
    print(f"{n_dist} coefficients: worst |project - cv2.projectPoints| = {worst:.2e} px")
    assert worst < PROJECT_TOL_PX


@pytest.mark.parametrize("n_dist", [4, 5, 8])
def test_virtual_rig_projection_matches_opencv(n_dist: int) -> None:
    """The renderer's kernel (the ground truth of the accuracy tests) against OpenCV."""
    rng = np.random.default_rng(200 + n_dist)
    for _ in range(MODELS):
        model = random_model(rng, n_dist)
        xyz = points_in_view(model, rng)
        np.testing.assert_allclose(sim_project(model, xyz), cv2_project(model, xyz), rtol=0, atol=PROJECT_TOL_PX)


@pytest.mark.parametrize("n_dist", [5, 8, 12])
def test_triangulation_distortion_kernel_matches_opencv(n_dist: int) -> None:
    """The reconstruction's distortion (with thin prism s1..s4) and its Jacobian against OpenCV."""
    rng = np.random.default_rng(300 + n_dist)
    for _ in range(MODELS):
        model = random_model(rng, n_dist)
        d = model.dist_padded(12)
        r = R_MAX * np.sqrt(rng.uniform(0, 1, 200))
        phi = rng.uniform(0, 2 * np.pi, 200)
        xn, yn = r * np.cos(phi), r * np.sin(phi)
        ours = np.array([distort_jac(x, y, d) for x, y in zip(xn, yn, strict=True)])
        cx, cy = _cv2_distort(model, xn, yn)
        f = model.K[0, 0]
        np.testing.assert_allclose(ours[:, 0] * f, cx * f, rtol=0, atol=PROJECT_TOL_PX)
        np.testing.assert_allclose(ours[:, 1] * f, cy * f, rtol=0, atol=PROJECT_TOL_PX)
        # the Jacobian against central differences of OpenCV's distortion
        h = 1e-6
        jx = (np.array(_cv2_distort(model, xn + h, yn)) - np.array(_cv2_distort(model, xn - h, yn))) / (2 * h)
        jy = (np.array(_cv2_distort(model, xn, yn + h)) - np.array(_cv2_distort(model, xn, yn - h))) / (2 * h)
        np.testing.assert_allclose(ours[:, 2], jx[0], rtol=0, atol=1e-6)
        np.testing.assert_allclose(ours[:, 3], jy[0], rtol=0, atol=1e-6)
        np.testing.assert_allclose(ours[:, 4], jx[1], rtol=0, atol=1e-6)
        np.testing.assert_allclose(ours[:, 5], jy[1], rtol=0, atol=1e-6)


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12])
def test_undistort_inverts_opencv_distortion(n_dist: int) -> None:
    rng = np.random.default_rng(400 + n_dist)
    worst = 0.0
    for _ in range(MODELS):
        model = random_model(rng, n_dist)
        xyz = points_in_view(model, rng)
        worst = max(worst, undistort_error_px(model, xyz, model.undistort_pixels))
        px = cv2_project(model, xyz)
        if n_dist:  # OpenCV's default of 5 iterations is coarser than the model's: iterate it to convergence
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
            ref = cv2.undistortPoints(px.reshape(-1, 1, 2), model.K, model.dist, R=None, P=None, criteria=crit)
            np.testing.assert_allclose(model.undistort_pixels(px) * model.K[0, 0],
                                       ref.reshape(-1, 2) * model.K[0, 0], rtol=0, atol=UNDISTORT_TOL_PX)
    print(f"{n_dist} coefficients: worst undistort error = {worst:.2e} px")
    assert worst < UNDISTORT_TOL_PX


@pytest.mark.parametrize("n_dist", [0, 8])
def test_skew(n_dist: int) -> None:
    """A skewed camera matrix (OpenCV's functions ignore K[0, 1]): u = fx xd + s yd + cx.

    Projection against OpenCV's skew-free projection plus the skew term; undistortion (the closed form
    without distortion, OpenCV with it) inverts it.
    """
    rng = np.random.default_rng(6 + n_dist)
    for _ in range(MODELS):
        plain = random_model(rng, n_dist)
        K = plain.K.copy()
        K[0, 1] = rng.uniform(-5, 5)
        skewed = CameraModel("cam", K, plain.dist, plain.width, plain.height, plain.R, plain.T)
        xyz = points_in_view(skewed, rng)
        ref = cv2_project(plain, xyz)
        ref[:, 0] += K[0, 1] * (ref[:, 1] - K[1, 2]) / K[1, 1]
        px, _ = skewed.project(xyz)
        np.testing.assert_allclose(px, ref, rtol=0, atol=PROJECT_TOL_PX)
        dev = skewed.to_device(xyz)
        np.testing.assert_allclose(skewed.undistort_pixels(ref) * K[0, 0], dev[:, :2] / dev[:, 2:] * K[0, 0],
                                   rtol=0, atol=UNDISTORT_TOL_PX)


# --- the comparisons catch a small error ------------------------------------------------------------------


def test_a_tenth_of_a_pixel_is_caught(monkeypatch: pytest.MonkeyPatch) -> None:
    """A model that is off by 0.1 px (projection) or 0.1 px (undistortion) fails the same comparisons."""
    rng = np.random.default_rng(7)
    model = random_model(rng, 8)
    xyz = points_in_view(model, rng)
    assert project_error_px(model, xyz) < PROJECT_TOL_PX
    original = CameraModel.distort_normalized

    def shifted(self: CameraModel, xn: F64, yn: F64) -> tuple[F64, F64]:
        xd, yd = original(self, xn, yn)
        return xd + 0.1 / self.K[0, 0], yd

    monkeypatch.setattr(CameraModel, "distort_normalized", shifted)
    assert project_error_px(model, xyz) == pytest.approx(0.1, abs=1e-6)
    monkeypatch.undo()
    assert undistort_error_px(model, xyz, lambda px: model.undistort_pixels(px + np.array([0.1, 0.0]))) > 0.05
    bad_dist = model.dist.copy()
    bad_dist[0] *= 1.001  # k1 off by 0.1 %
    wrong = CameraModel("cam", model.K, bad_dist, model.width, model.height, model.R, model.T)
    assert undistort_error_px(model, xyz, wrong.undistort_pixels) > UNDISTORT_TOL_PX


def test_undistort_inverts_the_model_where_it_can_and_is_nan_where_it_folds() -> None:
    """Strong barrel distortion (k1 = -0.6) folds over beyond r ~ 0.75: pixels the model reaches come back to
    1e-12 through the forward model; pixels past the fold (no undistorted point maps there) are NaN, not a
    wrong point."""
    cam = CameraModel("c", np.array([[800.0, 0, 640], [0, 800, 512], [0, 0, 1]]), np.array([-0.6, 0, 0, 0, 0]),
                      1280, 1024)  # fmt: skip
    rng = np.random.default_rng(3)
    ang, rad = rng.uniform(0, 2 * np.pi, 5000), 0.7 * np.sqrt(rng.uniform(0, 1, 5000))  # inside the fold
    und = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=1)
    xd, yd = cam.distort_normalized(und[:, 0], und[:, 1])
    px = np.stack([800 * xd + 640, 800 * yd + 512], axis=1)
    back = cam.undistort_pixels(px)
    np.testing.assert_allclose(back, und, atol=1e-11)
    # the largest distorted radius the model reaches: r_d(r) = r (1 - 0.6 r^2) peaks at r = 1 / sqrt(1.8)
    r_max = (1 / np.sqrt(1.8)) * (1 - 0.6 / 1.8)
    far = np.array([[640 + 800 * (r_max + 0.05), 512.0], [640.0, 512 - 800 * (r_max + 0.1)]])
    assert np.isnan(cam.undistort_pixels(far)).all()
