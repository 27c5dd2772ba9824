"""Frames -> reconstruction -> files: what a scan and an offline decode of recorded frames share.

A scan (:mod:`appliance.scan`) gets its frames from the cameras and decodes them as they stream in; an offline
decode (``scan3d decode``) reads them from a manifest (:class:`ReplayBatch`). From the decoded maps on, both run
the same code: :func:`reconstruct` (the reconstruction and the calibration-health verdict), :func:`scan_metadata`
(the sidecar's content) and :func:`result_files` (the files' bytes). The grey value of a pixel comes from one
converter, :func:`appliance.reconstruct.pipeline.white_to_uint8`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from appliance.calibration.health import TrendStore
from appliance.calibration.scan_health import assess_scan
from appliance.config.schema import ReconstructionConfig
from appliance.errors import ConfigError, ManifestError
from appliance.geometry.calibration_file import PROJECTOR_NAME, Calibration, read_calibration
from appliance.hardware.base import FrameArray
from appliance.output.scanfiles import FileContent, scan_file_contents
from appliance.output.sidecar import ScanMetadata
from appliance.patterns.manifest import Manifest, read_manifest
from appliance.patterns.sequence import PhaseFrame, Sequence
from appliance.reconstruct import pipeline
from appliance.reconstruct.decode import (
    DecodeParams,
    DecodePlan,
    decode,
    plan_decode,
    reason_advice,
    reason_block,
    stripe_widths,
)
from appliance.reconstruct.geometry_defaults import depth_range_from_geometry
from appliance.reconstruct.hdr import capture_record, capture_summary, decode_passes, fused_white
from appliance.reconstruct.types import DecodedMaps, PointCloud

Json = dict[str, object]

DECODE_MODES = pipeline.MODES
"""``scan3d decode --mode`` choices: camera-projector, camera-camera, or both (fused)."""


@dataclass(frozen=True)
class ScanResult:
    """The outcome of one scan or one replayed capture.

    Attributes
    ----------
    reconstruction : Reconstruction
        What the reconstruction produced (cloud, stages, warnings, residuals, matcher report).
    maps : dict of str to DecodedMaps
        Decoded maps per camera.
    white : dict of str to ndarray (H, W) uint8
        Grey image per camera (the intensity of the points).
    timings_ms : dict of str to float
        Wall times of the steps (ms).
    shapes : dict of str to (int, int)
        (H, W) of each camera (px).
    calibration_health : dict
        The scan's calibration health (:func:`appliance.calibration.scan_health.assess_scan`).
    frames : dict of str to ndarray (F, H, W)
        The captured frames, where the scanner keeps them (else empty).
    capture : dict
        A multi-exposure capture's exposures and what each pass gave per camera (the sidecar's ``extra.hdr``,
        see :func:`appliance.reconstruct.hdr.capture_summary`); empty for one pass.
    """

    reconstruction: pipeline.Reconstruction
    maps: dict[str, DecodedMaps]
    white: dict[str, npt.NDArray[np.uint8]]
    timings_ms: dict[str, float]
    shapes: dict[str, tuple[int, int]]
    calibration_health: Json = field(default_factory=dict)
    frames: dict[str, FrameArray] = field(default_factory=dict)
    capture: Json = field(default_factory=dict)

    @property
    def cloud(self) -> PointCloud:
        """The point cloud (mm, world frame)."""
        return self.reconstruction.cloud

    @property
    def stages(self) -> list[Json]:
        """Per camera, what each reconstruction stage rejected (JSON-ready)."""
        return [st.as_dict() for st in self.reconstruction.stages]

    @property
    def warnings(self) -> list[str]:
        """Plain-words warnings of the reconstruction."""
        return list(self.reconstruction.warnings)

    @property
    def stereo(self) -> Json | None:
        """What the camera-camera matcher did (modes ``stereo`` and ``both``)."""
        return self.reconstruction.stereo


def reconstruct(
    reconstructor: pipeline.Reconstructor,
    maps: dict[str, DecodedMaps],
    white: dict[str, npt.NDArray[np.uint8]],
    trend: TrendStore | None = None,
    tolerance_px: float | None = None,
) -> tuple[pipeline.Reconstruction, Json]:
    """The reconstruction of one scan and its calibration-health verdict (the same for scan and replay).

    Parameters
    ----------
    reconstructor : Reconstructor
        Built once for the rig, the axes and the settings.
    maps : dict of str to DecodedMaps
        Decoded maps per camera.
    white : dict of str to ndarray (H, W) uint8
        Grey image per camera (:func:`~appliance.reconstruct.pipeline.white_to_uint8`).
    trend : TrendStore, optional
        The appliance's history of residuals (a scan appends to it; an offline decode has none).
    tolerance_px : float, optional
        ``bad`` beyond this robust RMS (px).

    Returns
    -------
    reconstruction : Reconstruction
        The record of the run; its ``timings_ms`` gains ``health_ms``.
    health : dict
        The ``calibration_health`` block.
    """
    white_any: dict[str, npt.NDArray[np.generic]] = dict(white)
    rec = reconstructor.run(maps, white_any)
    t = time.perf_counter()
    health: Json = dict(assess_scan(rec.residuals, reconstructor.calibration, trend, tolerance_px))
    rec.timings_ms["health_ms"] = (time.perf_counter() - t) * 1e3
    return rec, health


def grey_of_stack(stack: FrameArray, plan: DecodePlan, bits: int) -> npt.NDArray[np.uint8]:
    """Grey value (0..255) per pixel of a recorded stack: the white frame, else the mean of the phase frames,
    else the brightest used frame, through :func:`~appliance.reconstruct.pipeline.white_to_uint8`.

    Parameters
    ----------
    stack : ndarray, shape (F, H, W)
        The frames of one camera (DN).
    plan : DecodePlan
        The decode plan of the stack's sequence.
    bits : int
        Significant bits of the frames.
    """
    if plan.white >= 0:
        return pipeline.white_to_uint8(stack[plan.white], bits)
    phase = [i for i, f in enumerate(plan.sequence.frames) if isinstance(f, PhaseFrame)]
    img = np.mean(stack[phase], axis=0, dtype=np.float32) if phase else np.max(stack[list(plan.used)], axis=0)
    return pipeline.white_to_uint8(np.asarray(img), bits)


def scan_metadata(
    scan_id: str,
    time_utc: str,
    sequence: Sequence,
    calibration: Calibration,
    cameras: list[str],
    result: ScanResult,
    *,
    serial: str = "",
    extra: Json | None = None,
    per_camera: dict[str, Json] | None = None,
) -> ScanMetadata:
    """The sidecar content of one scan or replayed capture.

    Parameters
    ----------
    scan_id, time_utc : str
        The scan's id (the files' stem) and its ISO 8601 start (UTC).
    sequence : Sequence
        The projected sequence.
    calibration : Calibration
        The calibration the reconstruction used (its hash is recorded).
    cameras : list of str
        Camera names in the order of the cloud's camera index.
    result : ScanResult
        What the scan produced.
    serial : str
        The appliance's serial ('' offline).
    extra : dict, optional
        More blocks for ``extra`` (the matcher's report is added as ``stereo``).
    per_camera : dict of str to dict, optional
        More per-camera counts (merged into ``counts.cameras``).
    """
    cloud = result.cloud
    per_cam: dict[str, Json] = {}
    for i, name in enumerate(cameras):
        mask = result.maps[name].mask
        per_cam[name] = {"decoded_pixels": int(mask.sum()), "pixels": int(mask.size),
                         "points": int(np.sum(cloud.camera == i)), **reason_block(result.maps[name]),
                         **(per_camera or {}).get(name, {})}  # fmt: skip
        edges = result.reconstruction.edge_corrected
        if name in edges:  # the codes the albedo-edge correction moved (reconstruction.edge_blur_px)
            per_cam[name]["albedo_edge_corrected"] = int(edges[name])
    more: Json = dict(extra or {})
    if result.capture:
        more["hdr"] = result.capture
    if result.stereo:
        more["stereo"] = result.stereo
    return ScanMetadata(
        scan_id=scan_id,
        time_utc=time_utc,
        sequence={"description": sequence.describe(), "frames": len(sequence),
                  "projector": [sequence.width, sequence.height]},
        calibration_hash=calibration.hash(),
        counts={"points": len(cloud), "cameras": per_cam},
        timings_ms=dict(result.timings_ms),
        appliance_serial=serial,
        cameras=list(cameras),
        stages=result.stages,
        warnings=[*result.warnings, *(a for name in cameras if (a := reason_advice(result.maps[name], name)))],
        calibration_health=dict(result.calibration_health),
        extra=more,
    )


def result_files(
    meta: ScanMetadata,
    result: ScanResult,
    *,
    normals: bool,
    preview: bool,
    ply_comments: list[str] | None = None,
) -> list[FileContent]:
    """The files of one result, rendered in memory: cloud (PLY), preview (PNG, optional), sidecar (JSON).

    The one "result -> files" step of ``scan3d scan`` and ``scan3d decode``; the service's share writer
    renders the same files (:func:`appliance.output.scanfiles.scan_file_contents`) with ``meta`` from
    :func:`scan_metadata` and the reasons from :func:`reason_maps`. The preview stripes each pixel without a
    point in the colour of its reason.

    Parameters
    ----------
    meta : ScanMetadata
        The sidecar's content (its ``files`` is filled in).
    result : ScanResult
        The cloud and the camera shapes.
    normals, preview : bool
        Normals in the PLY (the cloud must have them); a preview image.
    ply_comments : list of str, optional
        The PLY header's comments (default: the scan id and the unit).
    """
    return scan_file_contents(meta, result.cloud, list(result.shapes.values()), normals=normals, preview=preview,
                              comments=ply_comments, reasons=reason_maps(result))  # fmt: skip


def reason_maps(result: ScanResult) -> list[npt.NDArray[np.uint8] | None]:
    """Per camera (order of ``result.shapes``), its reason map (why each pixel has no point) or None: what the
    preview draws (:func:`appliance.output.preview.render_preview`)."""
    return [result.maps[name].reason if name in result.maps else None for name in result.shapes]


def choose_decode_mode(calib: Calibration, cameras: list[str] | tuple[str, ...], requested: str | None = None) -> str:
    """The reconstruction mode of an offline decode, from what the calibration holds.

    A projector entry: camera-projector for every camera (``'projector'``); two cameras and no projector:
    camera-camera (``'stereo'``); both: ``'both'`` (see :func:`~appliance.reconstruct.pipeline.available_modes`).
    ``requested`` overrides, if the calibration allows it.

    Raises
    ------
    ConfigError
        When the calibration cannot support the requested (or any) mode.
    """
    cams = [c for c in cameras if c != PROJECTOR_NAME and c in calib.devices]
    modes = pipeline.available_modes(calib, cams)
    if requested is None:
        for mode in ("both", "projector", "stereo"):
            if mode in modes:
                return mode
        raise ConfigError(
            f"decode: the calibration has camera(s) {cams} and no projector: nothing to triangulate with; "
            "add the projector's calibration or decode two cameras"
        )
    if requested not in DECODE_MODES:
        raise ConfigError(f"decode: --mode {requested!r}: must be one of {', '.join(DECODE_MODES)}")
    if requested in ("projector", "both") and "projector" not in modes:
        raise ConfigError(f"decode: --mode {requested}: the calibration has no 'projector'; use --mode stereo")
    if requested not in modes:
        raise ConfigError(
            f"decode: --mode {requested}: needs two cameras of the manifest in the calibration, found {cams}; "
            "use --mode projector"
        )
    return requested


@dataclass(frozen=True)
class ReplaySetup:
    """What one manifest is reconstructed with: the reconstructor, its mode and its settings."""

    reconstructor: pipeline.Reconstructor
    mode: str
    settings: ReconstructionConfig


class ReplayBatch:
    """What a batch of offline decodes shares: plans, calibrations and reconstructors are built once.

    Parameters
    ----------
    calibration : Path, optional
        The calibration file (without one, only maps are decoded).
    settings : ReconstructionConfig
        The reconstruction settings; the depth range, unless set explicitly, comes from the geometry.
    mode : str, optional
        The requested mode (default: from the calibration, :func:`choose_decode_mode`).
    """

    def __init__(self, calibration: Path | None, settings: ReconstructionConfig, mode: str | None) -> None:
        self.calibration_path = calibration
        self.mode_requested = mode
        self.settings = settings
        self.depth_given = bool({"min_depth_mm", "max_depth_mm"} & settings.model_fields_set)
        self._plans: dict[Sequence, DecodePlan] = {}
        self._calibs: dict[tuple[int, int], Calibration] = {}
        self._setups: dict[tuple[int, tuple[str, ...], str, str, str], ReplaySetup] = {}

    def plan(self, sequence: Sequence) -> DecodePlan:
        """The decode plan of ``sequence`` (built once)."""
        if sequence not in self._plans:
            self._plans[sequence] = plan_decode(sequence)
        return self._plans[sequence]

    def calib(self, projector_size: tuple[int, int]) -> Calibration:
        """The calibration, read for this projector size (once per size)."""
        assert self.calibration_path is not None
        if projector_size not in self._calibs:
            self._calibs[projector_size] = read_calibration(self.calibration_path, projector_size)
        return self._calibs[projector_size]

    def setup(self, man: Manifest, axes: str, shapes: dict[str, tuple[int, int]]) -> ReplaySetup:
        """The reconstructor, mode and settings for this manifest's cameras and sequence.

        Raises
        ------
        ManifestError
            When a camera of the manifest is not in the calibration or its images have another size.
        """
        calib = self.calib((man.sequence.width, man.sequence.height))
        missing = [c for c in man.cameras if c not in calib.devices]
        if missing:
            raise ManifestError(
                f"{man.path}: camera(s) {missing} have no entry in {self.calibration_path} (it has "
                f"{list(calib.devices)}); name the manifest's cameras as in the calibration"
            )
        for cam, (h, w) in shapes.items():
            dev = calib.devices[cam]
            if (dev.width, dev.height) != (w, h):
                raise ManifestError(
                    f"{man.path}: camera {cam!r}: images are {w}x{h} but {self.calibration_path} calibrates it at "
                    f"{dev.width}x{dev.height}; use the calibration of these images"
                )
        mode = choose_decode_mode(calib, man.cameras, self.mode_requested)
        pair: Literal["projector", "stereo", "both"] = "both" if mode == "both" else "stereo" if mode == "stereo" \
            else "projector"
        key = (id(calib), tuple(man.cameras), axes, mode, man.sequence.describe())
        if key not in self._setups:
            sub = Calibration({n: calib.devices[n] for n in [*man.cameras, PROJECTOR_NAME] if n in calib.devices})
            rc = self._settings_for(pair, sub)
            # the sequence gives every point its sigma_mm
            self._setups[key] = ReplaySetup(pipeline.Reconstructor(sub, axes, rc, man.sequence), rc.mode, rc)
        return self._setups[key]

    def _settings_for(self, mode: Literal["projector", "stereo", "both"], calib: Calibration) -> ReconstructionConfig:
        update: Json = {"mode": mode}
        if not self.depth_given:
            near, far = depth_range_from_geometry(calib, mode)
            update["min_depth_mm"], update["max_depth_mm"] = near, far
        return ReconstructionConfig.model_validate({**self.settings.model_dump(), **update})


def stripe_summary(maps: DecodedMaps, plan: DecodePlan) -> dict[str, dict[str, float]]:
    """Share of decoded pixels per effective stripe width (projector px; 0 = sub-pixel phase), per axis."""
    return {axis: {f"{w:g}": round(share, 6) for w, share in d.items()}
            for axis, d in stripe_widths(maps, plan).items()}  # fmt: skip


@dataclass(frozen=True)
class Replayed:
    """One recorded capture, decoded and (with a calibration) reconstructed.

    Attributes
    ----------
    manifest : Manifest
        The capture's manifest.
    plan : DecodePlan
        Its decode plan.
    maps : dict of str to DecodedMaps
        Decoded maps per camera.
    setup : ReplaySetup, optional
        The reconstructor, mode and settings (None without a calibration).
    result : ScanResult, optional
        The reconstruction (None without a calibration).
    exposure_shares : dict of str to list of float
        Multi-exposure captures: per camera, the share of decoded pixels each pass gave (darkest first).
    timings_ms : dict of str to float
        ``load_ms``, ``setup_ms``, ``decode_ms``, ``triangulate_ms``, ``filter_ms``, ``cloud_ms``.
    span_s : (float, float)
        ``time.perf_counter()`` at its start and end (the caller's later steps are timed from the end).
    """

    manifest: Manifest
    plan: DecodePlan
    maps: dict[str, DecodedMaps]
    setup: ReplaySetup | None
    result: ScanResult | None
    exposure_shares: dict[str, list[float]]
    timings_ms: dict[str, float]
    span_s: tuple[float, float]


def replay_capture(batch: ReplayBatch, manifest_path: Path, *, cloud_wanted: bool) -> Replayed:
    """Decode one recorded capture and, with the batch's calibration, reconstruct it as a scan would.

    Parameters
    ----------
    batch : ReplayBatch
        What the captures of one run share.
    manifest_path : Path
        The capture's manifest.
    cloud_wanted : bool
        A cloud is asked for (an error without a calibration).

    Raises
    ------
    ApplianceError
        One line, for a bad manifest, a calibration that does not fit it, or a cloud asked for without one.
    """
    t0 = time.perf_counter()
    man = read_manifest(manifest_path)
    stacks = {cam: man.load_stack(cam) for cam in man.cameras}
    bits = {cam: man.bits_of(st) for cam, st in stacks.items()}
    t1 = time.perf_counter()
    plan = batch.plan(man.sequence)
    shapes = {cam: (int(st.shape[1]), int(st.shape[2])) for cam, st in stacks.items()}
    setup = None
    if batch.calibration_path is not None:
        setup = batch.setup(man, "".join(plan.axes), shapes)
    elif cloud_wanted:
        raise ConfigError("decode: --out needs --calibration (without one, only --maps can be written)")
    rc = setup.settings if setup is not None else batch.settings
    t2 = time.perf_counter()
    maps: dict[str, DecodedMaps] = {}
    grey: dict[str, npt.NDArray[np.uint8]] = {}
    shares: dict[str, list[float]] = {}
    hdr: dict[str, object] = {}
    for cam, st in stacks.items():
        params = DecodeParams.from_settings(rc, max_value=float((1 << bits[cam]) - 1))
        if man.exposures is None:
            maps[cam] = decode(st, plan, params)
            continue
        # several exposures: each pass decoded on its own, fused per pixel (the brightest unclipped pass)
        maps[cam], choice, passes = decode_passes(st, man.sequence, man.exposures, params)
        greys = []
        for _light, idx in passes:
            sub = Sequence(man.sequence.width, man.sequence.height, tuple(man.sequence.frames[i] for i in idx))
            greys.append(grey_of_stack(st[idx], batch.plan(sub), bits[cam]))
        grey[cam] = fused_white(maps[cam], greys, passes, choice)  # as the service's scan
        per_pass = np.bincount(choice[maps[cam].mask], minlength=len(passes)) / max(int(maps[cam].mask.sum()), 1)
        shares[cam] = [float(s) for s in per_pass]
        hdr[cam] = capture_summary(man.exposures, passes, choice, maps[cam].mask)
    t3 = time.perf_counter()
    result = None
    stage_ms = {"triangulate_ms": 0.0, "filter_ms": 0.0}
    if setup is not None:
        white = grey or {cam: grey_of_stack(st, plan, bits[cam]) for cam, st in stacks.items()}
        rec, health = reconstruct(setup.reconstructor, maps, white)  # offline: no trend, the tolerance only
        stage_ms = {"triangulate_ms": rec.timings_ms["triangulate_ms"], "filter_ms": rec.timings_ms["filter_ms"]}
        capture: Json = {}
        if man.exposures is not None:
            capture = capture_record(man.exposures, hdr)
        result = ScanResult(rec, maps, white, {}, shapes, health, capture=capture)
    t4 = time.perf_counter()
    times = {
        "load_ms": round((t1 - t0) * 1e3, 3),
        "setup_ms": round((t2 - t1) * 1e3, 3),
        "decode_ms": round((t3 - t2) * 1e3, 3),
        # triangulation (camera-projector: with its filters, one pass), filters, and the rest of the
        # reconstruction (the point cloud, intensities, the health verdict): together t4 - t3
        "triangulate_ms": round(stage_ms["triangulate_ms"], 3),
        "filter_ms": round(stage_ms["filter_ms"], 3),
        "cloud_ms": round((t4 - t3) * 1e3 - stage_ms["triangulate_ms"] - stage_ms["filter_ms"], 3),
    }
    if result is not None:
        result.timings_ms.update(times)
    return Replayed(man, plan, maps, setup, result, shares, times, (t0, t4))
