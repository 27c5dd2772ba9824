"""Reconstruction of one scan: decoded maps -> triangulation -> filters -> PointCloud."""

from __future__ import annotations

import time

import numpy as np
import numpy.typing as npt

from appliance.config.schema import ReconstructionConfig
from appliance.errors import CalibrationError, ScanError
from appliance.geometry.calibration_file import Calibration
from appliance.geometry.rays import RayTable
from appliance.reconstruct._pool import BufferPool
from appliance.reconstruct.filters import estimate_normals, filter_isolated, to_point_cloud
from appliance.reconstruct.stereo import StereoTriangulator
from appliance.reconstruct.triangulate import ProjectorTriangulator
from appliance.reconstruct.types import DecodedMaps, PointCloud

F32 = npt.NDArray[np.float32]


def _as_uint8(img: npt.NDArray[np.generic], shape: tuple[int, int], name: str) -> npt.NDArray[np.uint8]:
    """Grey image -> uint8 (uint16 keeps its high byte, floats are clipped to 0..255)."""
    if img.shape[:2] != shape:
        raise ScanError(f"white image of {name}: shape {img.shape}: must be {shape} (H, W)")
    if img.ndim == 3:
        img = img.mean(axis=2)
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img, np.uint8)
    if img.dtype == np.uint16:
        return (np.asarray(img) >> 8).astype(np.uint8)
    return np.clip(np.asarray(img, np.float32), 0, 255).astype(np.uint8)


class Reconstructor:
    """Turns the decoded maps of one scan into a point cloud; every table is built once, here.

    Parameters
    ----------
    calibration : Calibration
        The rig (cameras in order; the projector for mode ``'projector'``).
    axes : {'x', 'y', 'xy'}
        Coded projector axes (``'x'``/``'y'``: ray / light-surface, ``'xy'``: ray-ray).
    cfg : ReconstructionConfig
        ``mode`` ``'projector'`` (every camera with the projector, clouds concatenated, camera index per
        point) or ``'stereo'`` (the first two cameras, cloud organised on the first), depth range, filters.

    Raises
    ------
    CalibrationError
        When the calibration lacks what the mode needs or its geometry cannot triangulate the axes.
    """

    def __init__(self, calibration: Calibration, axes: str, cfg: ReconstructionConfig) -> None:
        self.calibration, self.axes, self.cfg = calibration, axes, cfg
        names = calibration.camera_names
        if not names:
            raise CalibrationError("calibration holds no camera")
        self._proj_tri: dict[str, ProjectorTriangulator] = {}
        self._stereo: StereoTriangulator | None = None
        if cfg.mode == "projector":
            projector = calibration.projector
            if projector is None:
                raise CalibrationError(
                    "reconstruction.mode = projector: the calibration has no 'projector'; "
                    "calibrate it or use mode stereo"
                )
            for n in names:
                self._proj_tri[n] = ProjectorTriangulator(calibration.devices[n], projector, axes)
            self.outputs = list(names)
        else:
            if len(names) < 2:
                raise CalibrationError(
                    f"reconstruction.mode = stereo: needs two cameras, the calibration has {names}"
                )
            cam0, cam1 = calibration.devices[names[0]], calibration.devices[names[1]]
            self._stereo = StereoTriangulator(
                cam0,
                cam1,
                RayTable(cam0),
                max_epipolar_px=cfg.stereo_max_epipolar_px,
                projector=calibration.projector,
            )
            self.outputs = [names[0]]
        # camera-projector without normals needs no organised cloud: depth maps, filtered as they are made
        self._fused = cfg.mode == "projector" and not cfg.normals
        # clouds are views of blocks reused once the caller drops them (saves the page faults of ~26 B/point)
        self._pool = BufferPool()
        self._xyz: dict[str, F32] = {}
        self._depth: dict[str, F32] = {}
        self._counts: dict[str, npt.NDArray[np.int64]] = {}
        self._scratch: dict[str, npt.NDArray[np.bool_]] = {}
        self._normals: dict[str, F32] = {}
        self._jump_mm: dict[str, float] = {}
        for n in self.outputs:
            cam = calibration.devices[n]
            # neighbours are a pixel apart: allow the diagonal footprint of a pixel at mid range on top
            footprint_mm = 0.5 * (cfg.min_depth_mm + cfg.max_depth_mm) / float(cam.K[0, 0])
            self._jump_mm[n] = cfg.max_neighbour_jump_mm + 2.0 * footprint_mm
            if self._fused:
                self._depth[n] = np.full((cam.height, cam.width), np.nan, np.float32)
                self._counts[n] = np.zeros(cam.height + 1, np.int64)
                continue
            self._xyz[n] = np.empty((cam.height, cam.width, 3), np.float32)
            self._scratch[n] = np.empty((cam.height, cam.width), np.bool_)
            if cfg.normals:
                self._normals[n] = np.empty((cam.height, cam.width, 3), np.float32)

    def organised(self, name: str) -> F32:
        """The organised cloud (H, W, 3) of camera ``name`` from the last :meth:`run` (reused buffer).

        Where the reconstruction keeps depth maps only (mode ``'projector'`` without normals), the cloud
        is built from the depth map on this call.
        """
        if self._fused:
            cam = self.calibration.devices[name]
            if name not in self._xyz:
                self._xyz[name] = np.empty((cam.height, cam.width, 3), np.float32)
            self._proj_tri[name].organised_from_depth(self._depth[name], self._xyz[name])
        return self._xyz[name]

    def run(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None = None
    ) -> tuple[PointCloud, dict[str, float]]:
        """Reconstruct one scan.

        Parameters
        ----------
        maps : dict of str to DecodedMaps
            Decoded maps per camera name (both cameras in mode ``'stereo'``).
        white : dict of str to ndarray (H, W), optional
            Image under white light per camera, for the per-point intensity.

        Returns
        -------
        cloud : PointCloud
            Points of every output camera, world frame (mm), with their source pixel and camera index.
        timings : dict of str to float
            ``triangulate_ms``, ``filter_ms``, ``cloud_ms``, ``total_ms``. In mode ``'projector'``
            without normals the neighbour filter runs inside triangulation (``filter_ms`` is 0).
        """
        cfg = self.cfg
        needed = (
            [self.calibration.camera_names[i] for i in range(2)] if self._stereo is not None else self.outputs
        )
        for n in needed:
            if n not in maps:
                raise ScanError(f"reconstruct: no decoded maps for camera {n!r} (have {sorted(maps)})")
        if self._fused:
            return self._run_fused(maps, white)
        t0 = time.perf_counter()
        if self._stereo is not None:
            n0, n1 = needed
            self._stereo.triangulate(maps[n0], maps[n1], self._xyz[n0], cfg.min_depth_mm, cfg.max_depth_mm)
        else:
            for n, tri in self._proj_tri.items():
                tri.triangulate(maps[n], self._xyz[n], cfg.min_depth_mm, cfg.max_depth_mm)
        t1 = time.perf_counter()
        for n in self.outputs:
            filter_isolated(self._xyz[n], cfg.min_neighbours, self._jump_mm[n], self._scratch[n])
            if cfg.normals:
                eye = self.calibration.devices[n].center
                r = cfg.normal_radius_px
                estimate_normals(self._xyz[n], eye, self._normals[n], r, r * self._jump_mm[n])
        t2 = time.perf_counter()
        clouds = []
        names = self.calibration.camera_names
        for n in self.outputs:
            shape = self._xyz[n].shape[:2]
            inten = None if white is None or n not in white else _as_uint8(white[n], (shape[0], shape[1]), n)
            clouds.append(
                to_point_cloud(self._xyz[n], maps[n].quality, inten, names.index(n), self._normals.get(n))
            )
        cloud = clouds[0] if len(clouds) == 1 else PointCloud.concatenate(clouds)
        t3 = time.perf_counter()
        timings = {
            "triangulate_ms": 1e3 * (t1 - t0),
            "filter_ms": 1e3 * (t2 - t1),
            "cloud_ms": 1e3 * (t3 - t2),
            "total_ms": 1e3 * (t3 - t0),
        }
        return cloud, timings

    def _run_fused(
        self, maps: dict[str, DecodedMaps], white: dict[str, npt.NDArray[np.generic]] | None
    ) -> tuple[PointCloud, dict[str, float]]:
        """Depth + neighbour filter per camera (one pass), then every kept point into one cloud (one pass)."""
        cfg = self.cfg
        t0 = time.perf_counter()
        for n, tri in self._proj_tri.items():
            tri.triangulate_depth(
                maps[n], self._depth[n], cfg.min_depth_mm, cfg.max_depth_mm, cfg.min_neighbours,
                self._jump_mm[n], self._counts[n],
            )  # fmt: skip
        t1 = time.perf_counter()
        sizes = [int(self._counts[n].sum()) for n in self.outputs]
        total = sum(sizes)
        xyz, row, col, cam, inten8, qual = self._pool.arrays(
            [((total, 3), np.float32), ((total,), np.int32), ((total,), np.int32), ((total,), np.uint8),
             ((total,), np.uint8), ((total,), np.float32)]
        )  # fmt: skip
        cloud = PointCloud(xyz, row, col, cam, inten8, qual)  # type: ignore[arg-type]
        names = self.calibration.camera_names
        start = 0
        for n, size in zip(self.outputs, sizes, strict=True):
            shape = self._depth[n].shape
            inten = None if white is None or n not in white else _as_uint8(white[n], (shape[0], shape[1]), n)
            cloud.camera[start : start + size] = names.index(n)
            self._proj_tri[n].write_points(self._depth[n], self._counts[n], maps[n].quality, inten, cloud, start)
            start += size
        t2 = time.perf_counter()
        timings = {
            "triangulate_ms": 1e3 * (t1 - t0),
            "filter_ms": 0.0,
            "cloud_ms": 1e3 * (t2 - t1),
            "total_ms": 1e3 * (t2 - t0),
        }
        return cloud, timings
