"""Per-pixel ray tables, computed once per calibration."""

from __future__ import annotations

from functools import cached_property

import numpy as np
import numpy.typing as npt

from appliance.geometry.camera import CameraModel

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

ROW_TABLE_STEP = 8
"""Default row spacing of :meth:`RayTable.row_table` (px): cubic interpolation over 8 px rows is exact to
~2e-8 (normalised units, the float32 rounding of the table) for ordinary lens distortion."""


def catmull_rom(p0: F32, p1: F32, p2: F32, p3: F32, t: F64) -> F64:
    """Catmull-Rom cubic through p0..p3 (equally spaced) at ``t`` in [0, 1] between p1 and p2 (float64)."""
    a0, a1, a2, a3 = (np.asarray(p, np.float64) for p in (p0, p1, p2, p3))
    return a1 + 0.5 * t * (a2 - a0 + t * (2.0 * a0 - 5.0 * a1 + 4.0 * a2 - a3 + t * (3.0 * (a1 - a2) + a3 - a0)))


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
        self._normalized: F32 | None = self._compute()
        self.origin: F64 = camera.center
        self._row_tables: dict[int, tuple[F32, F32, float]] = {}

    def _compute(self) -> F32:
        camera = self.camera
        h, w = camera.height, camera.width
        norm = np.empty((h, w, 2), np.float32)
        xs = np.arange(w, dtype=np.float64)
        rows_per_chunk = max(1, 262144 // w)  # bounded temporaries for big sensors
        for r0 in range(0, h, rows_per_chunk):
            r1 = min(h, r0 + rows_per_chunk)
            gx, gy = np.meshgrid(xs, np.arange(r0, r1, dtype=np.float64))
            und = camera.undistort_pixels(np.stack([gx.ravel(), gy.ravel()], axis=1))
            norm[r0:r1] = und.reshape(r1 - r0, w, 2)
        return norm

    @property
    def normalized(self) -> F32:
        """The per-pixel table (see the class); computed again on first use after :meth:`release`."""
        if self._normalized is None:
            self._normalized = self._compute()
        return self._normalized

    def release(self) -> None:
        """Give back the per-pixel table (8 bytes a pixel, 10.5 MB at 1280x1024) where only the
        :meth:`row_table` is read per scan; the row tables already built are kept."""
        self._normalized = None

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the camera image."""
        return (self.camera.height, self.camera.width)

    def row_table(self, step: int = ROW_TABLE_STEP) -> tuple[F32, F32, float]:
        """The normalised coordinates of every ``step``-th pixel row, for cubic interpolation in between.

        A kernel rebuilds a row of rays from four table rows in cache instead of streaming
        :attr:`normalized` (8 bytes per pixel) from memory. Between table rows g and g + 1 the rays are
        the Catmull-Rom cubic through rows g - 1 .. g + 2.

        Parameters
        ----------
        step : int
            Row spacing of the table (px).

        Returns
        -------
        tx, ty : ndarray, shape ((H - 1) // step + 4, W), float32
            ``x/z`` and ``y/z`` of pixel rows ``-step, 0, step, 2 step, ...`` (table row k is pixel row
            ``(k - 1) * step``; the first and last two lie past the image, where the model extrapolates).
        max_error : float
            Largest difference of the interpolated rays from :attr:`normalized` (normalised units).
        """
        if step < 1:
            raise ValueError(f"step = {step}: must be >= 1 px")
        if step not in self._row_tables:
            h, w = self.shape
            n_rows = (h - 1) // step + 4
            tx = np.empty((n_rows, w), np.float32)
            ty = np.empty((n_rows, w), np.float32)
            xs = np.arange(w, dtype=np.float64)
            for k in range(n_rows):
                row = (k - 1) * step
                if 0 <= row < h:
                    tx[k], ty[k] = self.normalized[row, :, 0], self.normalized[row, :, 1]
                else:
                    und = self.camera.undistort_pixels(np.stack([xs, np.full(w, float(row))], axis=1))
                    tx[k], ty[k] = und[:, 0], und[:, 1]
            err = 0.0
            for r0 in range(0, h, 64):  # 64 rows at a time: float64 temporaries of a few MB, not ~100
                r = np.arange(r0, min(h, r0 + 64))
                g = r // step + 1
                t = ((r % step) / step)[:, None]
                for k, tab in enumerate((tx, ty)):
                    interp = catmull_rom(tab[g - 1], tab[g], tab[g + 1], tab[g + 2], t)
                    err = max(err, float(np.max(np.abs(interp - self.normalized[r0:r0 + r.size, :, k]))))
            self._row_tables[step] = (tx, ty, err)
        return self._row_tables[step]

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
