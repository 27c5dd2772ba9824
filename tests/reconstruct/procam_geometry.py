"""Exact camera-projector geometry for the triangulation tests: a camera and a projector with distortion,
surfaces cast through every camera pixel and their exact projector codes (``test_triangulate``,
``test_reconstruct_fused``)."""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt

from appliance.geometry.calibration_file import Calibration
from appliance.geometry.camera import CameraModel, look_at
from appliance.geometry.rays import RayTable
from appliance.reconstruct.triangulate import ProjectorTriangulator
from appliance.reconstruct.types import DecodedMaps

F64 = npt.NDArray[np.float64]
PLANE = ("plane", (np.array([0.0, 0.0, 600.0]), np.array([0.2, -0.1, -1.0])))
SPHERE = ("sphere", (np.array([10.0, -5.0, 560.0]), 60.0))
EXACT_TOL_MM = 0.005


def camera(name: str = "cam0", pose: tuple[F64, F64] | None = None) -> CameraModel:
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


def projector(
    offset: tuple[float, float, float], dist: tuple[float, ...] = (0.08, -0.05, -6e-4, 5e-4, 0.01)
) -> CameraModel:
    r, t = look_at(np.array(offset), np.array([0.0, 0.0, 575.0]))
    return CameraModel(
        "projector", [[1600, 0, 640.4], [0, 1600, 780.2], [0, 0, 1]], list(dist), 1280, 800, r, t
    )


@cache
def procam_rig(kind: str) -> tuple[CameraModel, CameraModel, RayTable]:
    """'h': 175 mm horizontal baseline, 'v': vertical, 'posed': camera not at the world origin."""
    if kind == "posed":
        cam = camera("cam1", look_at(np.array([-60.0, 20.0, -10.0]), np.array([0.0, 0.0, 590.0])))
        proj = projector((115.0, 20.0, 0.0))
    else:
        cam = camera()
        proj = projector((175.0, 0.0, 0.0) if kind == "h" else (0.0, 175.0, 0.0))
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
def true_points(kind: str, surface: str) -> F64:
    cam, _, _ = procam_rig(kind)
    return cast(cam, PLANE if surface == "plane" else SPHERE)


@cache
def triangulator(kind: str, axes: str) -> ProjectorTriangulator:
    cam, proj, rays = procam_rig(kind)
    return ProjectorTriangulator(cam, proj, axes, rays)


@cache
def two_camera_calibration() -> Calibration:
    cam0 = camera()
    cam1 = camera("cam1", look_at(np.array([200.0, 5.0, 3.0]), np.array([30.0, 0.0, 575.0])))
    return Calibration({"cam0": cam0, "cam1": cam1, "projector": projector((100.0, -30.0, 0.0))})
