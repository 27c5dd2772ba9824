"""Reconstruction defaults that follow from a calibration's geometry (no constants tuned to one rig).

:func:`default_depth_range_mm` answers "which depths can this rig triangulate at all": the depths at which
a camera pixel's ray lies inside the other device's field of view (the projector, or the second camera)
with a triangulation angle of at least :data:`MIN_TRIANGULATION_ANGLE_DEG`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]

#: Below this angle between a camera ray and the other device's ray, depth is too poorly conditioned to use.
MIN_TRIANGULATION_ANGLE_DEG = 2.0
#: The depth range found is widened by this factor on both ends (calibration and sampling slack).
DEPTH_MARGIN = 0.1
#: Depths tried along each sampled ray, log-spaced (mm).
_DEPTH_SAMPLES_MM = np.geomspace(5.0, 200_000.0, 800)
#: Pixels sampled per image side.
_GRID = 21


def _grid_pixels(dev: CameraModel, n: int = _GRID) -> F64:
    xs = np.linspace(0.0, dev.width - 1.0, n)
    ys = np.linspace(0.0, dev.height - 1.0, n)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _border_box(dev: CameraModel) -> tuple[float, float, float, float]:
    """Bounding box (x0, x1, y0, y1) of the device's image border in undistorted normalised coordinates."""
    t = np.linspace(0.0, 1.0, 129)
    w, h = dev.width - 1.0, dev.height - 1.0
    border = np.concatenate([
        np.stack([t * w, np.zeros_like(t)], 1), np.stack([t * w, np.full_like(t, h)], 1),
        np.stack([np.zeros_like(t), t * h], 1), np.stack([np.full_like(t, w), t * h], 1),
    ])  # fmt: skip
    n = dev.undistort_pixels(border)
    return float(n[:, 0].min()), float(n[:, 0].max()), float(n[:, 1].min()), float(n[:, 1].max())


def visible_depths_mm(camera: CameraModel, other: CameraModel) -> tuple[float, float] | None:
    """Nearest and farthest camera depth (mm) at which ``camera`` and ``other`` can triangulate.

    Parameters
    ----------
    camera : CameraModel
        The camera whose depth (z in its own frame) is meant.
    other : CameraModel
        The projector or the second camera (same world frame).

    Returns
    -------
    (near, far) or None
        Depth interval (mm, camera frame) over which some camera pixel's ray is inside ``other``'s image
        with a triangulation angle >= :data:`MIN_TRIANGULATION_ANGLE_DEG`; None when there is none.
    """
    rays = camera.undistort_pixels(_grid_pixels(camera))  # (P, 2) normalised: the ray (x, y, 1)
    dirs = np.concatenate([rays, np.ones((rays.shape[0], 1))], axis=1)
    z = _DEPTH_SAMPLES_MM
    pts_cam = dirs[None, :, :] * z[:, None, None]  # (Z, P, 3) in the camera frame
    # camera frame -> world -> other
    world = (pts_cam - camera.T) @ camera.R  # R^T (p - T), row-vector form
    p_other = world @ other.R.T + other.T
    zo = p_other[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = p_other[..., 0] / zo
        yn = p_other[..., 1] / zo
    x0, x1, y0, y1 = _border_box(other)
    inside = (zo > 0) & (xn >= x0) & (xn <= x1) & (yn >= y0) & (yn <= y1)
    # triangulation angle between the camera ray and the ray from the other device's centre
    c_other = other.center
    v_cam = world - camera.center
    v_oth = world - c_other
    cosang = np.sum(v_cam * v_oth, axis=-1) / (
        np.linalg.norm(v_cam, axis=-1) * np.linalg.norm(v_oth, axis=-1)
    )
    angle_ok = cosang <= math.cos(math.radians(MIN_TRIANGULATION_ANGLE_DEG))
    good = np.any(inside & angle_ok, axis=1)
    if not np.any(good):
        return None
    idx = np.flatnonzero(good)
    return float(z[idx[0]]), float(z[idx[-1]])


def default_depth_range_mm(cameras: Iterable[CameraModel], others: Iterable[CameraModel]) -> tuple[float, float]:
    """Depth range (mm) that a reconstruction should keep when none is configured.

    Parameters
    ----------
    cameras : iterable of CameraModel
        The cameras whose depth maps are made (mode projector: every camera; stereo: the reference camera).
    others : iterable of CameraModel
        The devices they triangulate with (the projector, or the second camera).

    Returns
    -------
    (min_depth_mm, max_depth_mm)
        The union of :func:`visible_depths_mm` over every (camera, other) pair, widened by
        :data:`DEPTH_MARGIN`.

    Raises
    ------
    CalibrationError
        When no pair of devices sees a common volume (the poses in the calibration cannot be right).
    """
    others = list(others)
    near, far = math.inf, 0.0
    names: list[str] = []
    for cam in cameras:
        for oth in others:
            if oth is cam:
                continue
            names.append(f"{cam.name}-{oth.name}")
            r = visible_depths_mm(cam, oth)
            if r is not None:
                near, far = min(near, r[0]), max(far, r[1])
    if not far > 0.0:
        raise CalibrationError(
            f"calibration: {', '.join(names) or 'no device pair'}: no depth at which the devices see a common "
            f"volume with a triangulation angle >= {MIN_TRIANGULATION_ANGLE_DEG:g} deg; check the poses (R, T) "
            "or give reconstruction.min_depth_mm / max_depth_mm"
        )
    return near * (1.0 - DEPTH_MARGIN), far * (1.0 + DEPTH_MARGIN)
