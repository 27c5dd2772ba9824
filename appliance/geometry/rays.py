"""Per-pixel ray tables, computed once per calibration."""

from __future__ import annotations

from functools import cached_property

import numpy as np
import numpy.typing as npt

from appliance.geometry.camera import CameraModel

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


class RayTable:
    """The viewing ray of every pixel of one camera.

    Parameters
    ----------
    camera : CameraModel
        The camera; its distortion is inverted once here (``CameraModel.undistort_pixels``, 1e-12).

    Attributes
    ----------
    camera : CameraModel
    normalized : ndarray, shape (H, W, 2), float32
        Undistorted normalised coordinates ``(x/z, y/z)`` of each pixel centre in the camera frame; the
        ray of pixel (row, col) in the camera frame is ``(nx, ny, 1)`` scaled by its depth z (mm).
    origin : ndarray, shape (3,), float64
        Optical centre in the world frame (mm).
    """

    def __init__(self, camera: CameraModel) -> None:
        self.camera = camera
        h, w = camera.height, camera.width
        norm = np.empty((h, w, 2), np.float32)
        xs = np.arange(w, dtype=np.float64)
        rows_per_chunk = max(1, 262144 // w)  # bounded temporaries for big sensors
        for r0 in range(0, h, rows_per_chunk):
            r1 = min(h, r0 + rows_per_chunk)
            gx, gy = np.meshgrid(xs, np.arange(r0, r1, dtype=np.float64))
            und = camera.undistort_pixels(np.stack([gx.ravel(), gy.ravel()], axis=1))
            norm[r0:r1] = und.reshape(r1 - r0, w, 2)
        self.normalized: F32 = norm
        self.origin: F64 = camera.center

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the camera image."""
        return (self.camera.height, self.camera.width)

    @cached_property
    def dirs(self) -> F32:
        """Unit ray directions in the world frame, shape (H, W, 3), float32 (computed on first use)."""
        h, w = self.shape
        d = np.empty((h, w, 3), np.float32)
        rt = self.camera.R.T.astype(np.float32)  # device -> world rotation
        n = self.normalized
        for k in range(3):
            d[..., k] = rt[k, 0] * n[..., 0] + rt[k, 1] * n[..., 1] + rt[k, 2]
        d /= np.sqrt(np.einsum("hwk,hwk->hw", d, d))[..., None]
        return d
