"""Camera-projector triangulation over precomputed tables.

Method
------
Everything is solved along the camera ray of each pixel, whose undistorted direction ``(nx, ny, 1)`` comes
from a :class:`~appliance.geometry.rays.RayTable` (camera frame, so the unknown is the depth z directly).

* One coded axis (``'x'`` columns or ``'y'`` rows), ray / light-surface: under projector distortion the set
  of points lit by projector column u is a curved surface, not a plane. Its intersection with the camera
  ray is found exactly in the projector's normalised (undistorted) image plane: the ray images there as a
  straight epipolar line through the epipole (the camera centre seen from the projector). Every epipolar
  line is named by one number, its intercept c on the projector's axis ``x = 0`` (``y = 0`` for rows), which
  is computed once per pixel. A table, built once by Newton's method on the full distortion model, holds
  for a grid of c (every 2 projector px) and every projector column (-2 .. W+1) the undistorted x on line c
  whose *distorted* column is that code. Per pixel the kernel interpolates the table bilinearly at (c, u)
  and intersects the camera ray with the plane through the projector centre at that x: two multiply-adds
  and one division, no iteration, no Python per pixel.
* Both axes (``'xy'``), ray-ray: (u, v) is undistorted by bilinear lookup in a per-projector-pixel table
  followed by one Newton step on the distortion model (exact to ~1e-12); the depth minimises the
  linearised projector reprojection error in pixels (least squares over the two equations), i.e. the
  point of the camera ray nearest to the coded projector ray, weighted by fx and fy.

Epipolar check (both axes): a direct reflection's (u, v) lies on the pixel's epipolar line in the projector
up to the code noise, so a pixel whose least-squares residual across it exceeds ``sqrt((5 sigma_u)^2 +
(0.5 px)^2)`` gives no point (reason ``EPIPOLAR``): a mirror-like surface re-projects the pattern as a second,
virtual projector whose codes generally miss the real one's lines. It cannot see a ghost whose code happens to
lie on the line: where the mirror maps an epipolar plane onto itself (a mirror whose normal is perpendicular
to the baseline's epipolar plane through it), or a blend of the direct and the mirrored pattern that shifts u
and v alike. With one coded axis nothing can be checked: every code defines a light surface that every
camera ray meets, so a ghost is a point on the ray like any other (only the depth range, the neighbour
filter and the decoder's Gray-against-phase check can drop it). When the check would drop most of a camera's
pixels the pipeline reruns without it: that is a calibration that no longer fits, for the health to judge.

Residual error (with exact codes): the table interpolation error is measured when the table is built
(:attr:`ProjectorTriangulator.table_error`, normalised units; the depth error is about
``z**2 / baseline_mm * table_error``, e.g. 1e-8 -> 2e-5 mm at 600 mm and 175 mm baseline), plus float32
rounding of the inputs (u to ~6e-5 px at 1000 px, i.e. ~1e-4 mm there). Tests hold it under 0.005 mm.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel
from appliance.geometry.rays import ROW_TABLE_STEP, RayTable
from appliance.reconstruct import _procam_kernels as K
from appliance.reconstruct.types import DecodedMaps, PointCloud, Reason
from appliance.reconstruct.uncertainty import CodeNoise, fringe_variance_table

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

CODE_MARGIN_PX = 2
"""Decoded codes may lie this far outside the projector image (px) and still triangulate."""
LINE_STEP_PX = 2.0
"""Spacing of the epipolar-line grid of the single-axis table (projector px)."""
MIN_LINE_SIN = 0.1
"""A pixel whose epipolar line meets the coded lines at less than asin(0.1) ~ 6 deg is left out."""
EPIPOLAR_SIGMAS = 5.0
"""Both axes coded: a pixel whose (u, v) lies farther off its epipolar line than this many code sigmas (and
:data:`EPIPOLAR_FLOOR_PX`) gives no point (reason ``EPIPOLAR``): its light came another way, e.g. a mirror-like
surface re-projecting the pattern. On the default virtual scene coded on both axes the largest residual is
3.2 sigma (p99.9), so 5 sigma drops no right point there."""
EPIPOLAR_FLOOR_PX = 0.5
"""Smallest epipolar limit (projector px), added in quadrature to the sigmas: room for a real calibration's
error across the epipolar lines (the calibration-health tolerance is 0.6 px), so that a well-lit pixel with
a tiny code sigma is not dropped for the calibration's residual."""


def relative_pose(camera: CameraModel, other: CameraModel) -> tuple[F64, F64]:
    """Pose of ``other`` relative to ``camera``: ``x_other = R @ x_camera + T`` (mm)."""
    r = other.R @ camera.R.T
    return r, other.T - r @ camera.T


def distortion12(model: CameraModel) -> F64:
    """The model's distortion padded to the 12 coefficients the kernels use (tilt is unsupported)."""
    if model.dist.size > 12:
        raise CalibrationError(
            f"{model.name}: {model.dist.size} distortion coefficients (tilted sensor model): triangulation "
            "supports at most 12 (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4); "
            "recalibrate without CALIB_TILTED_MODEL"
        )
    return model.dist_padded(12)


def check_maps(
    maps: DecodedMaps, shape: tuple[int, int], name: str, need_v: bool = True
) -> tuple[F32, F32, npt.NDArray[np.bool_]]:
    """C-contiguous float32 u, v and bool mask of ``maps``, checked against the camera's (H, W).

    With ``need_v`` False, v is returned as given (it may be a read-only broadcast NaN map).
    """
    if maps.shape != shape or maps.u.shape != shape or maps.v.shape != shape:
        raise ValueError(f"{name}: decoded maps are {maps.u.shape}, camera is {shape} (H, W): must match")
    u = np.ascontiguousarray(maps.u, dtype=np.float32)
    v = np.ascontiguousarray(maps.v, dtype=np.float32) if need_v else maps.v
    return u, v, np.ascontiguousarray(maps.mask, dtype=np.bool_)


def check_out(out: F32 | None, shape: tuple[int, int]) -> F32:
    """A (H, W, 3) float32 C-contiguous output buffer (allocated when ``out`` is None)."""
    if out is None:
        return np.empty((*shape, 3), np.float32)
    if out.shape != (*shape, 3) or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(
            f"out: {out.shape} {out.dtype}: must be a C-contiguous float32 array of {(*shape, 3)}"
        )
    return out


class ProjectorTriangulator:
    """Camera-projector triangulation for one camera; every table is built once, here.

    Parameters
    ----------
    camera : CameraModel
        The camera (any pose; output is in the world frame).
    projector : CameraModel
        The projector as an inverse camera.
    axes : {'x', 'y', 'xy'}
        Coded projector axes: ``'x'`` columns (ray / light-surface), ``'y'`` rows, ``'xy'`` ray-ray.
    rays : RayTable, optional
        The camera's ray table, when it is already computed.
    like : ProjectorTriangulator, optional
        Another camera's triangulator of the same projector: its projector table (both axes coded: 8 bytes
        per projector pixel) is shared, not built again.

    Raises
    ------
    CalibrationError
        When the geometry cannot triangulate the coded axis (e.g. rows coded with a horizontal baseline).
    """

    def __init__(
        self,
        camera: CameraModel,
        projector: CameraModel,
        axes: str,
        rays: RayTable | None = None,
        like: ProjectorTriangulator | None = None,
    ) -> None:
        if axes not in ("x", "y", "xy"):
            raise ValueError(f"axes = {axes!r}: must be 'x', 'y' or 'xy'")
        self.camera = camera
        self.projector = projector
        self.axes = axes
        self.rays = rays if rays is not None else RayTable(camera)
        if self.rays.shape != (camera.height, camera.width):
            raise ValueError(
                f"rays: table is {self.rays.shape}, camera {camera.name} is {camera.height}x{camera.width}"
            )
        self._rcp, self._tcp = relative_pose(camera, projector)
        self._rwc = np.ascontiguousarray(camera.R.T)
        self._cwc = camera.center
        self._to_world = not (
            np.allclose(camera.R, np.eye(3), atol=1e-12) and np.allclose(camera.T, 0, atol=1e-9)
        )
        self._kp = np.ascontiguousarray(projector.K)
        self._dp = distortion12(projector)
        self._fringe_hist = np.zeros(256, np.int64)
        self.table_error = 0.0
        """Largest interpolation error of the code table, normalised projector units (measured)."""
        if axes == "xy" and like is not None and like.projector is projector and like.axes == "xy":
            self._und: F32 = like._und
            self._origin: float = like._origin
        elif axes == "xy":
            self._build_undistort_table()
        else:
            self._build_line_table(0 if axes == "x" else 1)

    # --- tables -----------------------------------------------------------------------------------------

    def _build_undistort_table(self) -> None:
        p, m = self.projector, CODE_MARGIN_PX
        gx, gy = np.meshgrid(
            np.arange(-m, p.width + m, dtype=np.float64), np.arange(-m, p.height + m, dtype=np.float64)
        )
        und = p.undistort_pixels(np.stack([gx.ravel(), gy.ravel()], axis=1))
        self._und = np.ascontiguousarray(und.reshape(gx.shape[0], gx.shape[1], 2), dtype=np.float32)
        self._origin = float(-m)

    def _build_line_table(self, axis: int) -> None:
        p = self.projector
        raw = K.epipolar_intercepts(self.rays.normalized, self._rcp, self._tcp, 0.0, 1.0, axis, MIN_LINE_SIN)
        finite = np.isfinite(raw)
        if finite.mean() < 0.5:
            raise CalibrationError(
                f"{self.camera.name}/{p.name}: axis {self.axes!r}: the epipolar lines of "
                f"{100 * (1 - finite.mean()):.0f}% of the pixels run along the coded projector "
                f"{'columns' if axis == 0 else 'rows'}: the baseline has no component across them; "
                f"code the other axis or both ('xy')"
            )
        f = p.K[1, 1] if axis == 0 else p.K[0, 0]
        step = LINE_STEP_PX / f
        lo = float(raw[finite].min()) - 2 * step
        hi = float(raw[finite].max()) + 2 * step
        n_lines = math.ceil((hi - lo) / step) + 1
        if n_lines > 20000:
            raise CalibrationError(
                f"{self.camera.name}/{p.name}: epipolar lines span {hi - lo:.3g}: geometry is degenerate"
            )
        c_grid = lo + step * np.arange(n_lines)
        n_codes = (p.width if axis == 0 else p.height) + 2 * CODE_MARGIN_PX
        self._code0 = float(-CODE_MARGIN_PX)
        code_grid = self._code0 + np.arange(n_codes, dtype=np.float64)
        self._table = K.code_line_table(c_grid, code_grid, self._kp, self._dp, self._tcp, axis)
        self._c_lo, self._inv_dc = lo, 1.0 / step
        raw -= np.float32(lo)
        raw *= np.float32(1.0 / step)
        self._cidx = raw
        # measure the bilinear interpolation error at cell centres (a sample of columns)
        c_mid = c_grid[:-1] + step / 2
        sel = np.arange(0, n_codes - 1, 7)
        exact = K.code_line_table(c_mid, code_grid[sel] + 0.5, self._kp, self._dp, self._tcp, axis).astype(
            np.float64
        )
        t = self._table.astype(np.float64)
        interp = 0.25 * (t[:-1, sel] + t[:-1, sel + 1] + t[1:, sel] + t[1:, sel + 1])
        err = np.abs(interp - exact)
        self.table_error = float(np.nanmax(err)) if np.isfinite(err).any() else 0.0

    # --- per scan ---------------------------------------------------------------------------------------

    def triangulate(
        self,
        maps: DecodedMaps,
        out: F32 | None = None,
        min_depth_mm: float = 1e-6,
        max_depth_mm: float = math.inf,
    ) -> F32:
        """Triangulate every decoded pixel.

        Parameters
        ----------
        maps : DecodedMaps
            Decoded projector coordinates of this camera, shape (H, W); NaN or ``mask`` False = no point.
        out : ndarray, shape (H, W, 3), float32, optional
            Preallocated output (C-contiguous); allocated when None.
        min_depth_mm, max_depth_mm : float
            Depth range (z in this camera's frame, mm); points outside are NaN.

        Returns
        -------
        ndarray, shape (H, W, 3), float32
            World-frame points (mm), organised by camera pixel; NaN where there is no point.
        """
        shape = self.rays.shape
        u, v, mask = check_maps(maps, shape, self.camera.name, need_v=self.axes != "x")
        xyz = check_out(out, shape)
        zmin, zmax = max(float(min_depth_mm), 1e-6), float(max_depth_mm)
        if self.axes == "xy":
            K.tri_ray(
                u,
                v,
                mask,
                self.rays.normalized,
                self._und,
                self._origin,
                self._kp,
                self._dp,
                self._rcp,
                self._tcp,
                self._rwc,
                self._cwc,
                self._to_world,
                zmin,
                zmax,
                xyz,
            )
        else:
            axis = 0 if self.axes == "x" else 1
            K.tri_plane(
                u if axis == 0 else v,
                mask,
                self.rays.normalized,
                self._cidx,
                self._table,
                self._code0,
                self._rcp,
                self._tcp,
                self._rwc,
                self._cwc,
                self._to_world,
                zmin,
                zmax,
                axis,
                xyz,
            )
        return xyz

    # --- fused path: depth map with the neighbour filter, then the kept points -------------------------

    def triangulate_depth(
        self,
        maps: DecodedMaps,
        out: F32 | None = None,
        min_depth_mm: float = 1e-6,
        max_depth_mm: float = math.inf,
        min_neighbours: int = 0,
        max_jump_mm: float = math.inf,
        counts: npt.NDArray[np.int64] | None = None,
        *,
        noise: CodeNoise | None = None,
        white: npt.NDArray[np.generic] | None = None,
        sigma_out: F32 | None = None,
        jump_footprints: float = 0.0,
        jump_sigmas: float = 0.0,
        max_sigma_mm: float = math.inf,
        stats: npt.NDArray[np.int64] | None = None,
        spans: npt.NDArray[np.int64] | None = None,
        reason_out: npt.NDArray[np.uint8] | None = None,
        epipolar_sigmas: float = EPIPOLAR_SIGMAS,
        epipolar_floor_px: float = EPIPOLAR_FLOOR_PX,
    ) -> tuple[F32, npt.NDArray[np.int64]]:
        """Triangulate every decoded pixel to its depth and 1-sigma error, dropping isolated points, in one pass.

        Same geometry as :meth:`triangulate`, but rays come from the camera's coarse
        :meth:`~appliance.geometry.rays.RayTable.row_table` and only the depth is written (4 bytes per
        pixel instead of 12); :meth:`write_points` turns it into points. The filter is that of
        :func:`~appliance.reconstruct.filters.filter_isolated` (3-D distances, in the camera frame), with a
        limit per point: a neighbour counts when nearer than the mean of the two points' limits
        ``max_jump_mm + jump_footprints * z / fx + jump_sigmas * sigma``.

        The sigma of a point is its code noise (:class:`~appliance.reconstruct.uncertainty.CodeNoise`,
        from the pixel's quality) times the derivative of the triangulated point along its ray with
        respect to the code: for one axis ``dz/dq dq/du`` of the ray / light-surface intersection, for both
        ``Zp / |a|`` of the linearised least squares (equal, independent errors on u and v).

        With both axes coded the scan is overdetermined: a direct reflection's (u, v) lies on the pixel's
        epipolar line in the projector, up to the code noise. A pixel whose least-squares residual across
        that line (projector px) exceeds ``sqrt((epipolar_sigmas * sigma_u)^2 + epipolar_floor_px^2)``
        (``sigma_u`` the code's 1-sigma error per axis) gives no point: a second copy of the pattern, e.g.
        reflected by a mirror-like surface, comes from a virtual projector whose codes generally violate the
        real projector's epipolar geometry (never where the mirror maps an epipolar plane onto itself, so not
        every ghost). Without a noise model nothing is dropped; one coded axis has nothing to check (every
        code meets every ray).

        Parameters
        ----------
        maps : DecodedMaps
            Decoded projector coordinates of this camera, shape (H, W).
        out : ndarray, shape (H, W), float32, optional
            Preallocated C-contiguous depth map; allocated when None.
        min_depth_mm, max_depth_mm : float
            Depth range (mm).
        min_neighbours : int
            0..8: a point is kept when this many of its 8 neighbours lie within its jump limit.
        max_jump_mm : float
            Constant part of the jump limit (mm).
        counts : ndarray, shape (H + 1,), int64, optional
            Receives ``counts[r + 1]`` = kept points of row r (``counts[0]`` = 0); allocated when None.
        noise : CodeNoise, optional
            Code noise model; None: sigma is NaN (unknown), and so are limits that depend on it.
        white : ndarray, shape (H, W), optional
            Image under white light (DN of the decoded data), for the shot noise; else ``quality / 2``.
        sigma_out : ndarray, shape (H, W), float32, optional
            Receives the 1-sigma error (mm, along the ray) of every kept point, NaN elsewhere.
        jump_footprints, jump_sigmas : float
            Per-point parts of the jump limit: pixel footprints ``z / fx`` (mm) and sigmas.
        max_sigma_mm : float
            Points whose sigma exceeds this are dropped (after the neighbour filter, so that they still
            support their neighbours).
        stats : ndarray, shape (H, 6), int64, optional
            Receives per row the decoded, triangulated, epipolar-consistent, in-range, with-neighbours and
            kept counts.
        spans : ndarray, shape (H, 2), int64, optional
            Receives per row the columns (first, last + 1) that may hold points (for :meth:`write_points`).
        reason_out : ndarray, shape (H, W), uint8, optional
            Receives every pixel's :class:`~appliance.reconstruct.types.Reason`: the decoder's
            (``maps.reason``; ``WEAK_CODE`` where it has none) on pixels it did not decode, and on decoded
            ones ``DECODED`` (a point), ``OUT_OF_RANGE``, ``EPIPOLAR`` or ``FILTERED``. May be ``maps.reason``.
        epipolar_sigmas, epipolar_floor_px : float
            The epipolar limit (see above; ``inf`` turns the check off).

        Returns
        -------
        depth : ndarray, shape (H, W), float32
            Depth z in this camera's frame (mm) of every kept point, NaN elsewhere.
        counts : ndarray, shape (H + 1,), int64
            Kept points per row (see above).
        """
        shape = self.rays.shape
        if not 0 <= min_neighbours <= 8:
            raise ValueError(f"min_neighbours = {min_neighbours}: must be 0..8")
        u, v, mask = check_maps(maps, shape, self.camera.name, need_v=self.axes != "x")
        if self.axes == "x":
            v = u  # not read
        depth = check_depth(out, shape)
        sigma = check_depth(sigma_out, shape)
        if counts is None:
            counts = np.empty(shape[0] + 1, np.int64)
        elif counts.shape != (shape[0] + 1,) or counts.dtype != np.int64:
            raise ValueError(f"counts: {counts.shape} {counts.dtype}: must be int64 {(shape[0] + 1,)}")
        if stats is None:
            stats = np.empty((shape[0], 6), np.int64)
        elif stats.shape != (shape[0], 6) or stats.dtype != np.int64 or not stats.flags.c_contiguous:
            raise ValueError(f"stats: {stats.shape} {stats.dtype}: must be C-contiguous int64 {(shape[0], 6)}")
        if spans is None:
            spans = np.empty((shape[0], 2), np.int64)
        elif spans.shape != (shape[0], 2) or spans.dtype != np.int64 or not spans.flags.c_contiguous:
            raise ValueError(f"spans: {spans.shape} {spans.dtype}: must be C-contiguous int64 {(shape[0], 2)}")
        quality, wimg = self._noise_inputs(maps, white, shape)
        params = noise.params() if noise is not None else np.array([np.nan, np.nan, 0.0, 0.0])
        jump = np.array([max_jump_mm, jump_footprints, jump_sigmas], np.float64)
        if not (epipolar_sigmas >= 0 and epipolar_floor_px >= 0):
            raise ValueError(f"epipolar_sigmas = {epipolar_sigmas}, epipolar_floor_px = {epipolar_floor_px}: "
                             "must be >= 0")  # fmt: skip
        epi = np.array([epipolar_sigmas**2, epipolar_floor_px**2, float(self.axes == "xy")], np.float64)
        if math.isinf(epipolar_sigmas) or math.isinf(epipolar_floor_px):
            epi[2] = 0.0
        reason = _reason_buffer(reason_out, maps, mask, shape)
        tx, ty, _ = self.rays.row_table()
        zmin, zmax = max(float(min_depth_mm), 1e-6), float(max_depth_mm)
        ray = self.axes == "xy"
        axis = 1 if self.axes == "y" else 0
        if ray:
            table, code0, c_lo, inv_dc = np.zeros((2, 2), np.float32), 0.0, 0.0, 1.0
            und, origin = self._und, self._origin
        else:
            table, code0, c_lo, inv_dc = self._table, self._code0, self._c_lo, self._inv_dc
            und, origin = np.zeros((2, 2, 2), np.float32), 0.0
        p = K.DepthParams(
            has_w=white is not None, step=int(ROW_TABLE_STEP), ray=bool(ray), code0=float(code0), c_lo=float(c_lo),
            inv_dc=float(inv_dc), min_sin=float(MIN_LINE_SIN), origin=float(origin), axis=int(axis), zmin=zmin,
            zmax=zmax, max_sigma=float(max_sigma_mm), inv_f=1.0 / float(self.camera.K[0, 0]),
            min_nb=int(min_neighbours), nchunks=int(_chunks(shape[0])), nthreads=int(numba.get_num_threads()),
            has_r=reason_out is not None,
        )  # fmt: skip
        K.depth_filtered(u, v, mask, quality, wimg, tx, ty, table, und, self._kp, self._dp, self._rcp, self._tcp,
                         params, epi, jump, p, depth, sigma, counts, stats, spans, reason, _RCODES)  # fmt: skip
        return depth, counts

    def _noise_inputs(
        self, maps: DecodedMaps, white: npt.NDArray[np.generic] | None, shape: tuple[int, int]
    ) -> tuple[F32, npt.NDArray[np.generic]]:
        """The quality map and the white image (a (1, 1) placeholder without one) as the noise kernels read them."""
        quality = np.ascontiguousarray(maps.quality, np.float32)
        if quality.shape != shape:
            raise ValueError(f"{self.camera.name}: quality is {quality.shape}, camera is {shape} (H, W): must match")
        if white is None:
            return quality, np.zeros((1, 1), np.float32)
        wimg = np.ascontiguousarray(white if white.ndim == 2 else white.mean(axis=2, dtype=np.float32))
        if wimg.shape != shape:
            raise ValueError(f"{self.camera.name}: white image is {wimg.shape}, camera is {shape}: must match")
        return quality, wimg

    def indirect_bias(
        self,
        maps: DecodedMaps,
        depth: F32,
        sigma: F32,
        noise: CodeNoise | None,
        white: npt.NDArray[np.generic] | None,
        dropped: npt.NDArray[np.int64],
        max_sigma_mm: float = math.inf,
        reason_out: npt.NDArray[np.uint8] | None = None,
        widened: npt.NDArray[np.int64] | None = None,
        indirect: bool = True,
        extra_var: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], F32] | None = None,
    ) -> float | None:
        """Widen the sigma of the points of :meth:`triangulate_depth` by the bias of light that came another way.

        The code of a pixel whose fringe share (``maps.fringe``) lies below the scan's median may be shifted
        by indirect light; its variance gains
        :func:`~appliance.reconstruct.uncertainty.fringe_variance_table`'s term, and ``extra_var`` (px^2, per
        pixel, sparse: e.g. the albedo-edge correction's uncertainty). Run after the consistency checks (epipolar,
        neighbours, visibility), which judge noise: a bias is shared by neighbours.

        Parameters
        ----------
        maps : DecodedMaps
            The decoded maps the depth came from (``fringe``, ``quality``).
        depth, sigma : ndarray, shape (H, W), float32
            Depth and 1-sigma error (mm) of :meth:`triangulate_depth`, changed in place.
        noise : CodeNoise, optional
            The code noise model triangulate_depth used; nothing happens without one or without a phase code.
        white : ndarray, shape (H, W), optional
            The white image triangulate_depth used.
        dropped : ndarray, shape (H,), int64
            Receives per row the points dropped for a widened sigma over ``max_sigma_mm``.
        max_sigma_mm : float
            The sigma limit of the depth pass (mm).
        reason_out : ndarray, shape (H, W), uint8, optional
            Gets ``FILTERED`` on the points dropped.
        widened : ndarray, shape (H,), int64, optional
            Receives per row the points whose sigma the indirect term grew (dropped or not).
        indirect : bool
            Apply the indirect-light term (off: ``extra_var`` alone).
        extra_var : tuple of ndarray, optional
            A further code variance (projector px^2) of some pixels: ``(offsets, cols, variance)``, row ``r``'s
            pixels being entries ``offsets[r] .. offsets[r + 1] - 1`` (int64 (H + 1,); ascending int64 columns;
            float32), as :class:`~appliance.reconstruct.albedo_edges.AlbedoEdges` keeps them.

        Returns
        -------
        float or None
            The scan's median fringe share (0..1) the indirect term used, 0.0 where only ``extra_var`` applied;
            None where no term applied (``dropped`` 0).
        """
        shape = self.rays.shape
        dropped[:] = 0
        if widened is not None:
            widened[:] = 0
        fringe = maps.fringe
        if noise is None or noise.period_px <= 0:
            return None
        got = None
        if indirect and fringe is not None:
            if fringe.shape != shape or fringe.dtype != np.uint8 or not fringe.flags.c_contiguous:
                raise ValueError(f"{self.camera.name}: fringe map is {fringe.shape} {fringe.dtype}: must be a "
                                 f"C-contiguous {shape} uint8 map")  # fmt: skip
            # the median share from every 4th row: a quarter of the reads, the same median to a percent
            step = FRINGE_ROW_STEP if shape[0] >= 1000 else 1
            K.u8_histogram(fringe, int(_chunks(shape[0])), step, self._fringe_hist)
            self._fringe_hist *= step
            got = fringe_variance_table(self._fringe_hist, noise.period_px)
        has_e = extra_var is not None
        if got is None and not has_e:
            return None
        if extra_var is not None and extra_var[0].shape != (shape[0] + 1,):
            raise ValueError(f"{self.camera.name}: extra variance offsets {extra_var[0].shape}: must be "
                             f"({shape[0] + 1},)")  # fmt: skip
        eoff, ecols, evar = extra_var if extra_var is not None else (
            np.zeros(shape[0] + 1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
        table, median = got if got is not None else (np.zeros(256, np.float64), 0.0)
        fmap = fringe if got is not None and fringe is not None else np.zeros((1, 1), np.uint8)
        quality, wimg = self._noise_inputs(maps, white, shape)
        has_r = reason_out is not None
        K.indirect_bias(depth, sigma, quality, wimg, white is not None, fmap, got is not None, table,
                        eoff, ecols, evar, has_e,
                        noise.params(), float(max_sigma_mm), reason_out if has_r else np.zeros((1, 1), np.uint8),
                        has_r, np.uint8(Reason.FILTERED), dropped,
                        widened if widened is not None else np.zeros(shape[0], np.int64))  # fmt: skip
        return median

    def write_points(
        self,
        depth: F32,
        counts: npt.NDArray[np.int64],
        quality: npt.NDArray[np.float32],
        intensity: npt.NDArray[np.uint8] | None,
        cloud: PointCloud,
        start: int = 0,
        sigma: F32 | None = None,
        spans: npt.NDArray[np.int64] | None = None,
    ) -> int:
        """Write the points of a :meth:`triangulate_depth` result into ``cloud`` from index ``start``.

        Parameters
        ----------
        depth : ndarray, shape (H, W), float32
            Depth map (mm), NaN where there is no point.
        counts : ndarray, shape (H + 1,), int64
            Points per row as returned with ``depth``.
        quality : ndarray, shape (H, W), float32
            Per-pixel quality (DN).
        intensity : ndarray, shape (H, W), uint8, optional
            Grey value under white light; 0 when None.
        cloud : PointCloud
            Destination (world frame, mm); its ``camera`` array is not touched.
        start : int
            Index of the first point.
        sigma : ndarray, shape (H, W), float32, optional
            Per-pixel 1-sigma error (mm) from :meth:`triangulate_depth`, written to ``cloud.sigma_mm``
            (which must then exist); NaN when None.
        spans : ndarray, shape (H, 2), int64, optional
            Per row, the columns (first, last + 1) that may hold points, from :meth:`triangulate_depth`
            (skips the rest of each row); None: whole rows.

        Returns
        -------
        int
            Number of points written (``counts.sum()``), in row-major pixel order.
        """
        shape = self.rays.shape
        depth = check_depth(depth, shape)
        q = np.ascontiguousarray(quality, np.float32)
        if q.shape != shape:
            raise ValueError(f"quality: {q.shape}: must be {shape}")
        if intensity is None:
            inten = np.zeros((1, 1), np.uint8)
        else:
            inten = np.ascontiguousarray(intensity, np.uint8)
            if inten.shape != shape:
                raise ValueError(f"intensity: {inten.shape}: must be {shape}")
        starts = np.cumsum(counts)
        starts += start
        n = int(starts[-1]) - start
        if start < 0 or start + n > len(cloud):
            raise ValueError(f"cloud holds {len(cloud)} points: cannot write {n} from index {start}")
        sig = np.full((1, 1), np.nan, np.float32) if sigma is None else check_depth(sigma, shape)
        if spans is None:
            sp = np.zeros((1, 2), np.int64)
        elif spans.shape != (shape[0], 2) or spans.dtype != np.int64:
            raise ValueError(f"spans: {spans.shape} {spans.dtype}: must be int64 {(shape[0], 2)}")
        else:
            sp = np.ascontiguousarray(spans)
        o_s = cloud.sigma_mm if cloud.sigma_mm is not None else np.empty(len(cloud), np.float32)
        tx, ty, _ = self.rays.row_table()
        K.emit_points(
            depth, sig, sp, tx, ty, ROW_TABLE_STEP, q, inten, self._rwc, self._cwc, self._to_world, starts,
            _chunks(shape[0]), numba.get_num_threads(), cloud.xyz, cloud.row, cloud.col, cloud.quality, cloud.intensity,
            o_s,
        )  # fmt: skip
        return n

    def organised_from_depth(self, depth: F32, out: F32 | None = None) -> F32:
        """The organised world-frame cloud (H, W, 3) of a depth map (NaN where depth is NaN)."""
        shape = self.rays.shape
        depth = check_depth(depth, shape)
        xyz = check_out(out, shape)
        tx, ty, _ = self.rays.row_table()
        return K.organised_from_depth(  # type: ignore[no-any-return]
            depth, tx, ty, ROW_TABLE_STEP, self._rwc, self._cwc, self._to_world, xyz
        )


FRINGE_ROW_STEP = 4
"""The scan's median fringe share is counted on every this many rows (images of at least 1000 rows)."""

_RCODES = np.array([Reason.DECODED, Reason.OUT_OF_RANGE, Reason.EPIPOLAR, Reason.FILTERED], np.int64)
"""Reason of a decoded pixel by its outcome in the depth kernel (point, out of range, off the epipolar line),
then for a point a filter removed."""


def _reason_buffer(
    out: npt.NDArray[np.uint8] | None, maps: DecodedMaps, mask: npt.NDArray[np.bool_], shape: tuple[int, int]
) -> npt.NDArray[np.uint8]:
    """The reason map the depth kernel completes: ``out`` holding the decoder's reasons ((1, 1) when None)."""
    if out is None:
        return np.zeros((1, 1), np.uint8)
    if out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous:
        raise ValueError(f"reason_out: {out.shape} {out.dtype}: must be a C-contiguous uint8 array of {shape}")
    if maps.reason is None:
        out[...] = np.where(mask, np.uint8(Reason.DECODED), np.uint8(Reason.WEAK_CODE))
    elif maps.reason is not out:
        np.copyto(out, maps.reason)
    return out


def _chunks(height: int) -> int:
    """Row chunks of a parallel pass (several per thread, for load balance)."""
    return max(1, min(height, 8 * numba.get_num_threads()))


def check_depth(depth: F32 | None, shape: tuple[int, int]) -> F32:
    """A (H, W) float32 C-contiguous depth buffer (allocated when ``depth`` is None)."""
    if depth is None:
        return np.empty(shape, np.float32)
    if depth.shape != shape or depth.dtype != np.float32 or not depth.flags.c_contiguous:
        raise ValueError(f"depth: {depth.shape} {depth.dtype}: must be a C-contiguous float32 array of {shape}")
    return depth
