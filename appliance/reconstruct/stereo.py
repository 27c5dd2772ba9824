"""Camera-camera triangulation: match decoded projector codes between two cameras, then intersect rays.

Method
------
Both cameras are rectified once (per calibration) to a common orientation whose x axis is the baseline, so
that every epipolar plane is one rectified row ``b`` shared by both cameras. Per scan:

1. The code maps (u, and v when coded) of both cameras are resampled onto their rectified grids (bilinear,
   only where the four neighbours are decoded and agree within a few codes, i.e. not across an edge).
2. For every rectified row, a crossing table records the sub-pixel x where the code crosses each integer
   value (linear between pixels); an integer crossed twice in a row is marked ambiguous.
3. Every cam0 pixel keeps its own exact code and its exact rectified position (x0, b): its match is looked
   up on the (fractional) row b of cam1 by interpolating the crossing table between the integers around u
   and between the two rows around b: sub-pixel, no search. The match is rejected when:
   the code is ambiguous or absent; the crossing moves more than ``max_row_jump_px`` between the two rows;
   the same lookup on cam0's own rectified row does not come back to x0 within ``max_lr_px`` (left-right
   check: catches codes that appear twice); with v coded, cam1's v there differs from cam0's v by more than
   ``max_epipolar_px`` times the local dv/dy (i.e. the point where (u, v) match lies that far off the
   epipolar line); with a calibrated projector, the triangulated point does not project within
   ``max_code_err_px`` of the decoded code (a three-view check); or the depth is out of range.
4. The two rays are coplanar by construction, so they meet exactly: depth = baseline / disparity.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel
from appliance.geometry.rays import RayTable
from appliance.reconstruct import _tri_kernels as K
from appliance.reconstruct.triangulate import check_maps, check_out, distortion12
from appliance.reconstruct.types import DecodedMaps

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

CODE_OFFSET = 2
"""Integer codes from -2 up are tabulated."""


def _rect_coords(rot: F64, norm: F64) -> tuple[F64, F64]:
    """Rectified (a, b) of device-frame normalised coords (N, 2) under ``rot`` (device -> rect)."""
    p = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1) @ rot.T
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = p[:, 2] > 1e-9
        return np.where(ok, p[:, 0] / p[:, 2], np.nan), np.where(ok, p[:, 1] / p[:, 2], np.nan)


def _border_pixels(cam: CameraModel, n: int = 64) -> F64:
    w, h = cam.width - 1.0, cam.height - 1.0
    t = np.linspace(0.0, 1.0, n)
    return np.concatenate(
        [
            np.stack([t * w, 0 * t], 1),
            np.stack([t * w, 0 * t + h], 1),
            np.stack([0 * t, t * h], 1),
            np.stack([0 * t + w, t * h], 1),
        ]
    )


class StereoTriangulator:
    """Camera-camera triangulation for one camera pair; the rectification is built once, here.

    Parameters
    ----------
    cam0, cam1 : CameraModel
        The two cameras; output is organised for cam0's pixels, in the world frame.
    rays0 : RayTable, optional
        cam0's ray table, when already computed.
    max_epipolar_px : float
        With v coded: largest distance (rectified px) of the (u, v) match from the epipolar line.
    max_lr_px : float
        Left-right check: largest distance between a cam0 pixel and where its code lies on its own row (px).
    max_row_jump_px : float
        Largest change of a code's crossing between two neighbouring rectified rows (px).
    max_code_step : float
        Largest code change between neighbouring pixels still treated as one surface (projector px).
    max_code_gap_px : float
        Largest distance between the crossings of two consecutive integer codes (rectified px).
    projector : CameraModel, optional
        Calibrated projector for the three-view check.
    max_code_err_px : float
        Three-view check: largest |projected code - decoded code| (projector px).
    """

    def __init__(
        self,
        cam0: CameraModel,
        cam1: CameraModel,
        rays0: RayTable | None = None,
        max_epipolar_px: float = 1.5,
        max_lr_px: float = 1.0,
        max_row_jump_px: float = 2.0,
        max_code_step: float = 3.0,
        max_code_gap_px: float = 8.0,
        projector: CameraModel | None = None,
        max_code_err_px: float = 2.0,
    ) -> None:
        self.cam0, self.cam1, self.projector = cam0, cam1, projector
        self.rays0 = rays0 if rays0 is not None else RayTable(cam0)
        self.max_epipolar_px, self.max_lr_px, self.max_row_jump_px = (
            max_epipolar_px,
            max_lr_px,
            max_row_jump_px,
        )
        self.max_code_step, self.max_code_gap_px, self.max_code_err_px = (
            max_code_step,
            max_code_gap_px,
            max_code_err_px,
        )
        c0, c1 = cam0.center, cam1.center
        base = float(np.linalg.norm(c1 - c0))
        if base < 1e-6:
            raise CalibrationError(
                f"{cam0.name}/{cam1.name}: the cameras share one centre: no stereo baseline"
            )
        ex = (c1 - c0) / base
        zavg = cam0.R[2] + cam1.R[2]
        ez = zavg - (zavg @ ex) * ex
        if np.linalg.norm(ez) < 0.1 * np.linalg.norm(zavg):
            raise CalibrationError(f"{cam0.name}/{cam1.name}: the baseline runs along the viewing direction")
        ez /= np.linalg.norm(ez)
        rr = np.stack([ex, np.cross(ez, ex), ez])  # world -> rectified
        self._rr_t = np.ascontiguousarray(rr.T)
        rot0, rot1 = rr @ cam0.R.T, rr @ cam1.R.T  # device -> rectified
        step = 2.0 / (cam1.K[0, 0] + cam1.K[1, 1])
        h, w = self.rays0.shape
        a0, b0 = _rect_coords(rot0, self.rays0.normalized.reshape(-1, 2).astype(np.float64))
        a1, b1 = _rect_coords(rot1, cam1.undistort_pixels(_border_pixels(cam1)))
        if not (np.isfinite(a0).mean() > 0.5 and np.isfinite(a1).all()):
            raise CalibrationError(
                f"{cam0.name}/{cam1.name}: the cameras look more than 90 deg away from each other"
            )
        bmin = max(np.nanmin(b0), np.nanmin(b1)) - 2 * step
        bmax = min(np.nanmax(b0), np.nanmax(b1)) + 2 * step
        if bmax <= bmin:
            raise CalibrationError(
                f"{cam0.name}/{cam1.name}: the two views share no epipolar plane (no overlap)"
            )
        a0min, a0max = np.nanmin(a0) - 2 * step, np.nanmax(a0) + 2 * step
        a1min, a1max = np.nanmin(a1) - 2 * step, np.nanmax(a1) + 2 * step
        hr = math.ceil((bmax - bmin) / step) + 1
        wr0 = math.ceil((a0max - a0min) / step) + 1
        wr1 = math.ceil((a1max - a1min) / step) + 1
        big = 3 * max(cam0.width, cam0.height, cam1.width, cam1.height)
        if max(hr, wr0, wr1) > big:
            raise CalibrationError(
                f"{cam0.name}/{cam1.name}: rectified images would be {wr0}/{wr1}x{hr} px: views too oblique"
            )
        self._geom = np.array([a0min, a1min, bmin, step, base])
        self.rect_shape = (hr, wr0, wr1)
        k0, k1 = np.ascontiguousarray(cam0.K), np.ascontiguousarray(cam1.K)
        self._map0 = K.project_dirs(
            np.ascontiguousarray(rot0.T), a0min, bmin, step, hr, wr0, k0, distortion12(cam0)
        )
        self._map1 = K.project_dirs(
            np.ascontiguousarray(rot1.T), a1min, bmin, step, hr, wr1, k1, distortion12(cam1)
        )
        rect0 = np.empty((h, w, 2), np.float32)
        rect0[..., 0] = ((a0 - a0min) / step).reshape(h, w)
        rect0[..., 1] = ((b0 - bmin) / step).reshape(h, w)
        self._rect0 = rect0
        self._r0z = np.ascontiguousarray(cam0.R[2])
        self._t0z = float(cam0.T[2])
        self._c0 = c0
        if projector is not None:
            self._pr, self._pt = np.ascontiguousarray(projector.R), np.ascontiguousarray(projector.T)
            self._pk, self._pd = np.ascontiguousarray(projector.K), distortion12(projector)
        else:
            self._pr, self._pt, self._pk, self._pd = np.eye(3), np.zeros(3), np.eye(3), np.zeros(12)
        self._u0r = np.empty((hr, wr0), np.float32)
        self._u1r = np.empty((hr, wr1), np.float32)
        self._v1r = np.full((hr, wr1), np.nan, np.float32)
        self._cross0 = np.empty((hr, 0), np.float32)
        self._cross1 = np.empty((hr, 0), np.float32)

    def triangulate(
        self,
        maps0: DecodedMaps,
        maps1: DecodedMaps,
        out: F32 | None = None,
        min_depth_mm: float = 1e-6,
        max_depth_mm: float = math.inf,
    ) -> F32:
        """Match and triangulate.

        Parameters
        ----------
        maps0, maps1 : DecodedMaps
            Decoded projector codes of cam0 (H0, W0) and cam1 (H1, W1); v is used when decoded.
        out : ndarray, shape (H0, W0, 3), float32, optional
            Preallocated output.
        min_depth_mm, max_depth_mm : float
            Depth range (z in cam0's frame, mm).

        Returns
        -------
        ndarray, shape (H0, W0, 3), float32
            World-frame points (mm) organised by cam0 pixel; NaN where unmatched or rejected.
        """
        u0, v0, mask0 = check_maps(maps0, self.rays0.shape, self.cam0.name)
        u1, v1, mask1 = check_maps(maps1, (self.cam1.height, self.cam1.width), self.cam1.name)
        xyz = check_out(out, self.rays0.shape)
        use_v = bool(np.isfinite(v0[::7, ::7]).any() and np.isfinite(v1[::7, ::7]).any())
        hi = max(float(np.nanmax(u0, initial=0.0)), float(np.nanmax(u1, initial=0.0)))
        nk = math.ceil(hi) + CODE_OFFSET + 3
        if self._cross0.shape[1] < nk:
            hr = self.rect_shape[0]
            self._cross0 = np.empty((hr, nk), np.float32)
            self._cross1 = np.empty((hr, nk), np.float32)
        spread = 2.0 * self.max_code_step
        K.remap_codes(u0, mask0, self._map0, spread, self._u0r)
        K.remap_codes(u1, mask1, self._map1, spread, self._u1r)
        if use_v:
            K.remap_codes(v1, mask1, self._map1, spread, self._v1r)
        K.crossing_table(self._u0r, CODE_OFFSET, self.max_code_step, self._cross0)
        K.crossing_table(self._u1r, CODE_OFFSET, self.max_code_step, self._cross1)
        K.stereo_match(
            u0,
            v0,
            mask0,
            self._rect0,
            self._cross0,
            self._cross1,
            self._v1r,
            use_v,
            CODE_OFFSET,
            self._geom,
            self._rr_t,
            self._c0,
            self._r0z,
            self._t0z,
            self._pr,
            self._pt,
            self._pk,
            self._pd,
            self.projector is not None,
            self.max_code_err_px,
            self.max_code_gap_px,
            self.max_row_jump_px,
            self.max_lr_px,
            self.max_epipolar_px,
            max(float(min_depth_mm), 1e-6),
            float(max_depth_mm),
            xyz,
        )
        return xyz


def triangulate_stereo(
    maps0: DecodedMaps,
    maps1: DecodedMaps,
    cam0: CameraModel,
    cam1: CameraModel,
    max_epipolar_px: float = 1.5,
    projector: CameraModel | None = None,
    out: F32 | None = None,
    min_depth_mm: float = 1e-6,
    max_depth_mm: float = math.inf,
) -> F32:
    """Camera-camera triangulation in one call (builds a :class:`StereoTriangulator`: keep one instead).

    Parameters
    ----------
    maps0, maps1 : DecodedMaps
        Decoded codes of the two cameras.
    cam0, cam1 : CameraModel
        The cameras.
    max_epipolar_px : float
        With v coded: largest distance of the (u, v) match from the epipolar line (px).
    projector : CameraModel, optional
        Calibrated projector for the three-view consistency check.
    out : ndarray, shape (H0, W0, 3), float32, optional
        Output buffer.
    min_depth_mm, max_depth_mm : float
        Depth range in cam0's frame (mm).

    Returns
    -------
    ndarray, shape (H0, W0, 3), float32
        World-frame points (mm) organised by cam0 pixel, NaN where none.
    """
    tri = StereoTriangulator(cam0, cam1, max_epipolar_px=max_epipolar_px, projector=projector)
    return tri.triangulate(maps0, maps1, out, min_depth_mm, max_depth_mm)
