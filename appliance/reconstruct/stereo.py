"""Camera-camera triangulation: match decoded projector codes between two cameras, then intersect rays.

Method
------
Both cameras are rectified once (per calibration) to a common orientation whose x axis is the baseline, so
that every epipolar plane is one rectified row ``b`` shared by both cameras. Per scan:

1. The codes are looked at first: *continuous* codes (phase) change smoothly from pixel to pixel;
   *quantised* codes (Gray only) are stripe centres, constant over a stripe. Quantisation (step and grid)
   and the code gradient (codes per pixel) are measured from the maps, and every tolerance below scales
   with them. A pixel that dropped its finest Gray bits (``DecodedMaps.levels``: blur that makes the finest
   stripes marginal) holds the centre of a wider stripe, half way between two finest ones: it is judged on
   the grid of its own level.
2. The code maps of both cameras are resampled onto their rectified grids (bilinear, only where the four
   neighbours are decoded and agree within the measured gradient plus one code step: not across an edge).
   Codes are counted in *levels*: one projector pixel for continuous codes, the stripe boundaries for
   quantised ones.
3. For every rectified row, a crossing table records the sub-pixel x where the code crosses each level
   (linear between pixels); a level crossed twice on a row is ambiguous and never used. For quantised
   codes each crossing is a stripe boundary known to half a pixel; a local plane fit over neighbouring
   levels and rows (robust, with a second pass without outliers) takes that quantisation out.
4. Every cam0 pixel gets a continuous level: its own code (continuous) or its place between its stripe's
   boundaries on its own row (quantised; a pixel outside its own stripe is rejected, which is also the
   left-right check). Its match is looked up on row ``b`` of cam1 by interpolating cam1's crossing table:
   sub-pixel, no search, no averaging of codes seen twice.
5. With rows coded too (v), the match's epipolar residual is measured (how far off the row cam1's v equals
   cam0's v). A systematic offset (a calibration that drifted) is fitted as a plane over the image and the
   rows of cam1 are corrected by it; the tolerance then follows from the calibration's stated RMS and this
   scan's own residual spread, not from a constant. With a calibrated projector the point must project onto
   its code (three-view check), with a tolerance from the code step and the residuals.
6. The two rays are coplanar by construction: depth = baseline / disparity.

Gray codes on both axes with stripes of at most ``CELL_MAX_PX`` camera pixels are matched by *code cells*
instead (``_cell_kernels``): a (u, v) pair names one projector cell, whose pixel centroids in the two cameras
are images of one surface region. The cell disparities get a plane fit over a window of neighbouring cells
(separable, so its cost does not grow with the window; a window holding a disparity jump falls back to a
robust 3 x 3 fit of the cells on the cell's own surface), and every cam0 pixel takes its cell's plane at its
own position (a pixel whose code lies half way between two cells counts half to each cell's centroid, and
takes the cell whose centroid is nearest). Steps 2-4 are not needed, nor a search; the epipolar residual is
the cells' row difference and a drift correction only moves the residuals. The checks of step 5 are the same.

Every stage counts what it rejects (:class:`StereoReport`), and a stage that rejects most candidates is
said in words, with what to do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel
from appliance.geometry.rays import RayTable
from appliance.reconstruct import _cell_kernels as K
from appliance.reconstruct import _stereo_kernels as C
from appliance.reconstruct.residuals import Residual, summarise
from appliance.reconstruct.triangulate import check_maps, check_out, distortion12
from appliance.reconstruct.types import DecodedMaps
from appliance.reconstruct.uncertainty import CodeNoise

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

CODE_OFFSET = 2
"""Levels from -2 up are tabulated."""
#: The source-pixel maps of the rectified grid keep a knot every MAP_KNOTS[i] rectified pixels, the coarsest
#: of these whose bilinear interpolation stays within MAP_TOLERANCE_PX of the exact distorted pixel everywhere
#: the camera sees (a full map is 10 MB a camera; the lens's distortion is smooth at this scale)
MAP_KNOTS = (8, 4, 2, 1)
MAP_TOLERANCE_PX = 0.01

SMOOTH_ROWS = 2
"""Quantised codes: the crossing fit spans this many rectified rows either side."""
SMOOTH_SPAN_PX = 3.0
"""Quantised codes: ... and levels spanning about this many pixels either side."""
SMOOTH_MAX_LEVELS = 12
MAX_RES_PX = 1.0
"""A crossing further than this from the local fit is left out of it (px)."""
MAX_ROW_JUMP_PX = 2.0
"""Largest change of a crossing between two neighbouring rectified rows (px)."""
MAX_OWN_PX = 1.0
"""Continuous codes, left-right check: largest distance between a pixel and its code on its own row (px)."""
EPIPOLAR_OFFSET_MIN_PX = 0.3
"""A median epipolar residual beyond this (and beyond half its spread) is corrected (px)."""
DRIFT_REFUSE_FACTOR = 10.0
"""An epipolar offset beyond this multiple of the calibration's stated RMS (and beyond
:data:`DRIFT_REFUSE_MIN_PX`) is not a drift but a calibration of another rig: with ``drift="refuse"`` the pair
writes no points."""
DRIFT_REFUSE_MIN_PX = 5.0
"""... and never below this many rectified px: a bumped camera or warm-up moves the lines by a few px, which
the plane fit corrects to well under a millimetre."""
DRIFT_POLICIES = ("correct", "refuse")
NEIGHBOURS_AGREE = 2
"""The neighbour filter keeps a point only with this many valid neighbours within its jump limit."""
SEEN_MIN_PX = 1
"""A code cell counts as seen by the other camera when that many of its pixels decode it (2 would drop lone
wrong codes, but also the many cells a foreshortened view samples with one pixel: 19 % fewer on the real-like
render, where 1 counts 12 % more than the truth's both-seen pixels, at a share 1 point below the truth's)."""
MIN_SAMPLES = 200
"""Fewest residuals a statistic is taken from."""
MOST_SAMPLES = 40_000
"""A residual statistic (median, spread) is taken from at most about this many evenly spread samples: its
standard error is then ~0.6 % of the spread, and a full-frame scan does not spend milliseconds on medians."""
MOST = 0.5
"""A stage that rejects more than this share of the candidates is reported in words."""
CELL_MIN_PX = 1.2
"""Both axes quantised: a matching cell spans at least this many camera pixels along each axis (stripes finer
than that are grouped ``ku x kv`` codes to a cell)."""
CELL_SPAN_PX = 3.0
"""Both axes quantised: a cell's disparity plane is fitted over the neighbouring cells within about this many
pixels (at least one cell) either side."""
CELL_MAX_PX = 4.0
"""Both axes quantised with stripes up to this wide (camera px): matched by code cells. Wider stripes are
matched by their boundaries on rectified rows, which then carry more of the information than the centroids
(and a wide cell across an occluding edge would mix two surfaces)."""
CELL_EDGE_PX = 3.0
"""Both axes quantised: cells larger than this (camera px) next to a cell that one camera misses are left out
(partly hidden from one camera, their centroids are off by up to half a cell)."""
SPLIT_MIN_DROPPED = 0.02
"""Both axes quantised: with more than this share of the pixels having dropped finest Gray bits (their codes
half way between two cells), such a code counts half to each cell (``cell_sums_split``: 1.6x the time of
``cell_sums``); below it, rounding them into one cell moves the centroids by a negligible amount."""
CELL_VAR_FLOOR = 1.0 / 12.0
"""Both axes quantised: least variance of a centroid (px^2) times its pixel count (pixel sampling)."""

STAGES = {
    C.ST_OUTSIDE: "outside the rows both cameras see",
    C.ST_OWN: "code not consistent on its own row (edge, ambiguous, left-right check)",
    C.ST_OTHER: "code not found (or ambiguous) on the other camera's row",
    C.ST_EPIPOLAR: "off the epipolar line",
    C.ST_DEPTH: "outside the depth range",
    C.ST_THREE_VIEW: "does not project onto its projector code",
}
_N_STATUS = C.ST_OK + 1
_NO_V = np.full((1, 1), np.nan, np.float32)


@dataclass
class CodeGrid:
    """How one axis of codes is quantised, measured from the maps.

    Attributes
    ----------
    quantised : bool
        Codes are stripe centres (Gray only), not continuous.
    step : float
        Code step (projector px): the stripe width; 1 for continuous codes (levels are projector pixels).
    origin : float
        A stripe centre (projector px): centres are ``origin + k * step``.
    per_px : float
        Mean code change between neighbouring camera pixels along rows (projector px per camera px).
    dropped : float
        Share of the sampled pixels that dropped finest Gray bits (``DecodedMaps.levels`` > 0); 0 without levels.
    """

    quantised: bool
    step: float
    origin: float
    per_px: float
    dropped: float = 0.0

    @property
    def stripe_px(self) -> float:
        """Width of one code step in camera pixels."""
        return self.step / max(self.per_px, 1e-6)


def _value_counts(vals32: F32) -> tuple[F64, npt.NDArray[np.intp]]:
    """The distinct values and their counts. Stripe centres of whole-pixel stripes lie on half pixels: when
    99 % of the values do, they are counted in one pass (the few others are rare by that, and the grid rule
    leaves rare values out anyway); otherwise sorted."""
    share, cnt = C.half_pixel_counts(vals32)
    if cnt.size and share >= 0.99:
        nz = np.flatnonzero(cnt)
        return nz.astype(np.float64) * 0.5, cnt[nz]
    uniq32, counts = np.unique(vals32, return_counts=True)  # float32 sorts faster; the same values
    return uniq32.astype(np.float64), counts


def code_grid(
    code: F32,
    mask: npt.NDArray[np.bool_],
    stride: int = 5,
    along: int = 1,
    levels: npt.NDArray[np.uint8] | None = None,
) -> CodeGrid | None:
    """Measure the quantisation and gradient of a code map (a subsample of every ``stride``-th row/column).

    Parameters
    ----------
    code : ndarray, shape (H, W), float32
        Decoded code (projector px), NaN where not decoded.
    mask : ndarray, shape (H, W), bool
        Decoded pixels.
    stride : int
        Subsampling of rows and columns.
    along : {1, 0}
        The image axis the gradient is measured along: 1 along rows (x), 0 along columns (y: the v code of
        a camera pair whose baseline runs along x). Reading whole rows either way keeps it cache friendly.
    levels : ndarray, shape (H, W), uint8, optional
        This axis's plane of :attr:`DecodedMaps.levels`: per pixel how many of the finest Gray bits it dropped.
        A pixel that dropped ``L`` bits holds the centre of ``2**L`` stripes (half way between two stripe
        centres for ``L >= 1``; with blur that makes the finest stripes marginal, half the pixels): the step
        and origin are then measured on the pixels that kept every bit, and the codes count as quantised when
        (nearly) every value sits on the grid of its own level. Without it every value must sit on the
        finest grid.

    Returns
    -------
    CodeGrid or None
        None when fewer than 100 pixels are decoded.
    """
    buf = np.empty(-(-code.shape[0] // stride) * -(-code.shape[1] // stride), np.float32)
    # all of them: the rule for common values below assumes this density
    levs: npt.NDArray[np.uint8] | None = None
    dropped = 0.0
    if levels is None:
        vals32 = buf[: C.sample_codes(code, mask, stride, buf)]
        fine = vals32
    else:
        lbuf = np.empty(buf.size, np.uint8)
        n, n0 = K.sample_level_codes(code, mask, levels, stride, buf, lbuf)
        vals32, levs = buf[:n], lbuf[:n]
        dropped = 1.0 - n0 / max(n, 1)
        # the step from the pixels that kept every bit (those that dropped some hold centres of wider stripes,
        # half way between the finest ones); all of them when too few kept every bit
        fine = vals32[levs == 0] if n0 >= 100 and n0 < n else vals32
    if vals32.size < 100:
        return None
    step_mean = float(C.mean_step(code, along, stride, 64.0))  # changes of 64 and more: across an occlusion
    per_px = step_mean if math.isfinite(step_mean) else 1.0
    uniq, counts = _value_counts(fine)
    if uniq.size < 2:
        return CodeGrid(False, 1.0, 0.0, max(per_px, 1e-3))
    # stripe centres repeat; a rare value in between (a pixel on an edge) must not set the step
    common = uniq[counts >= max(2.0, 0.05 * float(np.median(counts)))]
    gaps = np.diff(common)
    gaps = gaps[gaps > 0.25]
    if gaps.size and counts.max() >= 3:
        # the smallest gap, unless edge values between stripe centres happen to repeat in the sample (about
        # one camera px per stripe): then the next larger gap that puts (nearly) every value on the grid
        for step in np.unique(np.round(gaps, 4))[:4].tolist():
            if step < 1.0 - 1e-6:
                continue
            origin = float(np.median(np.mod(common, step)))
            share = (
                C.on_grid_share(vals32, origin, step) if levs is None
                else K.on_level_grid_share(vals32, levs, origin, step)
            )  # fmt: skip
            if share >= 0.99:
                return CodeGrid(True, float(step), origin, max(per_px, 1e-3), dropped)
            break
    return CodeGrid(False, 1.0, 0.0, max(per_px, 1e-3))


@dataclass
class StereoReport:
    """What the last camera-camera reconstruction did, stage by stage.

    Attributes
    ----------
    candidates : int
        Decoded pixels of the reference camera.
    points : int
        Points kept.
    rejected : dict of str to int
        Candidates rejected, by stage (see ``STAGES``).
    code : str
        ``'quantised'`` or ``'continuous'`` codes, with the step and stripe width.
    epipolar : dict of str to float
        With rows coded: residual median and spread (robust sigma) before and after correction, the offset
        applied (px, rectified), the limit used and the number of samples.
    three_view : dict of str to float
        With a projector: residual median, spread, limit (projector px), samples.
    warnings : list of str
        Plain-words statements about stages that rejected most candidates, with what to do.
    refused : str
        Non-empty when the pair wrote no points because its calibration does not fit (the reason and the fix).
    both_seen : int
        Reference-camera pixels both cameras see, as far as the codes tell. Both axes coded: pixels whose
        projector code cell the other camera decodes too (within one cell for continuous codes); one axis:
        pixels whose code the other camera decodes on the same rectified row (within a row and a level: a
        projector px for continuous codes, a stripe for quantised ones).
    both_seen_points : int
        How many of those hold a point (after the filters of this triangulator, when they ran).
    """

    candidates: int = 0
    points: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    code: str = ""
    epipolar: dict[str, float] = field(default_factory=dict)
    three_view: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    refused: str = ""
    both_seen: int = 0
    both_seen_points: int = 0

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (for the sidecar and ``scan3d decode --report``)."""
        return {
            "candidates": self.candidates,
            "points": self.points,
            "rejected": dict(self.rejected),
            "code": self.code,
            "epipolar": dict(self.epipolar),
            "three_view": dict(self.three_view),
            "warnings": list(self.warnings),
            "refused": self.refused,
            "both_seen": {
                "pixels": self.both_seen,
                "reconstructed": self.both_seen_points,
                "share": self.both_seen_points / self.both_seen if self.both_seen else None,
            },
        }


def _sample(values: F32, ok: npt.NDArray[np.bool_]) -> F32:
    """The finite ``values[ok]``, thinned evenly to at most about :data:`MOST_SAMPLES` (1-D)."""
    v = values[ok]
    v = v[np.isfinite(v)]
    step = -(-v.size // MOST_SAMPLES)
    return v[::step] if step > 1 else v


def _robust(values: F32) -> tuple[float, float, int]:
    """Median, robust sigma (1.4826 MAD) and count of the finite values."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return math.nan, math.nan, 0
    med = float(np.median(v))
    return med, 1.4826 * float(np.median(np.abs(v - med))), int(v.size)


def _source_map(rot: F64, a0: float, b0: float, step: float, hr: int, wr: int, cam: CameraModel) -> tuple[F32, int]:
    """The camera's distorted pixel of rectified pixels (hr, wr) (grid origin (a0, b0), ``step`` apart),
    ``rot`` device -> rectified: a map of knots (rows, cols, 2) float32 and the knot spacing (rectified px, the
    coarsest of :data:`MAP_KNOTS` within :data:`MAP_TOLERANCE_PX`; 1, a full map, when none is)."""
    rot_t = np.ascontiguousarray(rot.T)
    kmat, d = np.ascontiguousarray(cam.K), distortion12(cam)
    for knot in MAP_KNOTS[:-1]:
        srcmap = C.project_dirs(rot_t, a0, b0, step * knot, (hr - 1) // knot + 2, (wr - 1) // knot + 2, kmat, d)
        err = C.map_error(rot_t, a0, b0, step, hr, wr, kmat, d, srcmap, knot, float(cam.width), float(cam.height))
        if err <= MAP_TOLERANCE_PX:
            return srcmap, knot
    return C.project_dirs(rot_t, a0, b0, step, hr, wr, kmat, d), 1


def _pixel_map(full: F32, rot: F64, a0: float, b0: float, step: float, cam: CameraModel) -> tuple[F32, int]:
    """The camera's pixels on the rectified grid, ``full`` (H, W, 2), as a map of knots every ``knot`` pixels
    (the coarsest of :data:`MAP_KNOTS` within :data:`MAP_TOLERANCE_PX` of ``full`` everywhere; ``full`` itself
    when none is): (map, knot)."""
    h, w = full.shape[0], full.shape[1]
    for knot in MAP_KNOTS[:-1]:
        rows, cols = (h - 1) // knot + 2, (w - 1) // knot + 2
        ys, xs = np.mgrid[0:rows, 0:cols] * knot
        px = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
        a, b = _rect_coords(rot, cam.undistort_pixels(px))
        knots = np.empty((rows, cols, 2), np.float32)
        knots[..., 0] = ((a - a0) / step).reshape(rows, cols)
        knots[..., 1] = ((b - b0) / step).reshape(rows, cols)
        if C.grid_error(full, knots, knot) <= MAP_TOLERANCE_PX:
            return knots, knot
    return full, 1


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


def _stated_rms(*devices: CameraModel) -> float:
    """Root-sum-square of the devices' stated reprojection RMS (px); 0 where none is stated."""
    vals = [d.rms for d in devices if math.isfinite(d.rms)]
    return math.sqrt(sum(v * v for v in vals)) if vals else 0.0


class StereoTriangulator:
    """Camera-camera triangulation for one camera pair; the rectification is built once, here.

    Parameters
    ----------
    cam0, cam1 : CameraModel
        The two cameras; output is organised for cam0's pixels, in the world frame.
    rays0 : RayTable, optional
        cam0's ray table, when already computed.
    max_epipolar_px : float, optional
        With v coded: fixed limit of the epipolar residual (rectified px). Default: from the calibration's
        stated RMS and this scan's residual spread.
    projector : CameraModel, optional
        Calibrated projector for the three-view check.
    max_code_err_px : float, optional
        Three-view check: fixed limit of |projected code - decoded code| (projector px). Default: from the
        code step and this scan's residual spread.
    correct_epipolar : bool, optional
        Fit and correct a systematic epipolar offset measured from (u, v) matches. Default: with the automatic
        limit only (a fixed ``max_epipolar_px`` trusts the calibration as it is).
    drift : {"refuse", "correct"}
        An offset beyond ``max(DRIFT_REFUSE_MIN_PX, DRIFT_REFUSE_FACTOR x the stated RMS)``: ``"refuse"``
        writes no points for the pair and says why (:attr:`StereoReport.refused`); ``"correct"`` corrects it
        like a small drift.

    Attributes
    ----------
    cell_min_px : float
        Both axes quantised: least extent of a matching code cell (camera px), ``CELL_MIN_PX`` unless set on
        the instance (``scripts/bench`` times coarser cells this way).
    """

    cell_min_px: float = CELL_MIN_PX

    def __init__(
        self,
        cam0: CameraModel,
        cam1: CameraModel,
        rays0: RayTable | None = None,
        max_epipolar_px: float | None = None,
        projector: CameraModel | None = None,
        max_code_err_px: float | None = None,
        correct_epipolar: bool | None = None,
        drift: str = "refuse",
    ) -> None:
        if drift not in DRIFT_POLICIES:
            raise ValueError(f"stereo drift policy {drift!r}: must be one of {DRIFT_POLICIES}")
        self.drift = drift
        self.cam0, self.cam1, self.projector = cam0, cam1, projector
        self.rays0 = rays0 if rays0 is not None else RayTable(cam0)
        self.max_epipolar_px, self.max_code_err_px = max_epipolar_px, max_code_err_px
        self.correct_epipolar = max_epipolar_px is None if correct_epipolar is None else correct_epipolar
        self.report = StereoReport()
        c0, c1 = cam0.center, cam1.center
        base = float(np.linalg.norm(c1 - c0))
        if base < 1e-6:
            raise CalibrationError(f"{cam0.name}/{cam1.name}: the cameras share one centre: no stereo baseline")
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
            raise CalibrationError(f"{cam0.name}/{cam1.name}: the cameras look more than 90 deg away from each other")
        bmin = max(np.nanmin(b0), np.nanmin(b1)) - 2 * step
        bmax = min(np.nanmax(b0), np.nanmax(b1)) + 2 * step
        if bmax <= bmin:
            raise CalibrationError(f"{cam0.name}/{cam1.name}: the two views share no epipolar plane (no overlap)")
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
        self._map0, self._knot0 = _source_map(rot0, a0min, bmin, step, hr, wr0, cam0)
        self._map1, self._knot1 = _source_map(rot1, a1min, bmin, step, hr, wr1, cam1)
        rect0 = np.empty((h, w, 2), np.float32)
        rect0[..., 0] = ((a0 - a0min) / step).reshape(h, w)
        rect0[..., 1] = ((b0 - bmin) / step).reshape(h, w)
        del a0, b0
        self._rect0, self._knot_r0 = _pixel_map(rect0, rot0, a0min, bmin, step, cam0)
        del rect0
        self._rot0, self._rot1 = rot0, rot1
        self._rect1: F32 | None = None  # cam1's pixels on the rectified grid: built when cells are matched
        self._rect1k: F32 | None = None  # ... as knots: built when a scan codes one axis (both-seen count)
        self._row_marks: npt.NDArray[np.uint8] | None = None  # the one-axis both-seen count's two tables
        self._cells: dict[str, npt.NDArray[Any]] = {}
        self._r0z = np.ascontiguousarray(cam0.R[2])
        self._t0z = float(cam0.T[2])
        self._c0 = c0
        # per-scan buffers, reused; those of coded rows (v) on the first scan that has them
        self._u0r = np.empty((hr, wr0), np.float32)
        self._u1r = np.empty((hr, wr1), np.float32)
        self._lev0 = np.empty((h, w), np.float32)
        # the three-view errors are taken after the last match (rematch included), when no level is read again
        self._err3 = self._lev0
        self._epi = np.empty((h, w), np.float32)
        self._vbufs: dict[str, F32] = {}
        self.sigma = np.empty((h, w), np.float32)
        """1-sigma error of each point of the last :meth:`triangulate` along cam0's ray (mm); NaN where none."""
        self._status = np.zeros((h, w), np.uint8)
        self._seen = np.zeros((h, w), np.bool_)
        self._seen_table: npt.NDArray[np.uint8] | None = None
        self._counts = np.zeros((h, _N_STATUS), np.int64)
        self._tabs: dict[str, F32] = {}
        self.last_grid: CodeGrid | None = None
        self.residuals: list[Residual] = []
        """Epipolar (rows coded) and three-view (projector) residuals of the last :meth:`triangulate`, before
        any correction: what the scan says about the calibration (:mod:`appliance.reconstruct.residuals`)."""

    def _vbuf(self, name: str) -> F32:
        """A buffer of coded rows: ``v1r``, ``v1s``, ``scr1`` (rectified grid of cam1) or ``v0s``, ``scr0`` (cam0)."""
        buf = self._vbufs.get(name)
        if buf is None:
            hr, wr1 = self.rect_shape[0], self.rect_shape[2]
            buf = self._vbufs[name] = np.empty((hr, wr1) if name in ("v1r", "v1s", "scr1") else self.rays0.shape,
                                               np.float32)  # fmt: skip
        return buf

    def _table(self, name: str, nk: int) -> F32:
        """A C-contiguous (rows, nk) table carved from a kept buffer (a column slice of a wider one would be
        strided: a second compiled variant of every kernel that reads it, loaded or compiled mid-scan)."""
        hr = self.rect_shape[0]
        flat = self._tabs.get(name)
        if flat is None or flat.size < hr * nk:
            flat = np.empty(hr * nk, np.float32)
            self._tabs[name] = flat
        return flat[: hr * nk].reshape(hr, nk)

    def triangulate(
        self,
        maps0: DecodedMaps,
        maps1: DecodedMaps,
        out: F32 | None = None,
        min_depth_mm: float = 1e-6,
        max_depth_mm: float = math.inf,
        noise: CodeNoise | None = None,
    ) -> F32:
        """Match and triangulate; :attr:`report` tells what each stage rejected, :attr:`sigma` each point's
        expected error.

        Parameters
        ----------
        maps0, maps1 : DecodedMaps
            Decoded projector codes of cam0 (H0, W0) and cam1 (H1, W1); v is used when decoded.
        out : ndarray, shape (H0, W0, 3), float32, optional
            Preallocated output.
        min_depth_mm, max_depth_mm : float
            Depth range (z in cam0's frame, mm).
        noise : CodeNoise, optional
            Noise of continuous codes (phase: finest period and steps, camera noise) for :attr:`sigma`; without
            it a continuous code's sigma is NaN. A quantised code's match error follows from the stripe and
            the pixel grid (each stripe boundary is known to a pixel / sqrt 12 before the local fit).

        Returns
        -------
        ndarray, shape (H0, W0, 3), float32
            World-frame points (mm) organised by cam0 pixel; NaN where unmatched or rejected.
        """
        u0, v0, mask0 = check_maps(maps0, self.rays0.shape, self.cam0.name)
        u1, v1, mask1 = check_maps(maps1, (self.cam1.height, self.cam1.width), self.cam1.name)
        xyz = check_out(out, self.rays0.shape)
        rep = StereoReport()
        self.report = rep
        lev0 = maps0.levels if maps0.levels is not None and maps0.levels.shape[1:] == u0.shape else None
        grid = code_grid(u0, mask0, levels=None if lev0 is None else lev0[0])
        self.last_grid = grid
        if grid is None:
            xyz[...] = np.nan
            rep.candidates = int(mask0.sum())
            rep.warnings.append(f"{self.cam0.name}: fewer than 100 decoded pixels: nothing to match")
            return xyz
        use_v = bool(np.isfinite(v0[::7, ::7]).any() and np.isfinite(v1[::7, ::7]).any())
        # levels: projector pixels (continuous) or stripe boundaries (quantised; stripe k = (k, k + 1))
        dl = grid.step
        lev_origin = grid.origin - 0.5 * grid.step if grid.quantised else 0.0
        per_lev = grid.per_px / dl  # levels per pixel
        spread = 1.5 * (grid.step if grid.quantised else 1.0) + 3.0 * grid.per_px
        max_step = spread / dl
        max_gap = max(4.0, 3.0 / per_lev)
        margin = max(0.25, 0.75 * per_lev) if grid.quantised else 0.0
        rep.code = (
            f"quantised, step {grid.step:g} projector px, {grid.stripe_px:.2f} camera px per step"
            if grid.quantised
            else f"continuous, {grid.per_px:.2f} projector px per camera px"
        )
        vgrid: CodeGrid | None = None
        if use_v:
            vgrid = code_grid(v0, mask0, along=0, levels=None if lev0 is None else lev0[1])
            vstep = vgrid.step if vgrid is not None and vgrid.quantised else 1.0
            vper = vgrid.per_px if vgrid is not None else 1.0
        zmin, zmax = max(float(min_depth_mm), 1e-6), float(max_depth_mm)
        cells = (
            use_v
            and grid.quantised
            and vgrid is not None
            and vgrid.quantised
            and max(grid.stripe_px, vgrid.stripe_px) <= CELL_MAX_PX
        )
        if cells:
            assert vgrid is not None
            rep.code += (
                f"; rows quantised, step {vgrid.step:g} projector px, {vgrid.stripe_px:.2f} camera px per step; "
                "matched by code cells"
            )
            split = max(grid.dropped, vgrid.dropped) > SPLIT_MIN_DROPPED
            self._match_cells(u0, v0, mask0, u1, v1, mask1, grid, vgrid, xyz, zmin, zmax, split)
            self._check(rep, grid, vgrid, xyz, u0, v0, use_v, True, None)
            self._both_seen(rep, xyz, (u0, v0, mask0), (u1, v1, mask1), grid, vgrid)
            return xyz
        hi = max(float(np.nanmax(u0, initial=0.0)), float(np.nanmax(u1, initial=0.0)))
        nk = math.ceil((hi - lev_origin) / dl) + CODE_OFFSET + 3
        C.remap_codes(u0, mask0, self._map0, self._knot0, spread, self._u0r)
        if use_v:  # cam1's u and v in one pass
            C.remap_pair(u1, v1, mask1, self._map1, self._knot1, spread, 1.5 * vstep + 3.0 * vper, self._u1r,
                         self._vbuf("v1r"))
        else:
            C.remap_codes(u1, mask1, self._map1, self._knot1, spread, self._u1r)
        C.to_levels(self._u0r, lev_origin, 1.0 / dl)
        C.to_levels(self._u1r, lev_origin, 1.0 / dl)
        np.subtract(u0, np.float32(lev_origin), out=self._lev0)
        np.multiply(self._lev0, np.float32(1.0 / dl), out=self._lev0)
        cross0, cross1 = self._table("c0", nk), self._table("c1", nk)
        C.level_crossings(self._u0r, CODE_OFFSET, max_step, cross0)
        C.level_crossings(self._u1r, CODE_OFFSET, max_step, cross1)
        levels = 0
        if grid.quantised:
            levels = int(min(SMOOTH_MAX_LEVELS, max(1, math.ceil(SMOOTH_SPAN_PX * per_lev))))
            s0, s1 = self._table("s0", nk), self._table("s1", nk)
            for raw, sm in ((cross0, s0), (cross1, s1)):
                C.smooth_crossings(raw, levels, False, MAX_RES_PX, sm)
                C.smooth_crossings(sm, SMOOTH_ROWS, True, MAX_RES_PX, raw)  # back into the raw table
        v0m, v1m = _NO_V, _NO_V  # not read without v
        if use_v:
            v0m, v1m = v0, self._vbuf("v1r")
            if vgrid is not None and vgrid.quantised:
                radius = int(min(8, max(1, math.ceil(vgrid.stripe_px))))
                span = (2 * radius + 1) * vper + 2.0 * vstep
                v0m, v1m = self._vbuf("v0s"), self._vbuf("v1s")
                C.box_mean(v0, radius, span, self._vbuf("scr0"), v0m)
                C.box_mean(self._vbuf("v1r"), radius, span, self._vbuf("scr1"), v1m)
        tol = np.array([max_gap, MAX_ROW_JUMP_PX, MAX_OWN_PX, margin])
        noise_p = self._noise_params(grid, noise, levels if grid.quantised else 0)
        shift = np.zeros(3)
        q0 = np.ascontiguousarray(maps0.quality, dtype=np.float32)
        args = (self._rr_t, self._c0, self._r0z, self._t0z, tol, zmin, zmax, q0, noise_p, xyz, self._epi,
                self.sigma, self._status)  # fmt: skip
        C.cc_match(self._lev0, mask0, self._rect0, self._knot_r0, cross0, cross1, grid.quantised, v0m, v1m, use_v,
                   CODE_OFFSET, self._geom, shift, *args)  # fmt: skip

        def rematch(shift: F64) -> None:
            C.cc_match(self._lev0, mask0, self._rect0, self._knot_r0, cross0, cross1, grid.quantised, v0m, v1m, use_v,
                       CODE_OFFSET, self._geom, shift, *args)  # fmt: skip

        self._check(rep, grid, vgrid, xyz, u0, v0, use_v, False, rematch)
        if use_v:
            self._both_seen(rep, xyz, (u0, v0, mask0), (u1, v1, mask1), grid, vgrid)
        else:
            self._both_seen_rows(rep, xyz, u0, mask0, u1, mask1, lev_origin, dl, nk)
        return xyz

    def _both_seen_rows(
        self,
        rep: StereoReport,
        xyz: F32,
        u0: F32,
        mask0: npt.NDArray[np.bool_],
        u1: F32,
        mask1: npt.NDArray[np.bool_],
        origin: float,
        step: float,
        nk: int,
    ) -> None:
        """One coded axis: count cam0's pixels whose code cam1 decodes on the same rectified row, within a row and
        a level (:attr:`StereoReport.both_seen`), from both cameras' decoded codes as they are (not the
        matcher's resampled ones), and the points among them."""
        hr = self.rect_shape[0]
        flat = self._row_marks
        if flat is None or flat.size < 2 * hr * nk:
            flat = self._row_marks = np.empty(2 * hr * nk, np.uint8)
        table, scratch = flat[: hr * nk].reshape(hr, nk), flat[hr * nk : 2 * hr * nk].reshape(hr, nk)
        rect1, knot1 = self._rect_knots1()
        C.mark_rows(u1, mask1, rect1, knot1, origin, 1.0 / step, table, scratch)
        seen, points = C.seen_on_rows(u0, mask0, self._rect0, self._knot_r0, origin, 1.0 / step, table, xyz,
                                      self._seen)  # fmt: skip
        rep.both_seen, rep.both_seen_points = int(seen), int(points)

    def _rect_knots1(self) -> tuple[F32, int]:
        """cam1's pixels on the rectified grid (grid units) as knots every ``MAP_KNOTS[0]`` pixels, for
        :func:`_stereo_kernels.mark_rows` (a count, which a row's rounding makes coarser than the knots' error);
        built once, on first use."""
        knot = MAP_KNOTS[0]
        if self._rect1k is None:
            cam1 = self.cam1
            rows, cols = (cam1.height - 1) // knot + 2, (cam1.width - 1) // knot + 2
            ys, xs = np.mgrid[0:rows, 0:cols] * knot
            px = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
            a, b = _rect_coords(self._rot1, cam1.undistort_pixels(px))
            a1min, bmin, step = self._geom[1], self._geom[2], self._geom[3]
            knots = np.empty((rows, cols, 2), np.float32)
            knots[..., 0] = ((a - a1min) / step).reshape(rows, cols)
            knots[..., 1] = ((b - bmin) / step).reshape(rows, cols)
            self._rect1k = knots
        return self._rect1k, knot

    def _both_seen(
        self,
        rep: StereoReport,
        xyz: F32,
        codes0: tuple[F32, F32, npt.NDArray[np.bool_]],
        codes1: tuple[F32, F32, npt.NDArray[np.bool_]],
        grid: CodeGrid,
        vgrid: CodeGrid | None,
    ) -> None:
        """Count cam0's pixels whose (u, v) cell cam1 decodes too (:attr:`StereoReport.both_seen`) and the points
        among them. A quantised axis is counted in its stripes, a continuous one in projector px within one.
        Stripes finer than the matcher's cell (:attr:`cell_min_px`) are looked for as far as it groups them: a
        camera samples such codes sparsely, so the very stripe cam0 decodes is often between cam1's pixels (with a
        projector three times finer than the cameras' pixels, 23 % of the both-seen pixels were counted)."""
        axes = []
        for g in (grid, vgrid):
            if g is not None and g.quantised:
                axes.append((g.origin, 1.0 / g.step, max(0, math.ceil(self.cell_min_px / g.stripe_px) - 1)))
            else:
                axes.append((0.0, 1.0, 1))
        cg = np.array([axes[0][0], axes[0][1], axes[1][0], axes[1][1]], np.float64)
        hu0, hv0 = K.code_max(codes0[0], codes0[1], codes0[2])
        hu1, hv1 = K.code_max(codes1[0], codes1[1], codes1[2])
        ncu = math.floor((max(hu0, hu1) - cg[0]) * cg[1] + 0.5) + 2
        ncv = math.floor((max(hv0, hv1) - cg[2]) * cg[3] + 0.5) + 2
        table = self._seen_table
        if table is None or table.shape != (ncv, ncu):
            table = self._seen_table = np.empty((ncv, ncu), np.uint8)
        C.mark_codes(*codes1, cg, table)
        rep.both_seen = int(C.seen_by_both(*codes0, cg, table, axes[0][2], axes[1][2], SEEN_MIN_PX, self._seen))
        rep.both_seen_points = int(C.count_points_in(xyz, self._seen))

    def _rect0_every(self, n: int) -> F32:
        """cam0's pixels ``[::n, ::n]`` on the rectified grid (grid units), (ceil(H / n), ceil(W / n), 2)."""
        h, w = self.rays0.shape
        out: F32 = C.sample_map(self._rect0, self._knot_r0, n, -(-h // n), -(-w // n))
        return out

    def _rect_cam1(self) -> F32:
        """cam1's pixels on the rectified grid (H1, W1, 2), in grid units; built once, on first use."""
        if self._rect1 is None:
            cam1 = self.cam1
            ys, xs = np.mgrid[0 : cam1.height, 0 : cam1.width]
            px = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
            a, b = _rect_coords(self._rot1, cam1.undistort_pixels(px))
            a1min, bmin, step = self._geom[1], self._geom[2], self._geom[3]
            rect = np.empty((cam1.height, cam1.width, 2), np.float32)
            rect[..., 0] = ((a - a1min) / step).reshape(cam1.height, cam1.width)
            rect[..., 1] = ((b - bmin) / step).reshape(cam1.height, cam1.width)
            self._rect1 = rect
        return self._rect1

    def _cell_buffers(self, n: int) -> tuple[npt.NDArray[np.int32], F32, npt.NDArray[np.int32], F32, F32]:
        got = self._cells.get("cnt0")
        if got is None or got.shape[0] < n:
            self._cells |= {"cnt0": np.empty(n, np.int32), "acc0": np.empty((n, 2), np.float32),
                           "cnt1": np.empty(n, np.int32), "acc1": np.empty((n, 2), np.float32),
                           "fits": np.empty((n, K.FIT_COLS), np.float32)}  # fmt: skip
        c = self._cells
        return c["cnt0"][:n], c["acc0"][:n], c["cnt1"][:n], c["acc1"][:n], c["fits"][:n]

    def _match_cells(
        self,
        u0: F32,
        v0: F32,
        mask0: npt.NDArray[np.bool_],
        u1: F32,
        v1: F32,
        mask1: npt.NDArray[np.bool_],
        grid: CodeGrid,
        vgrid: CodeGrid,
        xyz: F32,
        zmin: float,
        zmax: float,
        split: bool = False,
    ) -> None:
        """Both axes quantised: match by code cells (``_cell_kernels``), into xyz, epi, sigma and status.
        ``split``: a code half way between two cells (a pixel that dropped finest Gray bits) counts half to each
        cell's centroid (``cell_sums_split``) instead of all to the upper one."""
        ku = max(1, math.ceil(self.cell_min_px / grid.stripe_px))
        kv = max(1, math.ceil(self.cell_min_px / vgrid.stripe_px))
        cell_u, cell_v = ku * grid.stripe_px, kv * vgrid.stripe_px
        hu0, hv0 = K.code_max(u0, v0, mask0)
        hu1, hv1 = K.code_max(u1, v1, mask1)
        hi_u, hi_v = max(hu0, hu1), max(hv0, hv1)
        ou = grid.origin - grid.step * math.ceil(grid.origin / grid.step)  # at or below 0: no code below it
        ov = vgrid.origin - vgrid.step * math.ceil(vgrid.origin / vgrid.step)
        ncu = math.floor((hi_u - ou) / grid.step + 0.5) // ku + 1
        ncv = math.floor((hi_v - ov) / vgrid.step + 0.5) // kv + 1
        cgrid = np.array([ou, 1.0 / grid.step, ov, 1.0 / vgrid.step, ku, kv], np.float64)
        cnt0, acc0, cnt1, acc1, fits = self._cell_buffers(ncu * ncv)
        # codes half way between two cells (pixels that dropped finest Gray bits) count half to each
        sums = K.cell_sums_split if split else K.cell_sums
        sums(
            u0,
            v0,
            mask0,
            self._rect0,
            self._knot_r0,
            u1,
            v1,
            mask1,
            self._rect_cam1(),
            1,
            cgrid,
            ncu,
            ncv,
            cnt0,
            acc0,
            cnt1,
            acc1,
        )
        radius = int(min(4, max(1, math.ceil(CELL_SPAN_PX / min(cell_u, cell_v)))))
        jump = 1.0 + 0.15 * max(cell_u, cell_v)
        raw = self._cell_planes(ncu, ncv)
        K.cell_raw(cnt0, acc0, cnt1, acc1, ncu, ncv, max(cell_u, cell_v) > CELL_EDGE_PX,
                   float(K.SPLIT_UNIT if split else 1), raw)  # fmt: skip
        K.cell_window(raw, radius, 1.0 + 0.15 * (2 * radius + 1) * max(cell_u, cell_v),
                      2 * numba.get_num_threads(), fits)  # fmt: skip
        K.cell_fits_robust(raw, ncu, ncv, jump, fits)
        own = 0.5 * math.hypot(cell_u, cell_v) + 1.0
        var_unit = self._cell_variance(raw, fits, ncu)
        cen_x, cen_y = raw[K.RAW_X].reshape(-1), raw[K.RAW_Y].reshape(-1)
        K.cell_match(u0, v0, mask0, self._rect0, self._knot_r0, cgrid, ncu, ncv, cen_x, cen_y, fits, own, var_unit,
                     self._geom, self._rr_t, self._c0, self._r0z, self._t0z, zmin, zmax, xyz, self._epi, self.sigma,
                     self._status, split)  # fmt: skip

    @staticmethod
    def _cell_variance(raw: F32, fits: F32, ncu: int, stride: int = 3) -> float:
        """Variance of a cell's disparity at unit weight (px^2), from this scan: the robust spread of the cells'
        disparities about their fitted planes (every ``stride``-th cell row, or sparser so that about
        2 x ``MOST_SAMPLES`` cells are read), at least ``CELL_VAR_FLOOR``."""
        stride = max(stride, -(-raw[K.RAW_W].size // (2 * MOST_SAMPLES)))
        w = raw[K.RAW_W, ::stride].ravel()
        d = raw[K.RAW_D, ::stride].ravel()
        f = fits.reshape(-1, ncu, K.FIT_COLS)[::stride, :, 0].ravel()
        ok = (w > 0) & np.isfinite(f)
        if ok.sum() < MIN_SAMPLES:
            return CELL_VAR_FLOOR
        z = w[ok].astype(np.float64) * (d[ok].astype(np.float64) - f[ok]) ** 2
        return max(CELL_VAR_FLOOR, float(np.median(z)) / 0.4549)  # the median of chi-square with 1 dof

    def _cell_planes(self, ncu: int, ncv: int) -> F32:
        got = self._cells.get("raw")
        if got is None or got.shape[1:] != (ncv, ncu):
            self._cells["raw"] = np.empty((K.N_RAW, ncv, ncu), np.float32)
        return self._cells["raw"]

    def _check(
        self,
        rep: StereoReport,
        grid: CodeGrid,
        vgrid: CodeGrid | None,
        xyz: F32,
        u0: F32,
        v0: F32,
        use_v: bool,
        cells: bool,
        rematch: Any,
    ) -> None:
        """The checks after matching: epipolar residuals (measured, corrected, limited), three-view, report."""
        dl = grid.step
        stated = _stated_rms(self.cam0, self.cam1)
        self.residuals = []
        zs = xyz[::16, ::16, 2]
        zmed = float(np.nanmedian(zs)) if np.isfinite(zs).any() else math.nan
        if use_v:
            ep = _sample(self._epi[::3, ::3], self._status[::3, ::3] == C.ST_OK)
            med, sig, n = _robust(ep)
            res = summarise("epipolar", f"{self.cam0.name}/{self.cam1.name}", ep, zmed * float(self._geom[3]))
            if res is not None:
                self.residuals.append(res)
            rep.epipolar = {"median_px": med, "spread_px": sig, "samples": float(n), "offset_px": 0.0}
            allowed = max(DRIFT_REFUSE_MIN_PX, DRIFT_REFUSE_FACTOR * stated)
            if self.drift == "refuse" and self.correct_epipolar and n >= MIN_SAMPLES and abs(med) > allowed:
                rep.epipolar["allowed_px"] = allowed
                rep.refused = (
                    f"{self.cam0.name}/{self.cam1.name}: the epipolar lines are off by a median {med:.1f} px, "
                    f"beyond the {allowed:.1f} px a drift may reach ({DRIFT_REFUSE_FACTOR:g}x the calibration's "
                    f"stated {stated:.2f} px RMS, at least {DRIFT_REFUSE_MIN_PX:g} px): this calibration does not "
                    "fit the rig, so no camera-camera points were written for this pair; recalibrate (scan3d "
                    "calibrate) or check that the calibration file belongs to this rig "
                    "(reconstruction.stereo_drift: correct bends it anyway)"
                )
                rep.warnings.append(rep.refused)
                kept = self._status == C.ST_OK  # every point of the pair goes, a NaN residual too
                xyz[kept] = np.nan
                self._status[kept] = C.ST_EPIPOLAR
                self.sigma[kept] = np.nan
                self._summarise(rep)
                return
            if self.correct_epipolar and n >= MIN_SAMPLES and abs(med) > max(EPIPOLAR_OFFSET_MIN_PX, 0.5 * sig):
                shift = self._fit_offset(med, sig)
                if cells:  # the match itself does not depend on the row: only the residuals move
                    K.sub_plane(self._epi, self._rect0, self._knot_r0, shift)
                else:
                    rematch(shift)
                med2, sig2, _ = _robust(_sample(self._epi[::3, ::3], self._status[::3, ::3] == C.ST_OK))
                mean_xy = self._rect0_every(1).mean(axis=(0, 1), dtype=np.float64)
                rep.epipolar.update(
                    {"offset_px": float(shift[0] + shift[1] * mean_xy[0] + shift[2] * mean_xy[1]),
                     "corrected_median_px": med2, "corrected_spread_px": sig2}
                )  # fmt: skip
                med, sig = med2, sig2
            if self.max_epipolar_px is not None:
                limit = float(self.max_epipolar_px)
            else:
                vq = 0.5 / vgrid.stripe_px if vgrid is not None and vgrid.quantised else 0.0
                limit = max(3.0 * stated, abs(med) + 5.0 * (sig if math.isfinite(sig) else 0.0) + vq, 0.5)
            rep.epipolar["limit_px"] = limit
            C.reject(xyz, self._epi, limit, C.ST_EPIPOLAR, self._status)
        if self.projector is not None:
            p = self.projector
            C.three_view_error(xyz, u0, v0, use_v, np.ascontiguousarray(p.R), np.ascontiguousarray(p.T),
                               np.ascontiguousarray(p.K), distortion12(p), self._err3)  # fmt: skip
            e3 = _sample(self._err3[::3, ::3], self._status[::3, ::3] == C.ST_OK)
            med3, sig3, n3 = _robust(e3)
            if self.max_code_err_px is not None:
                limit3 = float(self.max_code_err_px)
            else:
                limit3 = max(2.0, 0.5 * dl + 3.0 * _stated_rms(p), med3 + 5.0 * (sig3 if math.isfinite(sig3) else 0))
            rep.three_view = {"median_px": med3, "spread_px": sig3, "samples": float(n3), "limit_px": limit3}
            res = summarise("three_view", f"{self.cam0.name}/{self.cam1.name}/{p.name}", e3, zmed / float(p.K[0, 0]))
            if res is not None:
                self.residuals.append(res)
            C.reject(xyz, self._err3, limit3, C.ST_THREE_VIEW, self._status)
        self._summarise(rep)

    def filter_neighbours(
        self,
        xyz: F32,
        min_neighbours: int,
        const_mm: float,
        k_sigma: float,
        k_footprint: float,
        scratch: npt.NDArray[np.bool_],
    ) -> int:
        """Remove points of the last :meth:`triangulate` that their neighbours do not agree with, in place.

        Agreement is judged by the points' sigmas, and a missing neighbour counts neither way: a point is kept
        when at most ``8 - min_neighbours`` of its valid neighbours lie beyond the pair's jump limit (with 8: none;
        a mixed pixel on a depth edge goes) and at least ``min(min_neighbours, NEIGHBOURS_AGREE)`` lie within it
        (a lone point goes). So a hole in the matches does not grow by a pixel all round, as it did when a
        point needed 8 valid near neighbours.

        Parameters
        ----------
        xyz : ndarray, shape (H0, W0, 3), float32
            The organised cloud the last :meth:`triangulate` wrote.
        min_neighbours : int
            0..8; 0 keeps every point.
        const_mm, k_sigma, k_footprint : float
            The jump limit of a point and its neighbour: ``const_mm + k_sigma * hypot(sigma, sigma_nb) +
            k_footprint * z / f`` (mm; f of cam0, px).
        scratch : ndarray, shape (H0, W0), bool
            Work buffer.

        Returns
        -------
        int
            Points kept.
        """
        C.agree_keep_sigma(xyz, self.sigma, 8 - min_neighbours, min(min_neighbours, NEIGHBOURS_AGREE), const_mm,
                           k_sigma, k_footprint, 1.0 / float(self.cam0.K[0, 0]), math.inf, scratch)  # fmt: skip
        return self._apply(xyz, scratch)

    def filter_sigma(self, xyz: F32, max_sigma_mm: float, scratch: npt.NDArray[np.bool_]) -> int:
        """Remove points whose expected error (:attr:`sigma`) exceeds ``max_sigma_mm``, in place; points kept."""
        C.isolated_keep_sigma(xyz, self.sigma, 0, math.inf, 0.0, 0.0, 0.0, float(max_sigma_mm), scratch)
        return self._apply(xyz, scratch)

    def _apply(self, xyz: F32, keep: npt.NDArray[np.bool_]) -> int:
        kept = int(C.drop_unkept(xyz, self.sigma, keep))
        if self.report.both_seen:
            self.report.both_seen_points = int(C.count_points_in(xyz, self._seen))
        return kept

    @staticmethod
    def _noise_params(grid: CodeGrid, noise: CodeNoise | None, levels: int) -> F64:
        """(phase_px, var_quant_px2, var_intensity_dn2, 1 / e- per DN, 1 / level step) for the matcher."""
        if grid.quantised:
            # a boundary is known to a pixel / sqrt 12 in each camera; the local fit averages the boundaries
            # of (2 levels + 1) x (2 rows + 1) crossings, of which only one per pixel is independent when
            # stripes are narrower than a pixel
            n_eff = (2 * levels + 1) * min(1.0, grid.stripe_px) * (2 * SMOOTH_ROWS + 1)
            return np.array([0.0, 2.0 / 12.0 / max(n_eff, 1.0), 0.0, 0.0, 1.0])
        if noise is None or noise.phase_px <= 0.0:
            return np.array([math.nan, 0.0, 0.0, 0.0, 1.0 / grid.step])
        p = noise.params()
        return np.array([p[0], 0.0, p[2], p[3], 1.0 / grid.step])

    def _fit_offset(self, med: float, sig: float) -> F64:
        """Plane ``s0 + sx x + sy y`` (rectified px) through the epipolar residuals near their median."""
        ok = self._status[::4, ::4] == C.ST_OK
        e = self._epi[::4, ::4][ok].astype(np.float64)
        grid = self._rect0_every(4)
        x = grid[..., 0][ok].astype(np.float64)
        y = grid[..., 1][ok].astype(np.float64)
        good = np.isfinite(e) & (np.abs(e - med) <= max(3.0 * sig, 0.5))
        if good.sum() < MIN_SAMPLES:
            return np.array([med, 0.0, 0.0])
        a = np.stack([np.ones(int(good.sum())), x[good], y[good]], 1)
        coef, *_ = np.linalg.lstsq(a, e[good], rcond=None)
        return np.asarray(coef, np.float64)

    def _summarise(self, rep: StereoReport) -> None:
        counts = C.status_counts(self._status, _N_STATUS, self._counts).sum(axis=0)
        rep.candidates = int(counts[1:].sum())
        rep.points = int(counts[C.ST_OK])
        rep.rejected = {STAGES[s]: int(counts[s]) for s in STAGES}
        if rep.candidates == 0:
            return
        names = f"{self.cam0.name}/{self.cam1.name}"
        epi = rep.epipolar
        for s, words in STAGES.items():
            share = counts[s] / rep.candidates
            if share <= MOST or (s == C.ST_EPIPOLAR and rep.refused):  # a refused pair says it once
                continue
            if s == C.ST_EPIPOLAR:
                rep.warnings.append(
                    f"{names}: {100 * share:.0f} % of camera-camera matches lie a median "
                    f"{abs(epi.get('median_px', math.nan)):.1f} px off the epipolar line (limit "
                    f"{epi.get('limit_px', math.nan):.1f}): the calibration may no longer fit the rig; "
                    "run scan3d verify or recalibrate"
                )
            elif s == C.ST_THREE_VIEW:
                rep.warnings.append(
                    f"{names}: {100 * share:.0f} % of points do not project onto their projector code "
                    f"(median {rep.three_view.get('median_px', math.nan):.1f} px, limit "
                    f"{rep.three_view.get('limit_px', math.nan):.1f}): the projector's calibration may no "
                    "longer fit the cameras; run scan3d verify or recalibrate"
                )
            elif s == C.ST_OUTSIDE:
                rep.warnings.append(
                    f"{names}: {100 * share:.0f} % of decoded pixels lie outside the rows both cameras see: "
                    "the cameras barely overlap, or the calibration does not belong to this rig"
                )
            elif s == C.ST_DEPTH:
                rep.warnings.append(
                    f"{names}: {100 * share:.0f} % of matches fall outside the depth range: check "
                    "reconstruction.min_depth_mm / max_depth_mm, or the calibration's baseline"
                )
            else:
                rep.warnings.append(
                    f"{names}: {100 * share:.0f} % of decoded pixels rejected: {words}; the two cameras may "
                    "see different parts of the scene, or the calibration does not fit the rig"
                )
        off = epi.get("offset_px", 0.0)
        if abs(off) > 1.0:
            rep.warnings.append(
                f"{names}: the epipolar lines are off by {off:.1f} px (corrected from this scan's matches): the "
                "calibration has drifted; run scan3d verify or recalibrate"
            )


def triangulate_stereo(
    maps0: DecodedMaps,
    maps1: DecodedMaps,
    cam0: CameraModel,
    cam1: CameraModel,
    max_epipolar_px: float | None = None,
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
    max_epipolar_px : float, optional
        With v coded: fixed epipolar limit (px); default from the calibration and the data.
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
