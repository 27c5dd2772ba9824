"""What the one-shot commands do (``patterns``, ``decode``, ``scan``, ``validate-config``, ``devices``, ``grab``).

Each function prints for a person and returns an exit status; ``cli.py`` only parses arguments.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.config import AppConfig, load_config
from appliance.config.schema import ReconstructionConfig
from appliance.errors import ApplianceError, ConfigError, ManifestError


def _config_or_default(path: Path | None) -> AppConfig:
    if path is not None and Path(path).exists():
        return load_config(path)
    return AppConfig()


def write_patterns(out: Path, config: Path | None, width: int | None, height: int | None) -> int:
    """Write the configured sequence's projector images (PNG) and a manifest into ``out``."""
    import cv2

    from appliance.patterns import render_frame, write_manifest
    from appliance.scan import build_sequence

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
    """Decode a recorded capture; with a calibration, triangulate and write a PLY."""
    from appliance.patterns import read_manifest
    from appliance.reconstruct.decode import DecodeParams, decode, plan_decode

    t0 = time.perf_counter()
    cfg = _config_or_default(config) if config is not None else None
    rc = cfg.reconstruction if cfg is not None else ReconstructionConfig()
    man = read_manifest(manifest_path)
    plan = plan_decode(man.sequence)
    stacks = {cam: man.load_stack(cam) for cam in man.cameras}
    t1 = time.perf_counter()
    params = DecodeParams(min_contrast_dn=rc.min_contrast_dn, relative_contrast=rc.relative_contrast)
    maps = {cam: decode(stacks[cam], man.sequence, params) for cam in man.cameras}
    t2 = time.perf_counter()
    for note in plan.ignored:
        print(f"ignored: {note}")
    for cam, m in maps.items():
        print(f"{cam}: {int(m.mask.sum())} of {m.mask.size} pixels decoded ({100 * m.mask.mean():.1f} %)")
    if maps_out is not None:
        arrays: dict[str, npt.NDArray[Any]] = {}
        for cam, m in maps.items():
            arrays[f"{cam}_u"], arrays[f"{cam}_v"] = m.u, m.v
            arrays[f"{cam}_mask"], arrays[f"{cam}_quality"] = m.mask, m.quality
        maps_out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(maps_out, allow_pickle=False, **arrays)
        print(f"maps: {maps_out}")
    t3 = t4 = time.perf_counter()
    if calibration is not None:
        from appliance.geometry.calibration_file import read_calibration
        from appliance.output.ply import write_ply
        from appliance.reconstruct.pipeline import Reconstructor

        calib = read_calibration(calibration)
        missing = [c for c in man.cameras if c not in calib.devices]
        if missing:
            raise ManifestError(
                f"{manifest_path}: camera(s) {missing} have no entry in {calibration} (it has "
                f"{list(calib.devices)}); name the manifest's cameras as in the calibration"
            )
        white_idx = next((i for i, f in enumerate(man.sequence.frames) if f.pattern == "white"), None)
        white = {}
        for cam, st in stacks.items():
            w = st[white_idx] if white_idx is not None else np.zeros(st.shape[1:], st.dtype)
            white[cam] = w if w.dtype == np.uint8 else (w >> 8).astype(np.uint8)
        sub = {name: calib.devices[name] for name in [*man.cameras, "projector"] if name in calib.devices}
        recon = Reconstructor(type(calib)(sub), "".join(plan.axes), rc)
        cloud, _ = recon.run(maps, white)
        t3 = time.perf_counter()
        out = out or manifest_path.with_suffix(".ply")
        write_ply(out, cloud, normals=rc.normals and cloud.normal is not None)
        t4 = time.perf_counter()
        print(f"cloud: {out} ({len(cloud)} points)")
    elif out is not None:
        raise ConfigError("decode: --out needs --calibration (without one, only --maps can be written)")
    if timings:
        print(json.dumps({
            "load_ms": round((t1 - t0) * 1e3, 3),
            "decode_ms": round((t2 - t1) * 1e3, 3),
            "triangulate_ms": round((t3 - t2) * 1e3, 3) if calibration is not None else 0.0,
            "write_ms": round((t4 - t3) * 1e3, 3),
            "total_ms": round((time.perf_counter() - t0) * 1e3, 3),
        }))
    return 0


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


def scan_command(config: Path, out: Path | None, count: int, compare: bool) -> int:
    """Run ``count`` scans on the configured rig and write their files."""
    cfg = load_config(config)
    return asyncio.run(_scan_async(cfg, out or cfg.output.directory, count, compare))


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
    lines: list[str] = []
    for name, cam in cfg.cameras.items():
        if cam.type == "sim":
            lines.append(f"camera {name}: sim (virtual rig) — ok")
        elif cam.type == "aravis":
            from appliance.hardware.devices_probe import probe_aravis

            lines.append(f"camera {name}: aravis {cam.address or cam.serial} — "
                         f"{probe_aravis(cam.address) if cam.address else 'by serial: needs --discover'}")
        else:
            lines.append(f"camera {name}: uvc {cam.device} — "
                         f"{'present' if Path(cam.device).exists() else 'absent'}")
    p = cfg.projector
    if p.type == "lightcrafter4500":
        from appliance.hardware.lightcrafter4500 import probe_lightcrafter

        lines.append(f"projector: lightcrafter4500 — {probe_lightcrafter()}")
    else:
        lines.append(f"projector: {p.type}")
    t = cfg.trigger
    if t.type == "serial":
        from appliance.hardware.serial import probe_serial

        lines.append(f"trigger: serial {t.port} — {probe_serial(t.port)}")
    elif t.type == "gpio":
        lines.append(f"trigger: gpio {t.chip} line {t.line} — "
                     f"{'present' if Path(t.chip).exists() else 'absent'}")
    else:
        lines.append("trigger: sim")
    if discover:
        from appliance.hardware.devices_probe import discover_aravis

        lines.append("GigE/USB3 Vision discovery (broadcast on every interface):")
        lines.extend(f"  {d}" for d in discover_aravis())
    print("\n".join(lines))
    return 0


def grab_command(config: Path, camera: str, frames: int, out: Path) -> int:
    """Grab software-triggered frames from one camera into PNG files."""
    from appliance.hardware.devices_probe import grab_frames

    cfg = load_config(config)
    paths = grab_frames(cfg, camera, frames, out)
    for p in paths:
        print(p)
    return 0
