"""What the one-shot commands do (``patterns``, ``decode``, ``scan``, ``validate-config``, ``devices``, ``grab``).

Each function prints for a person and returns an exit status; ``cli.py`` only parses arguments.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from appliance.atomic_write import same_file
from appliance.config import AppConfig, load_config
from appliance.config.schema import ReconstructionConfig
from appliance.errors import ApplianceError, ConfigError, OutputError

if TYPE_CHECKING:
    from appliance.hardware.registry import Rig
    from appliance.replay import ReplayBatch, ScanResult
    from appliance.scan import Scanner


def _config_or_default(path: Path | None) -> AppConfig:
    if path is not None and Path(path).exists():
        return load_config(path)
    if path is not None and Path(path) != Path("config/appliance.yaml"):  # named, not the last-resort default
        raise ConfigError(f"{path}: configuration file not found; fix --config, or leave it out for the defaults")
    return AppConfig()


MIN_IMAGE_PX, MAX_IMAGE_PX = 16, 10_000
"""Bounds of a projector's width and height given on the command line (px), as the configuration's."""


def write_patterns(out: Path, config: Path | None, width: int | None, height: int | None) -> int:
    """Write the configured sequence's projector images (PNG) and a manifest into ``out``."""
    import cv2

    from appliance.output.atomic import write_files_atomic
    from appliance.patterns import render_frame
    from appliance.patterns.from_config import build_sequence
    from appliance.patterns.manifest import manifest_text

    for key, size in (("--width", width), ("--height", height)):
        if size is not None and not MIN_IMAGE_PX <= size <= MAX_IMAGE_PX:
            raise ConfigError(f"patterns: {key} {size}: must be from {MIN_IMAGE_PX} to {MAX_IMAGE_PX} projector "
                              "pixels (or left out for the configured projector's)")
    cfg = _config_or_default(config)
    w = width if width is not None else cfg.virtual_rig.projector.width
    h = height if height is not None else cfg.virtual_rig.projector.height
    seq = build_sequence(cfg.sequence, w, h)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
        raise OutputError(f"{str(out)!r}: cannot be created ({getattr(exc, 'strerror', None) or exc}); "
                          "give --out a folder that can be made") from exc
    files: dict[str, bytes] = {}
    for i, frame in enumerate(seq.frames):
        name = f"pattern_{i:03d}.png"
        ok, png = cv2.imencode(".png", render_frame(frame, w, h))
        if not ok:
            raise ApplianceError(f"{out / name}: the PNG encoder failed; check the projector size")
        files[name] = png.tobytes()
    names = list(files)
    files["manifest.yaml"] = manifest_text(seq, ["projector"], images={"projector": names}).encode()
    write_files_atomic(out, files)  # all or none: a full disk keeps the previous images and manifest whole
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

    from appliance.config.loader import MAX_CONFIG_BYTES
    from appliance.config.yamlfile import parse_yaml, read_text_file

    text = read_text_file(path, what="configuration", error=ConfigError, limit_bytes=MAX_CONFIG_BYTES,
                          fix="check --config")
    try:
        doc, root = parse_yaml(text)
    except (yaml.YAMLError, RecursionError) as exc:
        raise ConfigError(f"{path}: not a YAML text file ({' '.join(str(exc).split())[:200]})") from exc
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: not a YAML mapping; give a file with a 'reconstruction:' section")
    try:
        return _Reconstruction.model_validate(doc).reconstruction
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, str(path), doc, root)) from exc


def _target(base: Path | None, manifest: Path, suffix: str, batch: bool) -> Path:
    """Where a capture's file goes: ``base`` itself (one capture, a file name), or ``base/<stem><suffix>``."""
    if base is None:
        return manifest.with_suffix(suffix)
    if batch or base.is_dir() or base.suffix == "":
        return base / f"{manifest.stem}{suffix}"
    return base


def _decode_outputs(manifest: Path, out: Path | None, maps_out: Path | None, report: Path | None, batch: bool,
                    cloud: bool) -> list[tuple[str, Path]]:
    """The files ``scan3d decode`` writes for one capture, each with the option that names it."""
    outputs = []
    if out is not None and cloud:
        ply = _target(out, manifest, ".ply", batch)
        outputs += [("--out", ply), ("the preview of --out", ply.with_suffix(".png"))]
    if maps_out is not None:
        outputs.append(("--maps", _target(maps_out, manifest, ".npz", batch)))
    if report is not None:
        outputs.append(("--report", report))
    return outputs


def _refuse_overwriting(outputs: list[tuple[str, Path]], inputs: list[tuple[str, Path]]) -> None:
    """An output that is one of the inputs, or another output, would destroy it: refuse before writing."""
    seen = list(inputs)
    for what, p in outputs:
        other = same_file(p, seen)
        if other is not None:
            raise ConfigError(f"decode: {what} {p} is also {other[0]} {other[1]}: writing it would destroy that "
                              "file; choose another output path")
        seen.append((what, p))


def _make_folder_of(path: Path, option: str) -> None:
    """The folder of an output file ``option`` names, made if absent; one line when it cannot be."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        why = "is a file, not a folder" if path.parent.exists() else f"cannot be created ({exc.strerror})"
        raise OutputError(f"{path.parent}: {why}; check {option}") from exc


def _decode_one(
    batch: ReplayBatch,
    manifest_path: Path,
    out: Path | None,
    maps_out: Path | None,
    report: Path | None,
    is_batch: bool,
) -> dict[str, float]:
    """Decode (and with a calibration reconstruct) one capture through the replay path; print what it did and
    write its files. Returns its timings (ms)."""
    from appliance.output.atomic import write_atomic
    from appliance.reconstruct.decode import reason_advice
    from appliance.replay import replay_capture, result_files, scan_metadata, stripe_summary

    tag = f"{manifest_path.stem}: " if is_batch else ""
    got = replay_capture(batch, manifest_path, cloud_wanted=out is not None)
    man, plan, maps, result, setup = got.manifest, got.plan, got.maps, got.result, got.setup
    frames = [("a frame of the capture", f) for files in (man.images or {}).values() for f in files]
    frames += [("a frame stack of the capture", f) for f in (man.stacks or {}).values()]
    _refuse_overwriting(_decode_outputs(manifest_path, out, maps_out, report, is_batch, result is not None), frames)
    for cam, shares in got.exposure_shares.items():
        print(f"{tag}{cam}: {len(shares)} exposure passes fused; decoded pixels per pass (darkest first): "
              + ", ".join(f"{100 * s:.1f} %" for s in shares))
    for note in plan.ignored if man.exposures is None else ():
        print(f"{tag}ignored: {note}")
    stripes = {cam: stripe_summary(m, plan) for cam, m in maps.items()}
    for cam, m in maps.items():
        line = f"{tag}{cam}: {int(m.mask.sum())} of {m.mask.size} pixels decoded ({100 * m.mask.mean():.1f} %)"
        for axis, shares_w in stripes[cam].items():
            if len(shares_w) > 1:  # some pixels could not resolve the finest stripes
                line += f"; stripe widths {axis}: " + ", ".join(
                    f"{w} px {100 * v:.1f} %" for w, v in shares_w.items())  # fmt: skip
        if m.separated is not None and len(m.separated):
            line += (f"; {len(m.separated)} of them lit by two copies of the pattern (a mirror), the direct one "
                     "taken apart")
        print(line)
        advice = reason_advice(m, cam)
        if advice:
            print(f"{tag}{advice}")
    t0, t4 = got.span_s  # printing and writing count as write_ms
    for warning in result.warnings if result is not None else ():
        print(f"{tag}warning: {warning}")
    written: dict[str, str] = {}
    if maps_out is not None:
        path = _target(maps_out, manifest_path, ".npz", is_batch)
        arrays: dict[str, np.ndarray[Any, Any]] = {}
        for cam, m in maps.items():
            arrays[f"{cam}_u"], arrays[f"{cam}_v"] = m.u, m.v
            arrays[f"{cam}_mask"], arrays[f"{cam}_quality"] = m.mask, m.quality
            if m.levels is not None:
                arrays[f"{cam}_levels"] = m.levels  # Gray bits dropped per axis (finest resolvable bit)
            if m.reason is not None:
                arrays[f"{cam}_reason"] = m.reason  # why a pixel has no code (reconstruct.types.Reason)
            if m.fringe is not None:
                arrays[f"{cam}_fringe"] = m.fringe  # % of the white - black range that carries the pattern
        _make_folder_of(path, "--maps")
        # through the atomic writer: a full disk keeps an existing file whole
        write_atomic(path, lambda f: np.savez_compressed(f, allow_pickle=False, **arrays))
        written["maps"] = str(path)
        print(f"{tag}maps: {path}")
    per_cam: dict[str, dict[str, object]] = {cam: {"stripe_widths": st} if st else {} for cam, st in stripes.items()}
    extra: dict[str, Any] = {"manifest": str(man.path), "ignored_frames": list(plan.ignored)}
    meta = None
    if result is not None and setup is not None:
        rc = setup.settings
        extra.update({
            "mode": setup.mode,
            "calibration_file": str(batch.calibration_path),
            "depth_range_mm": [round(rc.min_depth_mm, 3), round(rc.max_depth_mm, 3)],
        })  # fmt: skip
        meta = scan_metadata(man.path.stem, dt.datetime.now(dt.UTC).isoformat(), man.sequence,
                             setup.reconstructor.calibration, list(man.cameras), result, extra=extra,
                             per_camera=per_cam)  # fmt: skip
        path = _target(out, manifest_path, ".ply", is_batch)
        _make_folder_of(path, "--out")
        # the same files as a scan's (the preview beside the cloud, the pixels without a point striped by
        # reason); an offline PLY carries no header comment
        ply, png = result_files(meta, result, normals=rc.normals and result.cloud.normal is not None, preview=True,
                                ply_comments=[])[:2]  # fmt: skip
        write_atomic(path, ply.write_to)
        written["cloud"] = str(path)
        preview_path = write_atomic(path.with_suffix(".png"), png.write_to)
        written["preview"] = str(preview_path)
        print(f"{tag}cloud: {path} ({len(result.cloud)} points, mode {setup.mode}); preview: {preview_path}")
    t5 = time.perf_counter()
    times = {**got.timings_ms, "write_ms": round((t5 - t4) * 1e3, 3), "total_ms": round((t5 - t0) * 1e3, 3)}
    if report is not None:
        _write_report(report, meta, got, times, written, per_cam, extra)
    return times


def _write_report(
    report: Path, meta: Any, got: Any, times: dict[str, float], written: dict[str, str],
    per_cam: dict[str, dict[str, object]], extra: dict[str, Any],
) -> None:  # fmt: skip
    """The JSON sidecar of one offline decode: a scan's sidecar (:func:`appliance.replay.scan_metadata`), or
    without a calibration the decode's counts alone."""
    from appliance.output.sidecar import ScanMetadata, write_sidecar

    if meta is None:
        man = got.manifest
        from appliance.reconstruct.decode import reason_block

        cams = {cam: {"decoded_pixels": int(m.mask.sum()), "pixels": int(m.mask.size), **reason_block(m),
                      **per_cam[cam]} for cam, m in got.maps.items()}  # fmt: skip
        meta = ScanMetadata(
            scan_id=man.path.stem, time_utc=dt.datetime.now(dt.UTC).isoformat(),
            sequence={"description": man.sequence.describe(), "frames": len(man.sequence),
                      "projector": [man.sequence.width, man.sequence.height]},
            calibration_hash="", counts={"points": 0, "cameras": cams}, timings_ms={}, cameras=list(man.cameras),
            extra=extra,
        )  # fmt: skip
    meta.timings_ms = times
    meta.files = written
    _make_folder_of(report, "--report")
    write_sidecar(report, meta)
    print(f"report: {report}")
    health = meta.calibration_health
    if health:
        print(f"calibration health: {health['status']}: {health['reason']}")


def _note_compiling(command: str) -> None:
    """One line on stderr before a run that must compile the numba kernels first (after an install or an
    upgrade), so that a person knows why it is slow this once and where the compiled kernels go."""
    from appliance.reconstruct.decode import kernels_compiled

    state = kernels_compiled()
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

    The mode comes from the calibration (see :func:`appliance.replay.choose_decode_mode`) unless ``mode`` is given;
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
    if is_batch and (out is not None or maps_out is not None):
        by_stem: dict[str, Path] = {}
        for m in manifests:
            other = by_stem.setdefault(m.stem, m)
            if other is not m and os.path.realpath(other) == os.path.realpath(m):
                raise ConfigError(f"decode: {m} is given twice; its {m.stem}.ply/.npz would be written twice; give "
                                  "each capture once")
            if other is not m:
                raise ConfigError(f"decode: {other} and {m} would both write {m.stem}.ply/.npz into the --out/--maps "
                                  "folder, the second replacing the first; give the captures different names or "
                                  "decode them one at a time")
    inputs = [("the manifest", m) for m in manifests]
    inputs += [(f"--{what}", p) for what, p in (("calibration", calibration), ("config", config)) if p is not None]
    for m in manifests:  # before any work: an output that is an input (or another output) would destroy it
        _refuse_overwriting(_decode_outputs(m, out, maps_out, report, is_batch, calibration is not None), inputs)
    _note_compiling("decode")
    from appliance.replay import ReplayBatch

    settings = reconstruction_settings(config) if config is not None else ReconstructionConfig()
    batch = ReplayBatch(calibration, settings, mode)
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
    t = time.perf_counter()

    def make() -> tuple[Rig, Scanner]:  # imports, renders the virtual rig's scene, builds ray tables: off the loop
        from appliance.hardware.registry import build_rig
        from appliance.scan import Scanner, load_calibration_for

        _note_compiling("scan")
        rig = build_rig(cfg)
        return rig, Scanner(cfg, rig, load_calibration_for(cfg, rig))

    rig, scanner = await asyncio.to_thread(make)
    failed = 0
    try:
        await scanner.open()
        await scanner.warm_up()
        print(f"rig ready in {time.perf_counter() - t:.1f} s: {len(cfg.cameras)} camera(s), "
              f"{scanner.sequence.describe()}")

        def write(i: int, started: dt.datetime, result: ScanResult) -> int:
            """The scan's files (rendered, compared with the truth, written: off the event loop); 1 if spooled."""
            from appliance.output.atomic import write_atomic
            from appliance.output.scanfiles import make_scan_id
            from appliance.replay import result_files, scan_metadata
            from appliance.sim.accuracy import compare_to_ground_truth

            failed = 0
            scan_id = make_scan_id(cfg.serial, i + 1, started)
            meta = scan_metadata(scan_id, started.isoformat(), scanner.sequence, scanner.calibration, list(cfg.cameras),
                                 result, serial=cfg.serial)  # fmt: skip
            t_w = time.perf_counter()
            folder = out_dir / f"{started:%Y-%m-%d}"
            report = None
            if compare and rig.virtual is not None and cfg.calibration_file is None:
                report = compare_to_ground_truth(result.cloud, rig.virtual, list(cfg.cameras))
                meta.extra["ground_truth"] = report.__dict__
            meta.timings_ms["write_ms"] = 0.0
            contents = result_files(meta, result, normals=cfg.output.normals and result.cloud.normal is not None,
                                    preview=cfg.output.preview)  # fmt: skip
            try:
                folder.mkdir(parents=True, exist_ok=True)
                paths = [write_atomic(folder / c.name, c.write_to) for c in contents]  # the sidecar last
            except (OSError, OutputError) as exc:  # the scan is not lost: the spool keeps it, as in the service
                paths = _spool_scan(cfg, f"{started:%Y-%m-%d}", scan_id, contents)
                print(f"scan3d scan: {folder}: cannot be written ({exc}); scan {scan_id} kept in the spool "
                      f"{paths[0].parent} (scan3d run delivers it to the share)", file=sys.stderr)
                failed = 1
            tm = result.timings_ms
            print(f"scan {scan_id}: {len(result.cloud)} points in {tm['scan_ms']:.0f} ms "
                  f"(capture+decode {tm['capture_ms']:.0f} ms, reconstruct {tm['reconstruct_ms']:.0f} ms, "
                  f"write {1e3 * (time.perf_counter() - t_w):.0f} ms)")
            print(f"  cloud:   {paths[0]}\n  sidecar: {paths[-1]}\n  preview: {paths[1] if len(paths) > 2 else None}")
            if report is not None:
                print(f"  error against ground truth: {report.line()}")
            return failed

        for i in range(count):
            started = dt.datetime.now(dt.UTC)
            result = await scanner.scan()
            failed += await asyncio.to_thread(write, i, started, result)
    finally:
        await scanner.close()
    return 2 if failed else 0


def _spool_scan(cfg: AppConfig, day: str, scan_id: str, contents: list[Any]) -> list[Path]:
    """Keep one scan's files in the service's spool (``output.spool_directory``); its paths."""
    import shutil

    from appliance.output.spool import Spool

    spool = Spool(Path(cfg.output.spool_directory), cfg.output, lambda p: shutil.disk_usage(p).free)
    try:
        return spool.write(day, scan_id, contents)
    except OSError as exc:
        raise OutputError(f"scan {scan_id}: neither the output folder nor the spool {spool.directory} can be "
                          f"written ({exc.strerror or exc}); the scan is lost: free space or fix the folders") from exc


async def scan_command(config: Path, out: Path | None, count: int, compare: bool) -> int:
    """Run ``count`` scans on the configured rig and write their files (``cli.py`` runs the coroutine)."""
    if count < 1:
        raise ConfigError(f"scan: --count {count}: must be at least 1 (scans)")
    cfg = await asyncio.to_thread(load_config, config)
    from appliance.config.loader import folder_problem

    out_dir = out or cfg.output.directory
    why = folder_problem(out_dir, True)  # before the capture, so no scan is made that cannot be written
    if why:
        where = "--out" if out is not None else "output.directory"
        raise OutputError(f"scan: {where} {str(out_dir)!r}: {why}; give a writable folder")
    return await _scan_async(cfg, out_dir, count, compare)


def validate_config(path: Path) -> int:
    """Validate a configuration file; print what is wrong (exit 1) or a summary (exit 0)."""
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        print(str(exc))
        return 1
    from appliance.config.loader import check_files

    problems = check_files(cfg, str(path))
    if cfg.calibration_file is not None and not any("calibration_file" in p for p in problems):
        from appliance.geometry.calibration_file import read_calibration

        try:  # readable is not enough: the service would read it at every start and fail
            read_calibration(cfg.calibration_file)
        except ApplianceError as exc:
            problems.append(f"{path}: calibration_file: {exc}")
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

    if frames < 1:
        raise ConfigError(f"grab: --frames {frames}: must be at least 1 (frames)")
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

    if not 0 <= packet_loss <= 1:  # NaN too
        raise ConfigError(f"simulate-camera: --packet-loss {packet_loss}: must be a share from 0 to 1")
    if manifest is not None:
        recorded = read_manifest(manifest)
        name = camera if camera is not None else recorded.cameras[0]
        source = StackProvider(np.asarray(recorded.load_stack(name)))
    else:
        source = virtual_rig_frames(config, camera)
    return serve_fake_camera(source, address, serial, packet_loss=packet_loss)
