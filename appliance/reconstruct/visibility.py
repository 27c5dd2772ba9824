"""The projector visibility check: a point the projector cannot light is a ghost.

Light that reaches a surface straight from the projector lights the first surface along each projector ray, so a
point of a camera-projector scan lies at the nearest depth its projector ray meets, or its light came another
way. A mirror-like face breaks this in two ways, and both make points that look right:

- the camera sees, in the mirror, a surface the projector lights: the pixel decodes that surface's code, and the
  camera ray (straight, past the mirror) meets the code's light surface somewhere behind the surface the projector
  actually lights with it;
- a face in the projector's shadow is lit through the mirror by the mirrored projector: its code belongs to
  another projector ray, on which a directly lit surface lies nearer.

The check builds, per cell of the projector's image (:data:`CELL_PX` projector px square at the image centre, or
:data:`CAMERA_PX_PER_CELL` camera pixels where those are larger; the
cells tile the undistorted image plane, so each is a bundle of projector rays whatever the lens), the smallest
projector-frame depth of every point of every camera, and of the pixels the decoder left out because two copies
of the pattern reach them (their stronger copy's code: enough to know that a surface is there, never a point).
A point farther than the nearest of its cell by more than the cell's footprint on a surface
:data:`MIN_GRAZING_DEG` from the ray plus :data:`HIDDEN_SIGMAS` of its own error is dropped with reason
``HIDDEN`` ("hidden from the projector"). One point in front is enough: every point the check reads has passed
the neighbour filter (or, as evidence, lies in a region of such pixels), so a stray one is rare; requiring two
dropped most of what one drops on the mirror groove, whose camera pixels are larger than two projector pixels.

What it cannot see: a ghost with nothing in front of it on its projector ray (for example where the mirror maps
the projector's image onto empty space), and what lies within one cell of the edge of a projector shadow
(dropped, a thin band: such pixels mix two surfaces anyway).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from appliance.geometry.camera import CameraModel
from appliance.geometry.rays import ROW_TABLE_STEP
from appliance.reconstruct import _visibility_kernels as _k
from appliance.reconstruct.triangulate import ProjectorTriangulator, relative_pose
from appliance.reconstruct.types import Reason

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

CELL_PX = 2
"""Least side of a cell of the front buffer (projector px)."""
MIN_GRAZING_DEG = 10.0
"""A surface down to this angle from the projector's rays still spreads one cell over less depth than the margin."""
HIDDEN_SIGMAS = 5.0
"""Margin in the point's own 1-sigma errors, on top of the footprint."""
CAMERA_PX_PER_CELL = 1.5
"""... and at least this many camera pixels, so that a surface leaves a point in most cells it covers (where camera
pixels are larger than the projector's, as on the hard scenes' 480 x 384 renders)."""
MAX_BANDS = 4
"""Front buffers filled side by side (one per band of camera rows, then merged): at most this many."""


class ProjectorVisibility:
    """The check for one projector and the cameras of a scan; its front buffer is allocated once, here.

    Parameters
    ----------
    projector : CameraModel
        The projector as an inverse camera.
    triangulators : dict of str to ProjectorTriangulator
        The camera-projector triangulator of every camera whose points are checked (and count as evidence).
    """

    def __init__(self, projector: CameraModel, triangulators: dict[str, ProjectorTriangulator]) -> None:
        self.projector = projector
        self._tri = triangulators
        fp = float(projector.K[0, 0])
        # a cell spans at least CELL_PX projector px and CAMERA_PX_PER_CELL camera px (at equal distances)
        cell_px = max([CELL_PX] + [CAMERA_PX_PER_CELL * fp / float(t.camera.K[0, 0]) for t in triangulators.values()])
        self.cell_px = cell_px
        """Side of a cell at the image centre (projector px)."""
        cell = cell_px / fp  # normalised units
        w, h = projector.width, projector.height
        edge = np.concatenate([
            np.stack([np.linspace(-0.5, w - 0.5, 65), np.full(65, -0.5)], 1),
            np.stack([np.linspace(-0.5, w - 0.5, 65), np.full(65, h - 0.5)], 1),
            np.stack([np.full(65, -0.5), np.linspace(-0.5, h - 0.5, 65)], 1),
            np.stack([np.full(65, w - 0.5), np.linspace(-0.5, h - 0.5, 65)], 1),
        ])  # fmt: skip
        norm = projector.undistort_pixels(edge)
        norm = norm[np.isfinite(norm).all(axis=1)]
        if len(norm):
            lo, hi = norm.min(axis=0) - 2 * cell, norm.max(axis=0) + 2 * cell
        else:  # a lens model not invertible at its border: the image without distortion
            lo = np.array([-0.5 - projector.K[0, 2], -0.5 - projector.K[1, 2]]) / fp - 2 * cell
            hi = lo + np.array([w, h]) / fp + 4 * cell
        nx = min(math.ceil((hi[0] - lo[0]) / cell), 4 * w)
        ny = min(math.ceil((hi[1] - lo[1]) / cell), 4 * h)
        self._grid = np.array([lo[0], lo[1], 1.0 / cell, nx, ny], np.float64)
        # the buffers (4 B a cell each, per band) are made at the first scan that runs the check: hidden_check
        # auto leaves most services without one
        self._bands = max(1, min(numba.get_num_threads(), MAX_BANDS))
        self._fronts = np.empty((0, 0), np.float32)
        self._backs = np.empty((0, 0), np.float32)
        self.slope = cell / math.tan(math.radians(MIN_GRAZING_DEG))
        """Margin per mm of projector depth (mm / mm): one cell's footprint over the tangent of the grazing angle."""
        self._pose = {n: relative_pose(t.camera, projector) for n, t in triangulators.items()}
        # camera pixels across one cell at equal distances: the front fills from about 1.4 a cell each way (the
        # check itself reads every point)
        self._stride = {n: max(1, int(float(t.camera.K[0, 0]) * cell / 1.4)) for n, t in triangulators.items()}
        self._dropped = {n: np.zeros(t.camera.height, np.int64) for n, t in triangulators.items()}

    def apply(
        self,
        depth: dict[str, F32],
        sigma: dict[str, F32],
        counts: dict[str, npt.NDArray[np.int64]],
        stats: dict[str, npt.NDArray[np.int64]],
        reason: dict[str, npt.NDArray[np.uint8] | None],
        evidence: dict[str, npt.NDArray[np.float32] | None],
    ) -> dict[str, int]:
        """Drop the hidden points of every camera, in place (every camera's points and evidence first fill the
        front buffer, then each camera's points are checked against it).

        Parameters
        ----------
        depth, sigma : dict of str to ndarray (H, W) float32
            Per camera the depth (camera frame, mm) and 1-sigma error (mm) of every kept point, NaN elsewhere
            (:meth:`ProjectorTriangulator.triangulate_depth`); hidden points become NaN.
        counts : dict of str to ndarray (H + 1,) int64
            Kept points per row (``counts[r + 1]``), lowered by the points dropped.
        stats : dict of str to ndarray (H, 6) int64
            The depth pass's per-row counts; its kept column (5) is lowered likewise.
        reason : dict of str to ndarray (H, W) uint8 or None
            Reason maps that receive ``HIDDEN`` on the dropped pixels.
        evidence : dict of str to ndarray (N, 4) float32 or None
            Per camera the decoder's ``blend_codes`` (row, column, u, v): surfaces in front, never points.

        Returns
        -------
        dict of str to int
            Points dropped per camera.
        """
        if self._fronts.size == 0:
            cells = int(self._grid[3]) * int(self._grid[4])
            self._fronts = np.empty((self._bands, cells), np.float32)
            self._backs = np.empty((self._bands, cells), np.float32)
        fronts, backs, grid = self._fronts, self._backs, self._grid
        fronts.fill(np.inf)
        backs.fill(-np.inf)
        for n, tri in self._tri.items():
            rcp, tcp = self._pose[n]
            tx, ty, _ = tri.rays.row_table()
            _k.fill_from_depth(depth[n], tx, ty, ROW_TABLE_STEP, rcp, tcp, grid, self._stride[n], fronts, backs)
        for n in self._tri:  # evidence: a front only (its pixels have no point to hide)
            codes = evidence.get(n)
            if codes is not None and len(codes):
                _k.fill_from_points(self.evidence_points(n, codes), grid, fronts[0])
        spread = _k.merge_fronts(fronts, backs, self.slope)
        if not spread:  # no cell holds depths farther apart than a surface spreads over it: nothing is hidden
            return {n: 0 for n in self._tri}
        front = fronts[0]
        dropped: dict[str, int] = {}
        for n, tri in self._tri.items():
            rcp, tcp = self._pose[n]
            tx, ty, _ = tri.rays.row_table()
            r_map = reason.get(n)
            per_row = self._dropped[n]
            _k.drop_hidden(depth[n], sigma[n], tx, ty, ROW_TABLE_STEP, rcp, tcp, grid, front, self.slope, HIDDEN_SIGMAS,
                           r_map if r_map is not None else np.zeros((1, 1), np.uint8), r_map is not None,
                           np.uint8(Reason.HIDDEN), per_row)  # fmt: skip
            total = int(per_row.sum())
            if total:
                counts[n][1:] -= per_row
                stats[n][:, 5] -= per_row
            dropped[n] = total
        return dropped

    def evidence_points(self, camera: str, codes: npt.NDArray[np.float32]) -> F64:
        """Projector-frame points (N, 3) mm of decoder evidence: each pixel's camera ray met with the light
        surface of its code on the coded axis (columns, or rows where only rows are coded), NaN where they do
        not meet in front of both devices.

        Parameters
        ----------
        camera : str
            The camera the codes belong to.
        codes : ndarray, shape (N, 4), float32
            Row, column, u, v per pixel (``DecodedMaps.blend_codes``).
        """
        tri = self._tri[camera]
        rcp, tcp = self._pose[camera]
        c = np.asarray(codes, np.float64)
        norm = tri.camera.undistort_pixels(np.stack([c[:, 1], c[:, 0]], axis=1))
        rays = np.concatenate([norm, np.ones((len(c), 1))], axis=1) @ rcp.T  # camera rays in the projector frame
        axis = 1 if tri.axes == "y" else 0
        code = c[:, 2 + axis]
        p = self.projector
        other = np.full(len(c), float(p.K[1, 2] if axis == 0 else p.K[0, 2]))  # the other coordinate: refined below
        pts = np.full((len(c), 3), np.nan)
        for _ in range(3):
            a = np.stack([code, other - 0.5] if axis == 0 else [other - 0.5, code], axis=1)
            b = np.stack([code, other + 0.5] if axis == 0 else [other + 0.5, code], axis=1)
            da = np.concatenate([p.undistort_pixels(a), np.ones((len(c), 1))], axis=1)
            db = np.concatenate([p.undistort_pixels(b), np.ones((len(c), 1))], axis=1)
            normal = np.cross(da, db)  # the code's light plane through the projector's centre (locally)
            den = np.einsum("ij,ij->i", normal, rays)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -(normal @ tcp) / den
            pts = tcp + t[:, None] * rays
            pts[~(t > 0) | ~(pts[:, 2] > 0)] = np.nan
            with np.errstate(invalid="ignore"):
                other = np.where(np.isfinite(pts[:, 2]), self._project_axis(pts, 1 - axis), other)
        return np.ascontiguousarray(pts)

    def _project_axis(self, pts: F64, axis: int) -> F64:
        """One distorted pixel coordinate (0: column, 1: row) of projector-frame points."""
        p = self.projector
        with np.errstate(divide="ignore", invalid="ignore"):
            xd, yd = p.distort_normalized(pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2])
        if axis == 0:
            return np.asarray(p.K[0, 0] * xd + p.K[0, 1] * yd + p.K[0, 2], np.float64)
        return np.asarray(p.K[1, 1] * yd + p.K[1, 2], np.float64)
