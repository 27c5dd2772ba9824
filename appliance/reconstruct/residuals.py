"""What the redundancy in one scan says about the calibration: residuals of overdetermined measurements.

A reconstruction is overdetermined wherever the scan measures more than a point needs:

* ``ray_ray`` — one camera, both projector axes coded: the camera ray and the projector ray of (u, v) must
  meet. The point is the least-squares compromise; its reprojection into the projector misses (u, v) by the
  residual (projector px), which is the calibration's error across the epipolar line plus code noise.
* ``epipolar`` — two cameras with rows coded: the (u, v) match must lie on the epipolar row (rectified px).
* ``three_view`` — two cameras and a calibrated projector: the camera-camera point must project onto its
  own code (projector px).

Each residual is summarised robustly (median of the magnitude, a robust sigma, the count) and turned into mm
at the scene (px times the pixel footprint at the measured depth), so that it can be compared with what the
calibration promised (its stated reprojection RMS). Evaluating that comparison and its trend is the
calibration's business (:mod:`appliance.calibration.health`); this module only measures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.geometry.camera import CameraModel

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

STRIDE = 4
"""Every STRIDE-th pixel of each row and column is sampled (a residual needs thousands, not millions)."""
MIN_SAMPLES = 100
"""Fewer samples than this make no residual."""


@dataclass(frozen=True)
class Residual:
    """A robust summary of one kind of residual in one scan.

    Attributes
    ----------
    kind : {'ray_ray', 'epipolar', 'three_view'}
        What was overdetermined (see the module notes).
    devices : str
        The devices involved, e.g. ``'cam0/projector'``.
    median_px : float
        Median of the signed residual (px of the device it is measured in): a calibration that drifted
        shifts it.
    abs_median_px : float
        Median of the residual's magnitude (px).
    sigma_px : float
        Robust standard deviation about the median (1.4826 x MAD, px).
    rms_px : float
        Robust RMS, ``sqrt(median^2 + sigma^2)`` (px): what to compare with a calibration's stated RMS.
    rms_mm : float
        The same at the scene (mm): px times the pixel footprint at the median depth.
    samples : int
        Number of residuals.
    values_px : ndarray, shape (samples,), float64
        The residuals themselves (px), for judging them (:mod:`appliance.calibration.health`).
    mm_per_px : float
        Pixel footprint at the scene (mm per px).
    """

    kind: str
    devices: str
    median_px: float
    abs_median_px: float
    sigma_px: float
    rms_px: float
    rms_mm: float
    samples: int
    values_px: F64 = field(repr=False, default_factory=lambda: np.zeros(0))
    mm_per_px: float = math.nan

    def as_dict(self) -> dict[str, object]:
        """JSON-ready form (without the values)."""
        return {"kind": self.kind, "devices": self.devices, "median_px": self.median_px,
                "abs_median_px": self.abs_median_px, "sigma_px": self.sigma_px, "rms_px": self.rms_px,
                "rms_mm": self.rms_mm, "samples": self.samples}  # fmt: skip


def summarise(
    kind: str, devices: str, residual_px: npt.NDArray[np.floating[Any]], mm_per_px: float
) -> Residual | None:
    """Robust summary of signed residuals (px); None when fewer than :data:`MIN_SAMPLES` are finite.

    Parameters
    ----------
    kind, devices : str
        See :class:`Residual`.
    residual_px : ndarray, shape (N,), float32 or float64
        Signed residuals (px); NaN entries are ignored.
    mm_per_px : float
        Pixel footprint at the scene (mm per px) for ``rms_mm``.
    """
    r = np.asarray(residual_px, np.float64)
    r = r[np.isfinite(r)]
    if r.size < MIN_SAMPLES:
        return None
    med = float(np.median(r))
    sig = 1.4826 * float(np.median(np.abs(r - med)))
    rms = math.hypot(med, sig)
    return Residual(kind, devices, med, float(np.median(np.abs(r))), sig, rms, rms * mm_per_px, int(r.size), r,
                    float(mm_per_px))  # fmt: skip


def decoded_ray_ray_residual(
    u: F32,
    v: F32,
    normalized: F32,
    camera: CameraModel,
    projector: CameraModel,
    stride: int = STRIDE,
) -> Residual | None:
    """Projector reprojection residual across the epipolar line, of every decoded pixel with (u, v) coded,
    whether or not it gave a point.

    Each sampled pixel's point is where its camera ray passes closest to the projector ray of its decoded
    (u, v), so the calibration is judged on all the light the pattern put on the scene, before any check or
    filter chose among the pixels. A calibration that no longer fits moves most pixels off their epipolar
    lines, and judging only the pixels a per-pixel epipolar check kept would hide it (a projector moved 0.5 mm:
    49 % dropped, the rest scattered, 304 samples left); the robust summary (median and MAD,
    :func:`summarise`) keeps reflections, a minority of the pixels, from reading as a bad calibration.

    Parameters
    ----------
    u, v : ndarray, shape (H, W), float32
        Decoded projector coordinates (px), NaN where not decoded.
    normalized : ndarray, shape (H, W, 2), float32
        The camera's undistorted normalised ray of each pixel.
    camera, projector : CameraModel
        The calibrated camera and projector.
    stride : int
        Sampling of rows and columns.

    Returns
    -------
    Residual or None
        ``kind='ray_ray'``: the signed distance (projector px) of the decoded (u, v) from the epipolar line
        of the camera pixel, i.e. the part of the reprojection error that no depth can explain; None when
        fewer than :data:`MIN_SAMPLES` sampled pixels decoded.
    """
    uu = u[::stride, ::stride].astype(np.float64)
    vv = v[::stride, ::stride].astype(np.float64)
    ok = np.isfinite(uu) & np.isfinite(vv)
    if int(ok.sum()) < MIN_SAMPLES:
        return None
    n = normalized[::stride, ::stride][ok].astype(np.float64)
    ones = np.ones((n.shape[0], 1))
    dc = np.concatenate([n, ones], axis=1) @ camera.R  # world direction of the camera ray (device z = 1)
    pn = projector.undistort_pixels(np.stack([uu[ok], vv[ok]], axis=1))
    dp = np.concatenate([pn, ones], axis=1) @ projector.R
    w0 = camera.center - projector.center
    a = np.einsum("ij,ij->i", dc, dc)
    b = np.einsum("ij,ij->i", dc, dp)
    c = np.einsum("ij,ij->i", dp, dp)
    d = dc @ w0
    e = dp @ w0
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (b * e - c * d) / (a * c - b * b)  # camera ray parameter = depth along the camera's z (mm)
    z[~(z > 0)] = np.nan
    good = np.isfinite(z)
    if int(good.sum()) < MIN_SAMPLES:
        return None
    return _across_epipolar(z[good], n[good], uu[ok][good], vv[ok][good], camera, projector)


def _across_epipolar(
    zc: npt.NDArray[np.float64],
    n: npt.NDArray[np.float64],
    uu: npt.NDArray[np.float64],
    vv: npt.NDArray[np.float64],
    camera: CameraModel,
    projector: CameraModel,
) -> Residual | None:
    """Signed distance (projector px) of the decoded (uu, vv) from the epipolar line of each camera point
    (depth ``zc`` mm along normalised ray ``n``), summarised."""
    pc = np.stack([n[:, 0] * zc, n[:, 1] * zc, zc], axis=1)  # camera frame
    world = (pc - camera.T) @ camera.R  # x_dev = R x_world + T
    near, _ = projector.project(world)
    far, _ = projector.project(world + 50.0 * (world - camera.center) / np.linalg.norm(world - camera.center,
                                                                                       axis=1, keepdims=True))
    # the epipolar line of the pixel in the projector runs from near to far: residual across it
    dd = far - near
    length = np.linalg.norm(dd, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        across = ((uu - near[:, 0]) * dd[:, 1] - (vv - near[:, 1]) * dd[:, 0]) / length
    footprint = float(np.median(zc)) / float(projector.K[0, 0]) if projector.K[0, 0] > 0 else math.nan
    return summarise("ray_ray", f"{camera.name}/{projector.name}", across, footprint)
