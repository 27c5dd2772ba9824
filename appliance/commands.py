"""What the one-shot commands do (``patterns``, ``decode``, ``scan``, ``validate-config``, ``devices``, ``grab``).

Each function prints for a person and returns an exit status; ``cli.py`` only parses arguments.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.config import AppConfig, load_config
from appliance.config.schema import ReconstructionConfig
from appliance.errors import ApplianceError, ConfigError, ManifestError, OutputError


def _config_or_default(path: Path | None) -> AppConfig:
    if path is not None and Path(path).exists():
        return load_config(path)
    return AppConfig()


def write_patterns(out: Path, config: Path | None, width: int | None, height: int | None) -> int:
    """Write the configured sequence's projector images (PNG) and a manifest into ``out``."""
    import cv2

    from appliance.patterns import render_frame, write_manifest
    from appliance.patterns.from_config import build_sequence

    cfg = _config_or_default(config)
    w = width or cfg.virtual_rig.projector.width
    h = height or cfg.virtual_rig.projector.height
    seq = build_sequence(cfg.sequence, w, h)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for i, frame in enumerate(seq.frames):
        name = f"pattern_{i:03d}.png"
        if not cv2.imwrite(str(out / name), render_frame(frame, w, h)):
            raise ApplianceError(f"{out / name}: cannot be written; check the folder")
        names.append(name)
    write_manifest(out / "manifest.yaml", seq, ["projector"], images={"projector": names})
    print(f"wrote {len(names)} projector images ({seq.describe()}) and {out / 'manifest.yaml'}")
    return 0


def decode_manifest(
    manifest_path: Path,
    calibration: Path | None,
    out: Path | None,
    maps_out: Path | None,
    timings: bool,
    config: Path | None,
) -> int:
    """Decode one recorded capture (see :func:`decode_manifests`)."""
    return decode_manifests([manifest_path], calibration, out, maps_out, timings, config)


DECODE_MODES = ("projector", "stereo", "both")
"""``scan3d decode --mode`` choices: camera-projector, camera-camera, or both (fused where supported)."""


def choose_decode_mode(calib: Any, cameras: list[str] | tuple[str, ...], requested: str | None = None) -> str:
    """The reconstruction mode of an offline decode, from what the calibration holds.

    A projector entry: camera-projector for every camera (``'projector'``); two cameras and no projector:
    camera-camera (``'stereo'``); both: ``'both'``. ``requested`` overrides, if the calibration allows it.

    Raises
    ------
    ConfigError
        When the calibration cannot support the requested (or any) mode.
    """
    from appliance.geometry.calibration_file import PROJECTOR_NAME

    cams = [c for c in cameras if c != PROJECTOR_NAME and c in calib.devices]
    has_projector = calib.projector is not None
    if requested is None:
        if has_projector and len(cams) >= 2:
            return "both"
        if has_projector:
            return "projector"
        if len(cams) >= 2:
            return "stereo"
        raise ConfigError(
            f"decode: the calibration has camera(s) {cams} and no projector: nothing to triangulate with; "
            "add the projector's calibration or decode two cameras"
        )
    if requested not in DECODE_MODES:
        raise ConfigError(f"decode: --mode {requested!r}: must be one of {', '.join(DECODE_MODES)}")
    if requested in ("projector", "both") and not has_projector:
        raise ConfigError(f"decode: --mode {requested}: the calibration has no 'projector'; use --mode stereo")
    if requested in ("stereo", "both") and len(cams) < 2:
        raise ConfigError(
            f"decode: --mode {requested}: needs two cameras of the manifest in the calibration, found {cams}; "
            "use --mode projector"
        )
    return requested


def reconstruction_settings(path: Path) -> ReconstructionConfig:
    """The ``reconstruction:`` section of a configuration file; every other section is ignored (an offline
    decode needs no hardware entries, and a full appliance configuration may be given as it is).

    Raises
    ------
    ConfigError
        ``file:line: reconstruction.key = value: rule`` for a bad setting, or why the file is unreadable.
    """
    import yaml
    from pydantic import BaseModel, ConfigDict, ValidationError

    from appliance.config.loader import format_validation_error

    class _Reconstruction(BaseModel):
        model_config = ConfigDict(extra="ignore")
        reconstruction: ReconstructionConfig = ReconstructionConfig()

    try:
        text = Path(path).read_text(encoding="utf-8")
        root, doc = yaml.compose(text), yaml.safe_load(text)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror}); check --config") from exc
    except (UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: not a YAML text file ({' '.join(str(exc).split())[:200]})") from exc
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: not a YAML mapping; give a file with a 'reconstruction:' section")
    try:
        return _Reconstruction.model_validate(doc).reconstruction
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, str(path), doc, root)) from exc


class _DecodeBatch:
    """What a batch of offline decodes shares: plans, calibrations and reconstructors are built once."""

    def __init__(self, calibration: Path | None, config: Path | None, mode: str | None) -> None:
        self.calibration_path = calibration
        self.mode_requested = mode
        self.rc = reconstruction_settings(config) if config is not None else ReconstructionConfig()
        self.depth_given = bool({"min_depth_mm", "max_depth_mm"} & self.rc.model_fields_set)
        self._plans: dict[Any, Any] = {}
        self._calibs: dict[tuple[int, int], Any] = {}
        self._recons: dict[Any, Any] = {}
        self.notes: list[str] = []

    def plan(self, sequence: Any) -> Any:
        from appliance.reconstruct.decode import plan_decode

        if sequence not in self._plans:
            self._plans[sequence] = plan_decode(sequence)
        return self._plans[sequence]

    def calib(self, projector_size: tuple[int, int]) -> Any:
        from appliance.geometry.calibration_file import read_calibration

        assert self.calibration_path is not None
        if projector_size not in self._calibs:
            self._calibs[projector_size] = read_calibration(self.calibration_path, projector_size)
        return self._calibs[projector_size]

    def reconstructor(self, man: Any, axes: str, shapes: dict[str, tuple[int, int]]) -> tuple[Any, str, Any]:
        """(Reconstructor, mode, its ReconstructionConfig) for this manifest's cameras and sequence."""
        from appliance.geometry.calibration_file import PROJECTOR_NAME
        from appliance.reconstruct.pipeline import Reconstructor

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
        key = (id(calib), tuple(man.cameras), axes, mode, man.sequence.describe())
        if key in self._recons:
            return self._recons[key]  # type: ignore[no-any-return]
        sub = type(calib)({n: calib.devices[n] for n in [*man.cameras, PROJECTOR_NAME] if n in calib.devices})
        rc = self._config_for(mode, sub, list(man.cameras))
        used_mode = rc.mode
        if used_mode != mode:
            self.notes.append(
                f"mode {mode}: this reconstruction has no fused mode; triangulating camera-projector only "
                "(give --mode stereo for camera-camera)"
            )
        recon = Reconstructor(sub, axes, rc, man.sequence)  # the sequence gives every point its sigma_mm
        self._recons[key] = (recon, used_mode, rc)
        return self._recons[key]  # type: ignore[no-any-return]

    def _config_for(self, mode: str, calib: Any, cameras: list[str]) -> ReconstructionConfig:
        from pydantic import ValidationError

        from appliance.reconstruct.defaults import default_depth_range_mm

        update: dict[str, Any] = {"mode": mode}
        if not self.depth_given:
            cams = [calib.devices[c] for c in cameras if c in calib.devices]
            pairs: list[tuple[list[Any], list[Any]]] = []
            if mode in ("projector", "both"):
                pairs.append((cams, [calib.projector]))
            if mode in ("stereo", "both"):
                pairs.append((cams[:1], cams[1:2]))
            near, far = math.inf, 0.0
            for refs, others in pairs:
                lo, hi = default_depth_range_mm(refs, others)
                near, far = min(near, lo), max(far, hi)
            update["min_depth_mm"], update["max_depth_mm"] = near, far
        try:
            return ReconstructionConfig.model_validate({**self.rc.model_dump(), **update})
        except ValidationError:
            if mode != "both":
                raise
            update["mode"] = "projector"  # no fused mode in this build's schema
            return ReconstructionConfig.model_validate({**self.rc.model_dump(), **update})


def _intensity8(stack: Any, plan: Any, bits: int) -> npt.NDArray[np.uint8]:
    """Grey value (0..255) per pixel: the white frame, else the mean of the phase frames, else the brightest."""
    from appliance.patterns.sequence import PhaseFrame

    img: npt.NDArray[np.float32]
    if plan.white >= 0:
        img = np.asarray(stack[plan.white], np.float32)
    else:
        phase = [i for i, f in enumerate(plan.sequence.frames) if isinstance(f, PhaseFrame)]
        img = np.asarray(np.mean(stack[phase], axis=0, dtype=np.float32) if phase
                         else np.max(stack[list(plan.used)], axis=0), np.float32)  # fmt: skip
    scale = 255.0 / float((1 << bits) - 1)
    return np.asarray(np.clip(img * scale + 0.5, 0, 255), np.uint8)


def _target(base: Path | None, manifest: Path, suffix: str, batch: bool) -> Path:
    """Where a capture's file goes: ``base`` itself (one capture, a file name), or ``base/<stem><suffix>``."""
    if base is None:
        return manifest.with_suffix(suffix)
    if batch or base.is_dir() or base.suffix == "":
        return base / f"{manifest.stem}{suffix}"
    return base


def _stripe_summary(maps: Any, plan: Any) -> dict[str, dict[str, float]]:
    """Share of decoded pixels per effective stripe width (projector px; 0 = sub-pixel phase), per axis."""
    from appliance.reconstruct.decode import stripe_widths

    return {axis: {f"{w:g}": round(share, 6) for w, share in d.items()}
            for axis, d in stripe_widths(maps, plan).items()}  # fmt: skip


def _jsonable(value: Any) -> Any:
    """A report object as JSON-ready data (``as_dict``/``to_dict``, dataclasses, lists of them)."""
    import dataclasses

    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    for name in ("as_dict", "to_dict"):
        fn = getattr(value, name, None)
        if callable(fn):
            return fn()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return value


def _reconstruction_report(recon: Any) -> dict[str, Any]:
    """Per-stage counts, warnings and matcher reports of the last reconstruction, where it provides them."""
    out: dict[str, Any] = {}
    for name in ("stages", "warnings", "report", "last_report", "stereo_report"):
        value = getattr(recon, name, None)
        if value is None or callable(value):
            continue
        value = _jsonable(value)
        if isinstance(value, dict | list) and value:
            out[name] = value
    return out


def _decode_one(
    batch: _DecodeBatch,
    manifest_path: Path,
    out: Path | None,
    maps_out: Path | None,
    report: Path | None,
    is_batch: bool,
) -> dict[str, float]:
    """Decode (and with a calibration triangulate) one capture; returns its timings (ms)."""
    from appliance.patterns import read_manifest
    from appliance.reconstruct.decode import DecodeParams, decode

    tag = f"{manifest_path.stem}: " if is_batch else ""
    t0 = time.perf_counter()
    man = read_manifest(manifest_path)
    stacks = {cam: man.load_stack(cam) for cam in man.cameras}
    bits = {cam: man.bits_of(st) for cam, st in stacks.items()}
    t1 = time.perf_counter()
    plan = batch.plan(man.sequence)
    shapes = {cam: (int(st.shape[1]), int(st.shape[2])) for cam, st in stacks.items()}
    recon = None
    if batch.calibration_path is not None:
        recon, mode, rc = batch.reconstructor(man, "".join(plan.axes), shapes)
    else:
        if out is not None:
            raise ConfigError("decode: --out needs --calibration (without one, only --maps can be written)")
        rc = batch.rc
        mode = ""
    t2 = time.perf_counter()
    maps = {}
    hdr_white: dict[str, npt.NDArray[np.uint8]] = {}
    for cam, st in stacks.items():
        params = DecodeParams(min_contrast_dn=rc.min_contrast_dn, relative_contrast=rc.relative_contrast,
                              max_value=float((1 << bits[cam]) - 1))
        if man.exposures is None:
            maps[cam] = decode(st, plan, params)
            continue
        # several exposures: each pass decoded on its own, fused per pixel (the brightest unclipped pass)
        from appliance.patterns.sequence import Sequence as PatternSequence
        from appliance.reconstruct.hdr import decode_passes, pick_per_pixel

        maps[cam], choice, passes = decode_passes(st, man.sequence, man.exposures, params)
        greys = []
        for _light, idx in passes:
            sub = PatternSequence(man.sequence.width, man.sequence.height, tuple(man.sequence.frames[i] for i in idx))
            greys.append(_intensity8(st[idx], batch.plan(sub), bits[cam]))
        hdr_white[cam] = np.asarray(pick_per_pixel(greys, choice), np.uint8)
        per_pass = np.bincount(choice[maps[cam].mask], minlength=len(passes)) / max(int(maps[cam].mask.sum()), 1)
        print(f"{tag}{cam}: {len(passes)} exposure passes fused; decoded pixels per pass (darkest first): "
              + ", ".join(f"{100 * s:.1f} %" for s in per_pass))
    t3 = time.perf_counter()
    for note in plan.ignored if man.exposures is None else ():
        print(f"{tag}ignored: {note}")
    for cam, m in maps.items():
        line = f"{tag}{cam}: {int(m.mask.sum())} of {m.mask.size} pixels decoded ({100 * m.mask.mean():.1f} %)"
        for axis, shares in _stripe_summary(m, plan).items():
            if len(shares) > 1:  # some pixels could not resolve the finest stripes
                line += f"; stripe widths {axis}: " + ", ".join(
                    f"{w} px {100 * v:.1f} %" for w, v in shares.items())  # fmt: skip
        print(line)
    cloud = None
    stage_ms = {"triangulate_ms": 0.0, "filter_ms": 0.0}
    if recon is not None:
        white = hdr_white or {cam: _intensity8(st, plan, bits[cam]) for cam, st in stacks.items()}
        cloud, rt = recon.run(maps, white)
        stage_ms = {"triangulate_ms": rt["triangulate_ms"], "filter_ms": rt["filter_ms"]}
    t4 = time.perf_counter()
    for warning in getattr(recon, "warnings", None) or ():
        print(f"{tag}warning: {warning}")
    written: dict[str, str] = {}
    if maps_out is not None:
        path = _target(maps_out, manifest_path, ".npz", is_batch)
        arrays: dict[str, npt.NDArray[Any]] = {}
        for cam, m in maps.items():
            arrays[f"{cam}_u"], arrays[f"{cam}_v"] = m.u, m.v
            arrays[f"{cam}_mask"], arrays[f"{cam}_quality"] = m.mask, m.quality
            if m.levels is not None:
                arrays[f"{cam}_levels"] = m.levels  # Gray bits dropped per axis (finest resolvable bit)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(path, allow_pickle=False, **arrays)
        except OSError as exc:
            raise OutputError(f"{path}: the maps cannot be written ({exc.strerror}); check the folder") from exc
        written["maps"] = str(path)
        print(f"{tag}maps: {path}")
    if cloud is not None:
        from appliance.output.ply import write_ply

        path = _target(out, manifest_path, ".ply", is_batch)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{path.parent}: cannot be created ({exc.strerror}); check --out") from exc
        write_ply(path, cloud, normals=rc.normals and cloud.normal is not None)
        written["cloud"] = str(path)
        print(f"{tag}cloud: {path} ({len(cloud)} points, mode {mode})")
    for note in batch.notes:
        print(f"{tag}note: {note}")
    batch.notes.clear()
    t5 = time.perf_counter()
    times = {
        "load_ms": round((t1 - t0) * 1e3, 3),
        "setup_ms": round((t2 - t1) * 1e3, 3),
        "decode_ms": round((t3 - t2) * 1e3, 3),
        # triangulation (camera-projector: with its filters, one pass), filters, and the rest of the
        # reconstruction (the point cloud, intensities, the per-camera summary): together t4 - t3
        "triangulate_ms": round(stage_ms["triangulate_ms"], 3),
        "filter_ms": round(stage_ms["filter_ms"], 3),
        "cloud_ms": round((t4 - t3) * 1e3 - stage_ms["triangulate_ms"] - stage_ms["filter_ms"], 3),
        "write_ms": round((t5 - t4) * 1e3, 3),
        "total_ms": round((t5 - t0) * 1e3, 3),
    }
    if report is not None:
        _write_report(report, man, plan, maps, cloud, recon, mode, rc, batch, times, written)
    return times


def _write_report(
    report: Path, man: Any, plan: Any, maps: dict[str, Any], cloud: Any, recon: Any, mode: str,
    rc: ReconstructionConfig, batch: _DecodeBatch, times: dict[str, float], written: dict[str, str],
) -> None:  # fmt: skip
    """The JSON sidecar of one offline decode, as a scan writes it."""
    from appliance.output.sidecar import ScanMetadata, write_sidecar

    per_cam: dict[str, Any] = {}
    for i, (cam, m) in enumerate(maps.items()):
        entry: dict[str, Any] = {"decoded_pixels": int(m.mask.sum()), "pixels": int(m.mask.size)}
        if cloud is not None:
            entry["points"] = int(np.sum(cloud.camera == i)) if mode != "stereo" or i == 0 else 0
        stripes = _stripe_summary(m, plan)
        if stripes:
            entry["stripe_widths"] = stripes
        per_cam[cam] = entry
    counts: dict[str, Any] = {"points": len(cloud) if cloud is not None else 0, "cameras": per_cam}
    extra: dict[str, Any] = {"manifest": str(man.path), "ignored_frames": list(plan.ignored)}
    calib_hash = ""
    stages: list[dict[str, Any]] = []
    warnings: list[str] = []
    health: dict[str, Any] = {}
    if recon is not None:
        from appliance.calibration.scan_health import assess_scan

        calib_hash = recon.calibration.hash()
        stages, warnings = [st.as_dict() for st in recon.stages], list(recon.warnings)
        health = assess_scan(recon.residuals, recon.calibration)  # offline: no trend, the tolerance only
        extra.update({
            "mode": mode,
            "calibration_file": str(batch.calibration_path),
            "depth_range_mm": [round(rc.min_depth_mm, 3), round(rc.max_depth_mm, 3)],
        })  # fmt: skip
        extra.update(_reconstruction_report(recon))
    meta = ScanMetadata(
        scan_id=man.path.stem,
        time_utc=dt.datetime.now(dt.UTC).isoformat(),
        sequence={"description": man.sequence.describe(), "frames": len(man.sequence),
                  "projector": [man.sequence.width, man.sequence.height]},
        calibration_hash=calib_hash,
        counts=counts,
        timings_ms=times,
        cameras=list(man.cameras),
        files=written,
        extra=extra,
        stages=stages,
        warnings=warnings,
        calibration_health=health,
    )
    try:
        report.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{report.parent}: cannot be created ({exc.strerror}); check --report") from exc
    write_sidecar(report, meta)
    print(f"report: {report}")
    if health:
        print(f"calibration health: {health['status']}: {health['reason']}")


def _note_compiling(command: str) -> None:
    """One line on stderr before a run that must compile the numba kernels first (after an install or an
    upgrade), so that a person knows why it is slow this once and where the compiled kernels go."""
    from appliance._numba_cache import kernels_on_disk
    from appliance.reconstruct._decode_kernels import decode_stack

    state = kernels_on_disk(decode_stack)
    if state is not None and not state[0]:
        print(f"scan3d {command}: compiling the numba kernels for this version (once, 30-60 s on a small PC; later "
              f"runs load them from {state[1]})", file=sys.stderr, flush=True)


def decode_manifests(
    manifests: list[Path],
    calibration: Path | None,
    out: Path | None,
    maps_out: Path | None,
    timings: bool,
    config: Path | None,
    mode: str | None = None,
    report: Path | None = None,
) -> int:
    """Decode recorded captures offline; with a calibration, triangulate each and write a PLY.

    The mode comes from the calibration (see :func:`choose_decode_mode`) unless ``mode`` is given;
    ``config`` only overrides reconstruction settings (hardware entries are never needed) and the depth
    range defaults to what the calibration's geometry can see. Several manifests are a batch: plans,
    calibration and reconstruction tables are built once, ``out`` (and ``maps_out``) are folders holding
    ``<manifest stem>.ply`` (``.npz``). A capture that fails prints one line; the others go on.

    Returns
    -------
    int
        0 when every capture decoded, 2 when any failed.
    """
    if not manifests:
        raise ConfigError("decode: give at least one manifest")
    is_batch = len(manifests) > 1
    if is_batch and report is not None:
        raise ConfigError("decode: --report writes the sidecar of one capture; give one manifest (or no --report)")
    if is_batch and out is not None and out.suffix.lower() == ".ply":
        raise ConfigError(f"decode: --out {out}: several manifests need a folder (one <stem>.ply each)")
    _note_compiling("decode")
    batch = _DecodeBatch(calibration, config, mode)
    failed = 0
    totals: list[float] = []
    for path in manifests:
        try:
            times = _decode_one(batch, path, out, maps_out, report, is_batch)
        except ApplianceError as exc:
            if not is_batch:
                raise
            failed += 1
            print(f"scan3d decode: {path}: {exc}", file=sys.stderr)
            continue
        totals.append(times["total_ms"])
        if timings:
            print(json.dumps({"capture": path.stem, **times}))
    if timings and totals:
        rest = totals[1:]
        print(json.dumps({
            "summary": True,
            "captures": len(totals),
            "failed": failed,
            "total_ms": round(sum(totals), 3),
            "first_ms": totals[0],
            "median_after_first_ms": round(float(np.median(rest)), 3) if rest else None,
        }))  # fmt: skip
    elif is_batch:
        print(f"decoded {len(totals)} of {len(manifests)} captures" + (f" ({failed} failed)" if failed else ""))
    return 2 if failed else 0


async def _scan_async(cfg: AppConfig, out_dir: Path, count: int, compare: bool) -> int:
    from appliance.hardware.registry import build_rig
    from appliance.output.scanfiles import make_scan_id, write_scan_files
    from appliance.scan import Scanner, load_calibration_for, scan_metadata
    from appliance.sim.accuracy import compare_to_ground_truth

    rig = build_rig(cfg)
    calibration = load_calibration_for(cfg, rig)
    scanner = Scanner(cfg, rig, calibration)
    try:
        t = time.perf_counter()
        _note_compiling("scan")
        await scanner.open()
        await scanner.warm_up()
        print(f"rig ready in {time.perf_counter() - t:.1f} s: {len(cfg.cameras)} camera(s), "
              f"{scanner.sequence.describe()}")
        for i in range(count):
            started = dt.datetime.now(dt.UTC)
            result = await scanner.scan()
            scan_id = make_scan_id(cfg.serial, i + 1, started)
            meta = scan_metadata(scan_id, started.isoformat(), cfg, scanner, result)
            t_w = time.perf_counter()
            folder = out_dir / f"{started:%Y-%m-%d}"
            report = None
            if compare and rig.virtual is not None and cfg.calibration_file is None:
                report = compare_to_ground_truth(result.cloud, rig.virtual, list(cfg.cameras))
                meta.extra["ground_truth"] = report.__dict__
            meta.timings_ms["write_ms"] = 0.0
            files = write_scan_files(folder, meta, result.cloud, list(result.shapes.values()),
                                     normals=cfg.output.normals and result.cloud.normal is not None,
                                     preview=cfg.output.preview)
            tm = result.timings_ms
            print(f"scan {scan_id}: {len(result.cloud)} points in {tm['scan_ms']:.0f} ms "
                  f"(capture+decode {tm['capture_ms']:.0f} ms, reconstruct {tm['reconstruct_ms']:.0f} ms, "
                  f"write {1e3 * (time.perf_counter() - t_w):.0f} ms)")
            print(f"  cloud:   {files.cloud}\n  sidecar: {files.sidecar}\n  preview: {files.preview}")
            if report is not None:
                print(f"  error against ground truth: {report.line()}")
    finally:
        await scanner.close()
    return 0


async def scan_command(config: Path, out: Path | None, count: int, compare: bool) -> int:
    """Run ``count`` scans on the configured rig and write their files (``cli.py`` runs the coroutine)."""
    cfg = await asyncio.to_thread(load_config, config)
    return await _scan_async(cfg, out or cfg.output.directory, count, compare)


def validate_config(path: Path) -> int:
    """Validate a configuration file; print what is wrong (exit 1) or a summary (exit 0)."""
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        print(str(exc))
        return 1
    from appliance.config.loader import check_files

    problems = check_files(cfg, str(path))
    if problems:
        print("\n".join(problems))
        return 1
    cams = ", ".join(f"{n} ({c.type})" for n, c in cfg.cameras.items())
    print(f"{path}: valid. cameras: {cams}; projector: {cfg.projector.type}; trigger: {cfg.trigger.type}; "
          f"sequence: {cfg.sequence.kind} {cfg.sequence.axes}")
    return 0


def devices_command(config: Path, discover: bool = False) -> int:
    """Print each configured device and whether it answers (no broadcast unless ``discover``)."""
    cfg = load_config(config)
    from appliance.hardware.registry import backend

    lines = [f"camera {name}: {backend('camera', cam).probe(cam)}" for name, cam in cfg.cameras.items()]
    lines.append(f"projector: {backend('projector', cfg.projector).probe(cfg.projector)}")
    lines.append(f"trigger: {backend('trigger', cfg.trigger).probe(cfg.trigger)}")
    if discover:
        from appliance.hardware.devices_probe import discover_aravis

        lines.append("GigE/USB3 Vision discovery (broadcast on every interface):")
        lines.extend(f"  {d}" for d in discover_aravis())
    print("\n".join(lines))
    return 0


async def grab_command(config: Path, camera: str, frames: int, out: Path) -> int:
    """Grab software-triggered frames from one camera into PNG files (``cli.py`` runs the coroutine)."""
    from appliance.hardware.devices_probe import grab_frames

    cfg = await asyncio.to_thread(load_config, config)
    paths = await grab_frames(cfg, camera, frames, out)
    for p in paths:
        print(p)
    return 0


def virtual_rig_frames(config: Path, camera: str | None) -> Any:
    """The virtual rig's rendering of the configured sequence for one camera (the first when None).

    Returns an :class:`appliance.fakes.gige.FrameSource` of shape (F, H, W).
    """
    from appliance.fakes.gige import StackProvider
    from appliance.patterns.from_config import build_sequence
    from appliance.sim.rig import VirtualRig

    cfg = load_config(config)
    rig = VirtualRig(cfg.virtual_rig, base_dir=Path(config).parent)
    name = camera if camera is not None else next(iter(rig.cameras))
    if name not in rig.cameras:
        raise ConfigError(f"{config}: camera {name!r} is not in virtual_rig.cameras ({sorted(rig.cameras)})")
    sequence = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    return StackProvider(np.asarray(rig.render(sequence, name)))


def simulate_camera_command(
    address: str, serial: str, camera: str | None, manifest: Path | None, config: Path, packet_loss: float
) -> int:
    """``scan3d simulate-camera``: serve a manifest's (or else the virtual rig's) frames as a GigE Vision camera."""
    from appliance.fakes.gige import StackProvider, serve_fake_camera
    from appliance.patterns import read_manifest

    if manifest is not None:
        recorded = read_manifest(manifest)
        name = camera if camera is not None else recorded.cameras[0]
        source = StackProvider(np.asarray(recorded.load_stack(name)))
    else:
        source = virtual_rig_frames(config, camera)
    return serve_fake_camera(source, address, serial, packet_loss=packet_loss)
