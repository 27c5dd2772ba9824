"""Reconstruction of one scan: decoded maps -> triangulation -> filters -> PointCloud.

Camera-projector reconstruction goes through one depth pass per camera
(:meth:`~appliance.reconstruct.triangulate.ProjectorTriangulator.triangulate_depth`): depth, the 1-sigma
error of every point, the depth range, the sigma filter and the neighbour filter, whose jump limit follows
from each point's expected error and pixel footprint, so that one default holds at 0.3 m and at 4 m.
Each stage's rejections are counted (:class:`~appliance.reconstruct.types.StageCounts`), and a stage that
rejects most of its candidates is said in plain words. :meth:`Reconstructor.run` returns everything one scan
produced as one frozen :class:`Reconstruction` record; the reconstructor keeps only its tables and buffers.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError, ScanError
from appliance.geometry.calibration_file import Calibration
from appliance.geometry.rays import RayTable
from appliance.patterns.sequence import Sequence
from appliance.reconstruct._pool import BufferPool
from appliance.reconstruct.albedo_edges import AlbedoEdges
from appliance.reconstruct.decode_batch import nan_map
from appliance.reconstruct.filters import estimate_normals, to_point_cloud
from appliance.reconstruct.fuse import fuse_points_into
from appliance.reconstruct.residuals import Residual, decoded_ray_ray_residual
from appliance.reconstruct.settings import ReconstructionSettings
from appliance.reconstruct.stereo import StereoTriangulator
from appliance.reconstruct.triangulate import EPIPOLAR_SIGMAS, ProjectorTriangulator
from appliance.reconstruct.types import DecodedMaps, PointCloud, Reason, StageCounts
from appliance.reconstruct.uncertainty import CodeNoise, code_noise_for_sequence
from appliance.reconstruct.visibility import ProjectorVisibility
from appliance.reconstruct.walled import drop_isolated, drop_walled

F32 = npt.NDArray[np.float32]

MOST_REJECTED = 0.5
MOST_UNDECODED = 0.9
"""The decode stage is said only beyond this share: an object on a dark background leaves most pixels unlit."""
"""A stage that rejects more than this share of its candidates is reported in words."""
EPIPOLAR_SAID = 0.02
"""Both axes coded: a share of the triangulated points off their epipolar lines beyond this is said in words."""
EPIPOLAR_CALIBRATION = 0.5
"""... and beyond this share it more likely means a calibration that no longer fits than reflections."""
FIXED_JUMP_MM = 2.0
"""Jump limit (plus two footprints) where no per-point error is known (stereo, or no sequence given)."""


MODES = ("projector", "stereo", "both")
"""Reconstruction modes: camera-projector, camera-camera, or both fused."""


def white_to_uint8(img: npt.NDArray[np.generic], bits: int | None = None) -> npt.NDArray[np.uint8]:
    """A grey image in the sensor's digital numbers -> 0..255, the one conversion of every path.

    Parameters
    ----------
    img : ndarray, shape (H, W) or (H, W, 3)
        Grey (or colour, averaged) image; uint8, uint16 or float (DN).
    bits : int, optional
        Significant bits of the sensor (full scale ``2**bits - 1`` becomes 255). Default: 8 for uint8 and
        float images, 16 for uint16.

    Returns
    -------
    ndarray, shape (H, W), uint8
        ``round(img * 255 / (2**bits - 1))``, clipped to 0..255.
    """
    if img.ndim == 3:
        img = img.mean(axis=2, dtype=np.float32)
    if bits is None:
        bits = 16 if img.dtype == np.uint16 else 8
    if img.dtype == np.uint8 and bits == 8:
        return np.ascontiguousarray(img, np.uint8)
    scale = 255.0 / float((1 << bits) - 1)
    return np.asarray(np.clip(np.asarray(img, np.float32) * scale + 0.5, 0, 255), np.uint8)


def _as_uint8(img: npt.NDArray[np.generic], shape: tuple[int, int], name: str) -> npt.NDArray[np.uint8]:
    if img.shape[:2] != shape:
        raise ScanError(f"white image of {name}: shape {img.shape}: must be {shape} (H, W)")
    return white_to_uint8(img)


def _reason_map(maps: DecodedMaps) -> npt.NDArray[np.uint8] | None:
    """The decoder's reason map, which the reconstruction completes in place (later stages add their reasons
    on the decoded pixels that gave no point); None when the decode has none or it cannot be written."""
    r = maps.reason
    if r is None or r.shape != maps.shape or r.dtype != np.uint8 or not r.flags.c_contiguous or not r.flags.writeable:
        return None
    return r


def _stereo_reasons(reason: npt.NDArray[np.uint8] | None, matched: npt.NDArray[np.bool_], z: F32) -> None:
    """Camera-camera (organised on the reference camera): decoded pixels without a match are ``NOT_MATCHED``,
    matched ones the filters removed ``FILTERED``, pixels with a point ``DECODED``."""
    if reason is None:
        return
    decoded = reason == Reason.DECODED
    reason[decoded & ~matched] = Reason.NOT_MATCHED
    reason[decoded & matched] = Reason.FILTERED
    reason[np.isfinite(z)] = Reason.DECODED


def available_modes(calibration: Calibration, cameras: Iterable[str] | None = None) -> tuple[str, ...]:
    """The reconstruction modes a calibration supports for ``cameras`` (default: all its cameras).

    A projector allows ``'projector'``; two cameras allow ``'stereo'``; both allow ``'both'``.
    """
    names = calibration.camera_names if cameras is None else [c for c in cameras if c in calibration.devices
                                                               and c in calibration.camera_names]  # fmt: skip
    has_projector = calibration.projector is not None
    return tuple(m for m, ok in (("projector", has_projector), ("stereo", len(names) >= 2),
                                 ("both", has_projector and len(names) >= 2)) if ok)  # fmt: skip


@dataclass(frozen=True)
class Reconstruction:
    """Everything one :meth:`Reconstructor.run` produced (the reconstructor keeps none of it).

    Attributes
    ----------
    cloud : PointCloud
        Points of every output camera, world frame (mm).
    timings_ms : dict of str to float
        ``triangulate_ms``, ``filter_ms``, ``cloud_ms``, ``total_ms``.
    stages : tuple of StageCounts
        Per output camera, what each stage rejected.
    warnings : tuple of str
        Plain-words warnings (see :func:`stage_warnings`, the matcher's and the fusion's).
    residuals : tuple of Residual
        The calibration-health inputs: residuals wherever the scan was overdetermined (both projector axes,
        two cameras with rows coded, two cameras and a projector).
    fusion : dict of str to int
        Mode ``'both'``: reference-camera pixels by source (see ``fuse_points_into``); else empty.
    stereo : dict, optional
        What the camera-camera matcher did, stage by stage (modes ``'stereo'`` and ``'both'``).
    edge_corrected : dict of str to int
        Per camera-projector camera, the pixels whose code the albedo-edge correction moved by more than
        ``albedo_edges.REPORT_SHIFT_PX`` (absent: no correction ran).
    """

    cloud: PointCloud
    timings_ms: dict[str, float]
    stages: tuple[StageCounts, ...] = ()
    warnings: tuple[str, ...] = ()
    residuals: tuple[Residual, ...] = ()
    fusion: dict[str, int] = field(default_factory=dict)
    stereo: dict[str, object] | None = None
    edge_corrected: dict[str, int] = field(default_factory=dict)


def stage_warnings(stages: list[StageCounts], cfg: ReconstructionSettings) -> list[str]:
    """Plain-words warnings for every stage that rejected most (> :data:`MOST_REJECTED`) of its candidates.

    Parameters
    ----------
    stages : list of StageCounts
        Per camera counts of one reconstruction.
    cfg : ReconstructionSettings
        The settings the limits came from (named in the messages).

    Returns
    -------
    list of str
        One line per offending (camera, stage), naming the share, the limit and what to do.
    """
    out: list[str] = []
    for st in stages:
        n = st.remaining()
        for i, (stage, lost) in enumerate(st.rejected().items()):
            limit = MOST_UNDECODED if stage == "decode" else EPIPOLAR_SAID if stage == "epipolar" else MOST_REJECTED
            if n[i] == 0 or lost <= limit * n[i]:
                continue
            pct = f"{100.0 * lost / n[i]:.0f} %"
            cam = st.camera
            if stage == "decode":
                msg = (f"{pct} of camera {cam}'s pixels decoded no code (shadow, unlit background or contrast "
                       f"under reconstruction.min_contrast_dn = {cfg.min_contrast_dn:g} / relative_contrast = "
                       f"{cfg.relative_contrast:g}): check exposure, focus and that the projector lights the object")
            elif stage == "geometry":
                msg = (f"{pct} of camera {cam}'s decoded pixels gave no point (codes off the projector's image, "
                       "rays along the coded light planes, points behind a device): the calibration may not fit "
                       "this rig or sequence; run scan3d verify or recalibrate")
            elif stage == "epipolar":
                msg = epipolar_warning(cam, lost, n[i])
            elif stage == "depth_range":
                msg = (f"{pct} of camera {cam}'s points lie outside reconstruction.min_depth_mm .. max_depth_mm = "
                       f"{cfg.min_depth_mm:g} .. {cfg.max_depth_mm:g} mm: widen the range to where the object is")
            elif stage == "sigma":
                msg = (f"{pct} of camera {cam}'s points have an expected error over reconstruction.max_sigma_mm = "
                       f"{cfg.max_sigma_mm} mm: raise it, or give the scan more contrast (exposure, projector "
                       "brightness, a finer phase period)")
            elif cfg.max_neighbour_jump_mm is not None:
                msg = (f"{pct} of camera {cam}'s points have fewer than reconstruction.min_neighbours = "
                       f"{cfg.min_neighbours} of 8 neighbours within the fixed max_neighbour_jump_mm = "
                       f"{cfg.max_neighbour_jump_mm:g} mm: the limit is below this scan's depth noise; unset it "
                       "(limits from each point's expected error) or raise it")
            else:
                msg = (f"{pct} of camera {cam}'s points have fewer than reconstruction.min_neighbours = "
                       f"{cfg.min_neighbours} of 8 neighbours within their jump limit: the surface is noisy or "
                       "fragmented (focus, camera noise settings); lower min_neighbours or raise "
                       "neighbour_jump_sigmas")
            out.append(msg)
    return out


def epipolar_warning(camera: str, dropped: int, triangulated: int) -> str:
    """The plain-words line for points dropped off their epipolar lines (both projector axes coded).

    A minority points at reflections (a second copy of the pattern), not at the calibration, which the
    consistent pixels still judge; most of them at the calibration (then every pixel misses its line).
    """
    pct = f"{100.0 * dropped / triangulated:.0f} %" if dropped >= 0.01 * triangulated else \
        f"{100.0 * dropped / triangulated:.1f} %"  # fmt: skip
    if dropped > EPIPOLAR_CALIBRATION * triangulated:
        return (f"{pct} of camera {camera}'s decoded pixels lie off their epipolar lines: more than reflections "
                "would, so the check was not applied (the points are kept for the calibration health to judge); "
                "the calibration may no longer fit the rig: run scan3d verify or recalibrate")
    return (f"{pct} of camera {camera}'s decoded pixels were left out as lit a second time by reflected light "
            "(their code lies off the pixel's epipolar line: a mirror-like or glossy surface re-projects the "
            "pattern), not for a calibration fault: the calibration health judges the consistent pixels only. "
            "Dull or tilt the shiny surface, or scan it from another side")


INDIRECT_WARN_SHARE = 0.2
"""A camera whose points got a widened sigma for indirect light (``indirect_sigma``) in at least this share is
told in words."""


def indirect_warning(camera: str, widened: int, points: int, dropped: int, max_sigma_mm: float | None) -> str:
    """The plain-words line for a scan whose points are largely lit by light that came another way."""
    pct = f"{100.0 * widened / max(points, 1):.0f} %"
    tail = (f"; {dropped} of them exceeded reconstruction.max_sigma_mm = {max_sigma_mm} mm and were dropped"
            if dropped else "; set reconstruction.max_sigma_mm to drop the worst")
    return (f"{pct} of camera {camera}'s points are lit partly by light that came another way (their pattern "
            "contrast is more than 10 % below the scan's median: interreflection in a concave part, a translucent "
            f"material): their sigma says how far that light may shift them{tail}. Matte spray or another view "
            "angle helps")


REFLECTION_SHARE = 1e-3
"""``hidden_check: auto`` runs the projector visibility check when at least this share of a camera's decoded pixels
shows a reflection: a normal scene's stray blends stay near 1e-4 (the bench's 2 x 5 MP scene: 0.007 %), a
mirror-like face in view gives percents (the mirror groove: 20 %)."""


class Reconstructor:
    """Turns the decoded maps of one scan into a point cloud; every table is built once, here.

    Parameters
    ----------
    calibration : Calibration
        The rig (cameras in order; the projector for mode ``'projector'``).
    axes : {'x', 'y', 'xy'}
        Coded projector axes (``'x'``/``'y'``: ray / light-surface, ``'xy'``: ray-ray).
    cfg : ReconstructionSettings
        ``mode`` ``'projector'`` (every camera with the projector, clouds concatenated, camera index per
        point) or ``'stereo'`` (the first two cameras, cloud organised on the first), depth range, filters,
        camera noise.
    sequence : Sequence, optional
        The projected sequence: with it (mode ``'projector'``) every point gets its expected error
        ``sigma_mm`` (:mod:`appliance.reconstruct.uncertainty`, camera noise from ``cfg``), and the
        neighbour filter's limits follow from it; without it sigma is NaN and the jump limit fixed.
    noise : CodeNoise, optional
        The code noise model itself (overrides ``sequence``).

    Raises
    ------
    CalibrationError
        When the calibration lacks what the mode needs or its geometry cannot triangulate the axes.
    """

    def __init__(
        self,
        calibration: Calibration,
        axes: str,
        cfg: ReconstructionSettings,
        sequence: Sequence | None = None,
        noise: CodeNoise | None = None,
    ) -> None:
        self.calibration, self.axes, self.cfg = calibration, axes, cfg
        names = calibration.camera_names
        if not names:
            raise CalibrationError("calibration holds no camera")
        if noise is None and sequence is not None:
            # both axes coded: the finer code of the two stands for both
            cands = [code_noise_for_sequence(sequence, a, cfg.camera_read_noise_dn, cfg.camera_electrons_per_dn)
                     for a in axes]  # fmt: skip
            noise = min(cands, key=lambda c: c.phase_px if c.phase_px > 0 else c.stripe_px)
        self.noise = noise
        self._proj_tri: dict[str, ProjectorTriangulator] = {}
        self._stereo: StereoTriangulator | None = None
        modes = available_modes(calibration)
        if cfg.mode in ("projector", "both"):
            projector = calibration.projector
            if projector is None or "projector" not in modes:
                raise CalibrationError(
                    f"reconstruction.mode = {cfg.mode}: the calibration has no 'projector'; "
                    "calibrate it or use mode stereo"
                )
            first: ProjectorTriangulator | None = None
            for n in names:  # the projector's table is built once, for every camera
                first = self._proj_tri[n] = ProjectorTriangulator(calibration.devices[n], projector, axes, like=first)
            self.outputs = list(names)
        if cfg.mode in ("stereo", "both"):
            if "stereo" not in modes:
                raise CalibrationError(
                    f"reconstruction.mode = {cfg.mode}: needs two cameras, the calibration has {names}"
                )
            cam0, cam1 = calibration.devices[names[0]], calibration.devices[names[1]]
            self._stereo = StereoTriangulator(
                cam0,
                cam1,
                self._proj_tri[names[0]].rays if names[0] in self._proj_tri else RayTable(cam0),  # one table a camera
                max_epipolar_px=cfg.stereo_max_epipolar_px,
                projector=calibration.projector,
                drift=cfg.stereo_drift,
            )
            if cfg.mode == "stereo":
                self.outputs = [names[0]]
        self._depth_path = cfg.mode in ("projector", "both")
        # clouds are views of blocks reused once the caller drops them (saves the page faults of ~26 B/point)
        self._pool = BufferPool()
        self._xyz: dict[str, F32] = {}
        self._depth: dict[str, F32] = {}
        self._sigma: dict[str, F32] = {}
        self._counts: dict[str, npt.NDArray[np.int64]] = {}
        self._stats: dict[str, npt.NDArray[np.int64]] = {}
        self._spans: dict[str, npt.NDArray[np.int64]] = {}
        self._bias_dropped: dict[str, npt.NDArray[np.int64]] = {}
        self._bias_widened: dict[str, npt.NDArray[np.int64]] = {}
        self._edge: dict[str, AlbedoEdges] = {}
        self.edge_corrected: dict[str, int] = {}
        """Per camera the pixels whose code the last run corrected for an albedo edge (absent: no correction)."""
        self.fringe_median: dict[str, float] = {}
        """Per camera the median fringe share (0..1) the last run's indirect-light term used (absent: none)."""
        self._scratch: dict[str, npt.NDArray[np.bool_]] = {}
        self._normals: dict[str, F32] = {}
        self._jump: dict[str, tuple[float, float, float]] = {}
        for n in self.outputs:
            cam = calibration.devices[n]
            # (constant mm, pixel footprints, sigmas) of each point's jump limit
            # stereo points always carry a sigma (the matcher's own model for quantised codes)
            knows_sigma = self.noise is not None or not self._depth_path
            if cfg.max_neighbour_jump_mm is not None or not knows_sigma:
                # neighbours are a pixel apart: allow the diagonal footprint of a pixel at mid range on top
                const = cfg.max_neighbour_jump_mm if cfg.max_neighbour_jump_mm is not None else FIXED_JUMP_MM
                footprint_mm = 0.5 * (cfg.min_depth_mm + cfg.max_depth_mm) / float(cam.K[0, 0])
                self._jump[n] = (const + 2.0 * footprint_mm, 0.0, 0.0)
            else:
                self._jump[n] = (0.0, cfg.neighbour_jump_footprints, cfg.neighbour_jump_sigmas)
            if self._depth_path:
                self._depth[n] = np.full((cam.height, cam.width), np.nan, np.float32)
                self._sigma[n] = np.full((cam.height, cam.width), np.nan, np.float32)
                self._counts[n] = np.zeros(cam.height + 1, np.int64)
                self._stats[n] = np.zeros((cam.height, 6), np.int64)
                self._spans[n] = np.zeros((cam.height, 2), np.int64)
                self._bias_dropped[n] = np.zeros(cam.height, np.int64)
                self._bias_widened[n] = np.zeros(cam.height, np.int64)
                if cfg.edge_blur_px > 0:
                    self._edge[n] = AlbedoEdges(cam.height)
            else:
                self._xyz[n] = np.empty((cam.height, cam.width, 3), np.float32)
                self._scratch[n] = np.empty((cam.height, cam.width), np.bool_)
            if cfg.normals:
                self._normals[n] = np.empty((cam.height, cam.width, 3), np.float32)
        if cfg.mode == "both":  # the reference camera's camera-camera estimate, fused into its depth map
            cam = calibration.devices[names[0]]
            self._xyz[names[0]] = np.empty((cam.height, cam.width, 3), np.float32)
            self._scratch[names[0]] = np.empty((cam.height, cam.width), np.bool_)
        self._visibility: ProjectorVisibility | None = None
        if self._depth_path and cfg.hidden_check != "off" and calibration.projector is not None:
            self._visibility = ProjectorVisibility(calibration.projector, self._proj_tri)
        self.hidden: dict[str, int] = {}
        """Points the projector visibility check dropped in the last scan, per camera."""
        if self._depth_path and axes != "xy":  # a scan reads the row tables only (xy: the residual reads all)
            for tri in self._proj_tri.values():
                tri.rays.row_table()
                tri.rays.release()

    def warm_up(self) -> None:
        """Compile (or load from the cache) the camera-camera matcher's kernels, before the first scan.

        Modes ``'stereo'`` and ``'both'``: a run on blank frames decodes nothing and the matcher stops before
        its kernels, so they would be compiled inside the first scan (a minute on a fresh clone). Here they
        run on synthetic codes of the cameras' sizes (a ramp of 0.9 projector px per pixel; stripe centres
        when the sequence is Gray only; rows too when both axes are coded).
        """
        if self._stereo is None:
            return
        quantised = self.noise is None or self.noise.phase_px <= 0.0
        names = self.calibration.camera_names
        maps = []
        for n in names[:2]:
            cam = self.calibration.devices[n]
            h, w = cam.height, cam.width
            u = np.empty((h, w), np.float32)
            u[...] = np.arange(w, dtype=np.float32) * np.float32(0.9)
            coded = [u]
            if "y" in self.axes:
                v = np.empty((h, w), np.float32)
                v[...] = (np.arange(h, dtype=np.float32) * np.float32(0.9))[:, None]
                coded.append(v)
            else:
                v = nan_map((h, w))  # the decoder's own shared read-only map: the variants a scan compiles
            if quantised:  # stripes of 2 projector px
                for c in coded:
                    np.floor(c * np.float32(0.5), out=c)
                    c *= np.float32(2.0)
                    c += np.float32(1.0)
            maps.append(DecodedMaps(u, v, np.ones((h, w), np.bool_), np.full((h, w), 50.0, np.float32)))
        self._stereo.triangulate(maps[0], maps[1], self._xyz[names[0]], self.cfg.min_depth_mm, self.cfg.max_depth_mm,
                                 self.noise)  # fmt: skip

    def _correct_edges(self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None) -> None:
        """Correct each camera-projector camera's codes, in place until :meth:`_restore_edges`, for the light
        albedo edges blur into a pixel (:mod:`appliance.reconstruct.albedo_edges`): with a phase code and a
        white-light level (the maps' ``radiance``, else the white image)."""
        self.edge_corrected = {}
        if not self._edge or self.noise is None or self.noise.phase_px <= 0:
            return
        for n, edges in self._edge.items():
            m = maps[n]
            level = m.radiance if m.radiance is not None else (None if white is None else white.get(n))
            if level is None:
                continue
            edges.apply(m, level, self.cfg.edge_blur_px, self.axes)
            self.edge_corrected[n] = edges.moved

    def _restore_edges(self) -> None:
        """The decoded codes as the caller gave them again."""
        for edges in self._edge.values():
            edges.restore()

    def _indirect_bias(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None, max_sigma: float
    ) -> None:
        """Every camera's sigma widened by the bias of indirect light and the albedo-edge correction's
        uncertainty (after the checks, which judge noise)."""
        for n, tri in self._proj_tri.items():
            dropped = self._bias_dropped[n]
            edges = self._edge.get(n) if n in self.edge_corrected else None
            extra = _extra_variance(None if edges is None else (edges.offsets, edges.cols, edges.variance),
                                    maps[n].separated, maps[n].shape)  # fmt: skip
            median = tri.indirect_bias(maps[n], self._depth[n], self._sigma[n], self.noise,
                                       None if white is None else white.get(n), dropped, max_sigma,
                                       _reason_map(maps[n]), self._bias_widened[n], self.cfg.indirect_sigma,
                                       extra)  # fmt: skip
            if median is None:
                continue
            if median > 0:
                self.fringe_median[n] = median
            total = int(dropped.sum())
            if total:
                self._counts[n][1:] -= dropped
                self._stats[n][:, 5] -= dropped

    def _shows_reflections(self, maps: dict[str, DecodedMaps]) -> bool:
        """Whether the last depth pass saw reflections (``hidden_check: auto``): at least :data:`REFLECTION_SHARE`
        of some camera's decoded pixels lit by two copies of the pattern, or (both axes) off their epipolar lines."""
        for n in self._proj_tri:
            s = self._stats[n].sum(axis=0)
            codes = maps[n].blend_codes
            blends = 0 if codes is None else len(codes)
            if blends and blends >= REFLECTION_SHARE * (int(s[0]) + blends):
                return True
            if self.axes == "xy" and int(s[1]) - int(s[2]) >= max(1.0, REFLECTION_SHARE * int(s[1])):
                return True
        return False

    def _fuse_stereo(self, maps: dict[str, DecodedMaps]) -> dict[str, int]:
        """Mode ``'both'``: camera-camera on the reference camera, fused with its camera-projector depth by
        inverse-variance weighting; pixels where the two disagree beyond 3 sigma are left out (counted)."""
        assert self._stereo is not None
        cfg = self.cfg
        n0, n1 = self.calibration.camera_names[0], self.calibration.camera_names[1]
        xyz = self._xyz[n0]
        self._stereo.triangulate(maps[n0], maps[n1], xyz, cfg.min_depth_mm, cfg.max_depth_mm, self.noise)
        const, fp, ks = self._jump[n0]
        self._stereo.filter_neighbours(xyz, cfg.min_neighbours, const, ks, fp, self._scratch[n0])
        if cfg.max_sigma_mm is not None:
            self._stereo.filter_sigma(xyz, cfg.max_sigma_mm, self._scratch[n0])
        cam = self.calibration.devices[n0]
        # in place, one pass: fusion drops disagreeing pixels (reason filtered) and adds camera-camera-only ones
        return fuse_points_into(self._depth[n0], self._sigma[n0], xyz, self._stereo.sigma, cam.R[2], float(cam.T[2]),
                                self._counts[n0], _reason_map(maps[n0]), (Reason.DECODED, Reason.FILTERED))

    def _stereo_report(self) -> dict[str, object] | None:
        return None if self._stereo is None else self._stereo.report.as_dict()

    def organised(self, name: str) -> F32:
        """The organised cloud (H, W, 3) of camera ``name`` from the last :meth:`run` (reused buffer).

        In mode ``'projector'`` the cloud is built from the depth map (on this call, unless normals were
        estimated, which needed it already).
        """
        if self._depth_path:
            cam = self.calibration.devices[name]
            if name not in self._xyz:
                self._xyz[name] = np.empty((cam.height, cam.width, 3), np.float32)
            self._proj_tri[name].organised_from_depth(self._depth[name], self._xyz[name])
        return self._xyz[name]

    def sigma_map(self, name: str) -> F32:
        """The per-pixel 1-sigma error (H, W, mm) of camera ``name`` from the last :meth:`run` (NaN: none)."""
        if not self._depth_path:
            raise ScanError("reconstruct: per-pixel sigma exists in mode projector only")
        return self._sigma[name]

    def run(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None = None
    ) -> Reconstruction:
        """Reconstruct one scan.

        Parameters
        ----------
        maps : dict of str to DecodedMaps
            Decoded maps per camera name (both cameras in mode ``'stereo'``).
        white : dict of str to ndarray (H, W), optional
            Image under white light per camera (DN of the frames), for the per-point intensity and the
            shot noise of the per-point error.

        Returns
        -------
        Reconstruction
            The cloud (every output camera, world frame, mm, with source pixel, camera index and ``sigma_mm``),
            the timings (in mode ``'projector'`` the filters run inside triangulation: ``filter_ms`` is the
            normals' time, or 0), what each stage rejected, the warnings and the residuals.
        """
        needed = list(self.outputs)
        if self._stereo is not None:
            needed += [n for n in self.calibration.camera_names[:2] if n not in needed]
        for n in needed:
            if n not in maps:
                raise ScanError(f"reconstruct: no decoded maps for camera {n!r} (have {sorted(maps)})")
        if self._depth_path:
            return self._run_depth(maps, white)
        return self._run_stereo(maps, white)

    def _run_stereo(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None
    ) -> Reconstruction:
        cfg = self.cfg
        assert self._stereo is not None
        t0 = time.perf_counter()
        n0, n1 = self.calibration.camera_names[0], self.calibration.camera_names[1]
        xyz = self._xyz[n0]
        self._stereo.triangulate(maps[n0], maps[n1], xyz, cfg.min_depth_mm, cfg.max_depth_mm, self.noise)
        if self._stereo.report.refused:  # the only pair: nothing to write
            raise ScanError(self._stereo.report.refused)
        t1 = time.perf_counter()
        matched_map = np.isfinite(xyz[..., 2])
        matched = int(np.count_nonzero(matched_map))
        const, fp, ks = self._jump[n0]
        sigma = self._stereo.sigma
        with_nb = self._stereo.filter_neighbours(xyz, cfg.min_neighbours, const, ks, fp, self._scratch[n0])
        kept = with_nb
        if cfg.max_sigma_mm is not None:
            kept = self._stereo.filter_sigma(xyz, cfg.max_sigma_mm, self._scratch[n0])
        jump = const if const > 0 else FIXED_JUMP_MM
        if cfg.normals:
            eye = self.calibration.devices[n0].center
            r = cfg.normal_radius_px
            estimate_normals(self._xyz[n0], eye, self._normals[n0], r, r * jump)
        _stereo_reasons(_reason_map(maps[n0]), matched_map, xyz[..., 2])
        t2 = time.perf_counter()
        shape = self._xyz[n0].shape[:2]
        inten = None if white is None or n0 not in white else _as_uint8(white[n0], (shape[0], shape[1]), n0)
        cloud = to_point_cloud(xyz, maps[n0].quality, inten, 0, self._normals.get(n0), sigma)
        t3 = time.perf_counter()
        rep = self._stereo.report
        h, w = xyz.shape[:2]
        # geometry: matched (the matcher's own stages are in stereo_report); depth range is inside the matcher
        stages = (StageCounts(n0, h * w, rep.candidates, matched, matched, with_nb, kept),)
        warnings = (*rep.warnings, *stage_warnings(list(stages), cfg))
        timings = {
            "triangulate_ms": 1e3 * (t1 - t0),
            "filter_ms": 1e3 * (t2 - t1),
            "cloud_ms": 1e3 * (t3 - t2),
            "total_ms": 1e3 * (t3 - t0),
        }
        return Reconstruction(cloud, timings, stages, warnings, tuple(self._stereo.residuals), {},
                              self._stereo_report())  # fmt: skip

    def _run_depth(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None
    ) -> Reconstruction:
        """Depth, sigma and filters per camera (one pass), then every kept point into one cloud (one pass)."""
        cfg = self.cfg
        max_sigma = math.inf if cfg.max_sigma_mm is None else cfg.max_sigma_mm
        t0 = time.perf_counter()
        self._correct_edges(maps, white)
        try:
            return self._run_depth_corrected(maps, white, max_sigma, t0)
        finally:
            self._restore_edges()

    def _run_depth_corrected(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None, max_sigma: float,
        t0: float,
    ) -> Reconstruction:
        """:meth:`_run_depth` once the codes are corrected for albedo edges."""
        cfg = self.cfg
        unchecked: dict[str, tuple[int, int]] = {}
        for n, tri in self._proj_tri.items():
            const, fp, ks = self._jump[n]
            for epi_sigmas in (EPIPOLAR_SIGMAS, math.inf):
                tri.triangulate_depth(
                    maps[n], self._depth[n], cfg.min_depth_mm, cfg.max_depth_mm, cfg.min_neighbours, const,
                    self._counts[n], noise=self.noise, white=None if white is None else white.get(n),
                    sigma_out=self._sigma[n], jump_footprints=fp, jump_sigmas=ks, max_sigma_mm=max_sigma,
                    stats=self._stats[n], spans=self._spans[n], reason_out=_reason_map(maps[n]),
                    epipolar_sigmas=epi_sigmas,
                )  # fmt: skip
                tri_n, cons_n = int(self._stats[n][:, 1].sum()), int(self._stats[n][:, 2].sum())
                if self.axes != "xy" or tri_n - cons_n <= EPIPOLAR_CALIBRATION * tri_n or unchecked.get(n):
                    break
                # most pixels off their lines is no reflection but a calibration that no longer fits: keep the
                # points (as one axis would) so that the calibration health judges them all, and say so
                unchecked[n] = (tri_n - cons_n, tri_n)
        self.hidden = {}
        # not where most pixels lie off their epipolar lines: the calibration no longer fits (said below), and the
        # check's geometry is the calibration's
        reasons = {n: _reason_map(maps[n]) for n in self._proj_tri}
        if self._visibility is not None and not unchecked and (
            cfg.hidden_check == "always" or self._shows_reflections(maps)
        ):
            self.hidden = self._visibility.apply(self._depth, self._sigma, self._counts, self._stats, reasons,
                                                 {n: maps[n].blend_codes for n in self._proj_tri})  # fmt: skip
            # the band next to a mirror's corner line where the two copies coincide: walled in by what was dropped
            for n, r_map in reasons.items():
                if r_map is not None:
                    drop_walled(self._depth[n], self._sigma[n], r_map, self._counts[n], self._stats[n],
                                maps[n].separated)  # fmt: skip
        if cfg.min_neighbours > 0:
            # a point the one-pass neighbour filter and the checks after it left without any neighbour
            for n, r_map in reasons.items():
                drop_isolated(self._depth[n], self._sigma[n], r_map, self._counts[n], self._stats[n])
        self.fringe_median = {}
        if cfg.indirect_sigma or self.edge_corrected or any(
            maps[n].separated is not None for n in self._proj_tri
        ):
            self._indirect_bias(maps, white, max_sigma)
        fusion = self._fuse_stereo(maps) if self._stereo is not None else {}
        t1 = time.perf_counter()
        stages = []
        for n in self.outputs:
            s = self._stats[n].sum(axis=0)
            h, w = self._depth[n].shape
            cons = int(s[2]) if self.axes == "xy" else None
            stages.append(StageCounts(n, h * w, int(s[0]), int(s[1]), int(s[3]), int(s[4]), int(s[5]), cons))
        warnings = stage_warnings(stages, cfg)
        warnings += [epipolar_warning(n, off, tri_n) for n, (off, tri_n) in unchecked.items()]
        for n in self.fringe_median:
            widened = int(self._bias_widened[n].sum())
            points = int(self._counts[n][1:].sum()) + int(self._bias_dropped[n].sum())  # before the bias drops
            if widened >= INDIRECT_WARN_SHARE * max(points, 1):
                warnings.append(indirect_warning(n, widened, points, int(self._bias_dropped[n].sum()),
                                                 cfg.max_sigma_mm))  # fmt: skip
        residuals = list(self._stereo.residuals) if self._stereo is not None else []
        if self.axes == "xy" and self.calibration.projector is not None:
            for n, tri in self._proj_tri.items():
                # every decoded pixel, not only those the epipolar check and the filters kept: a calibration
                # that no longer fits must not hide behind the check (decoded_ray_ray_residual)
                res = decoded_ray_ray_residual(maps[n].u, maps[n].v, tri.rays.normalized,
                                               self.calibration.devices[n], self.calibration.projector)  # fmt: skip
                if res is not None:
                    residuals.append(res)
        if self._stereo is not None:
            warnings = list(self._stereo.report.warnings) + warnings
            disagree = fusion.get("disagree", 0)
            both = disagree + fusion.get("fused", 0)
            if both and disagree > 0.05 * both:
                warnings.append(
                    f"{100.0 * disagree / both:.0f} % of the pixels both camera-projector and camera-camera "
                    "reconstruct disagree by more than 3 sigma (left out): the calibration may no longer fit "
                    "the rig; run scan3d verify or recalibrate"
                )
        names = self.calibration.camera_names
        if cfg.normals:
            clouds = []
            for n in self.outputs:
                org = self.organised(n)
                r = cfg.normal_radius_px
                eye = self.calibration.devices[n].center
                jump = self._jump[n][0] if self._jump[n][0] > 0 else FIXED_JUMP_MM
                estimate_normals(org, eye, self._normals[n], r, r * jump)
                shape = org.shape[:2]
                inten = None if white is None or n not in white else _as_uint8(white[n], (shape[0], shape[1]), n)
                clouds.append(to_point_cloud(org, maps[n].quality, inten, names.index(n), self._normals[n],
                                             self._sigma[n]))  # fmt: skip
            t2 = time.perf_counter()
            cloud = clouds[0] if len(clouds) == 1 else PointCloud.concatenate(clouds)
            t3 = time.perf_counter()
            timings = {"triangulate_ms": 1e3 * (t1 - t0), "filter_ms": 1e3 * (t2 - t1),
                       "cloud_ms": 1e3 * (t3 - t2), "total_ms": 1e3 * (t3 - t0)}  # fmt: skip
            return Reconstruction(cloud, timings, tuple(stages), tuple(warnings), tuple(residuals), fusion,
                                  self._stereo_report(), dict(self.edge_corrected))  # fmt: skip
        sizes = [int(self._counts[n].sum()) for n in self.outputs]
        total = sum(sizes)
        xyz, row, col, cam, inten8, qual, sig = self._pool.arrays(
            [((total, 3), np.float32), ((total,), np.int32), ((total,), np.int32), ((total,), np.uint8),
             ((total,), np.uint8), ((total,), np.float32), ((total,), np.float32)]
        )  # fmt: skip
        cloud = PointCloud(xyz, row, col, cam, inten8, qual, None, sig)  # type: ignore[arg-type]
        start = 0
        for n, size in zip(self.outputs, sizes, strict=True):
            shape = self._depth[n].shape
            inten = None if white is None or n not in white else _as_uint8(white[n], (shape[0], shape[1]), n)
            cloud.camera[start : start + size] = names.index(n)
            self._proj_tri[n].write_points(
                self._depth[n], self._counts[n], maps[n].quality, inten, cloud, start, self._sigma[n], self._spans[n]
            )
            start += size
        t2 = time.perf_counter()
        timings = {
            "triangulate_ms": 1e3 * (t1 - t0),
            "filter_ms": 0.0,
            "cloud_ms": 1e3 * (t2 - t1),
            "total_ms": 1e3 * (t2 - t0),
        }
        return Reconstruction(cloud, timings, tuple(stages), tuple(warnings), tuple(residuals), fusion,
                              self._stereo_report(), dict(self.edge_corrected))


def _extra_variance(
    edges: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]] | None,
    separated: npt.NDArray[np.float32] | None,
    shape: tuple[int, int],
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]] | None:
    """The further code variance of a camera's pixels as ``TriangulatorProcam.indirect_bias`` takes it
    (offsets per row, ascending columns, variance px^2): the albedo-edge correction's and that of the pixels
    whose code was taken apart from a second copy of the pattern (``DecodedMaps.separated``), summed where both."""
    if separated is None or len(separated) == 0:
        return edges
    h, w = shape
    keys = separated[:, 0].astype(np.int64) * w + separated[:, 1].astype(np.int64)
    var = separated[:, 2].astype(np.float64)
    if edges is not None and int(edges[0][-1]) > int(edges[0][0]):
        offsets, cols, evar = edges
        first, end = int(offsets[0]), int(offsets[-1])
        rows = np.repeat(np.arange(h, dtype=np.int64), np.diff(offsets))
        keys = np.concatenate([keys, rows * w + cols[first:end]])
        var = np.concatenate([var, evar[first:end].astype(np.float64)])
    uniq, inv = np.unique(keys, return_inverse=True)
    total = np.zeros(len(uniq))
    np.add.at(total, inv, var)
    offsets_out = np.searchsorted(uniq // w, np.arange(h + 1), side="left").astype(np.int64)
    return offsets_out, (uniq % w).astype(np.int64), total.astype(np.float32)

