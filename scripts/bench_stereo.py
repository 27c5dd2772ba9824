"""Camera-camera benchmark (part of scripts/bench): two 1920x1280 cameras, Gray-only codes in OpenCV's layout.

Rendered by the virtual rig (projector 1280x800, columns and rows, each bit with its inverse, white, black:
44 frames per camera). Measured in one run: our decode of both stacks + camera-camera triangulation (warm),
OpenCV contrib's ``GrayCodePattern.decode`` on the very same frames (in ``.bench-venv``), and ``scan3d decode``
of a batch of five manifests of the capture (per-capture times after the first against the warm figure).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from bench_common import REPO, median_ms, parallel_read_floor

BATCH = 5
"""Captures in the batch decode (one process); the figure is the median of those after the first."""
COARSE_CELL_PX = 8.0
"""The camera-camera path timed once more with code cells of at least this many camera px (the default is
``StereoTriangulator.cell_min_px``): what the time would be if the per-cell work were nearly free, and what
accuracy that costs."""

OPENCV_STACKS = r"""
import sys, time, json, statistics
import cv2, numpy as np
a, b, repeats = np.load(sys.argv[1]), np.load(sys.argv[2]), int(sys.argv[3])
n = a.shape[0] - 2
pats = [[f for f in a[:n]], [f for f in b[:n]]]
g = cv2.structured_light.GrayCodePattern.create(1280, 800)
kw = dict(blackImages=[a[n + 1], b[n + 1]], whiteImages=[a[n], b[n]])
ok, disp = g.decode(pats, **kw)
times = []
for _ in range(repeats):
    t = time.perf_counter(); g.decode(pats, **kw); times.append((time.perf_counter() - t) * 1e3)
print(json.dumps({"opencv_version": cv2.__version__, "opencv_decode_ms": statistics.median(times), "ok": bool(ok)}))
"""


def _ms(fn: Any, repeats: int) -> float:
    return median_ms(fn, repeats)[0]


def _error_stats(xyz: np.ndarray, truth: np.ndarray) -> tuple[int, float, float]:
    """Points, median and p99 distance (mm) of an (H, W, 3) cloud from the true (H, W, 3) surface, NaN left out."""
    err = np.linalg.norm(xyz - truth, axis=2)
    err = err[np.isfinite(err)]
    if not err.size:
        return 0, float("nan"), float("nan")
    return int(err.size), float(np.median(err)), float(np.percentile(err, 99))


def bench_stereo(repeats: int) -> dict[str, Any]:
    """Decode + camera-camera triangulation of two 1920x1280 Gray-only stacks; OpenCV contrib; batch decode."""
    from appliance.config.schema import DeviceOptics, PlaneObject, SphereObject, VirtualRigConfig
    from appliance.geometry.calibration_file import Calibration, write_calibration
    from appliance.patterns import BlackFrame, GrayFrame, Sequence, WhiteFrame, write_manifest
    from appliance.reconstruct.decode import decode, plan_decode
    from appliance.reconstruct.stereo import StereoTriangulator
    from appliance.sim.rig import VirtualRig

    cams = {
        "cam0": DeviceOptics(width=1920, height=1280, focal_px=2600.0, position_mm=(0.0, 0.0, 0.0),
                             look_at_mm=(0.0, 0.0, 1000.0)),
        "cam1": DeviceOptics(width=1920, height=1280, focal_px=2600.0, position_mm=(300.0, 0.0, 0.0),
                             look_at_mm=(0.0, 0.0, 1000.0)),
    }  # fmt: skip
    proj = DeviceOptics(width=1280, height=800, focal_px=1500.0, position_mm=(150.0, -60.0, 0.0),
                        look_at_mm=(0.0, 0.0, 1000.0))  # fmt: skip
    scene = (PlaneObject(point_mm=(0.0, 0.0, 1100.0), normal=(0.1, 0.1, -1.0), texture=0.3),
             SphereObject(center_mm=(0.0, 0.0, 950.0), radius_mm=120.0, texture=0.2))  # fmt: skip
    rig = VirtualRig(VirtualRigConfig(projector=proj, cameras=cams, scene=scene))
    frames: list[Any] = []
    for axis, bits in (("x", 11), ("y", 10)):
        for b in range(bits - 1, -1, -1):
            frames += [GrayFrame(axis, b, False), GrayFrame(axis, b, True)]
    frames += [WhiteFrame(), BlackFrame()]
    seq = Sequence(1280, 800, tuple(frames))
    t0 = time.perf_counter()
    stacks = {n: rig.render(seq, n) for n in ("cam0", "cam1")}
    render_s = time.perf_counter() - t0
    plan = plan_decode(seq)
    tri = StereoTriangulator(rig.cameras["cam0"], rig.cameras["cam1"])

    def decode_both() -> dict[str, Any]:
        return {n: decode(s, plan) for n, s in stacks.items()}

    maps = decode_both()
    # memory floors: one numpy pass reading both stacks' frames, and one writing an (H, W, 3) float32 cloud
    t_read = _ms(lambda: [np.add.reduce(s, axis=0, dtype=np.uint16) for s in stacks.values()], repeats)
    read_all = parallel_read_floor()
    t_read_par = _ms(lambda: [read_all(s) for s in stacks.values()], repeats)
    cloud = np.empty((*stacks["cam0"].shape[1:], 3), np.float32)
    t_write = _ms(lambda: cloud.fill(1.0), repeats)
    t_dec = _ms(decode_both, repeats)
    t_tri = _ms(lambda: tri.triangulate(maps["cam0"], maps["cam1"]), repeats)
    t_all = _ms(lambda: tri.triangulate(*decode_both().values()), repeats)
    # the same on one core: how the work scales (compute-bound work halves with the second core, a pass
    # limited by memory bandwidth does not)
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        t_all_1 = _ms(lambda: tri.triangulate(*decode_both().values()), max(3, repeats // 3))
    finally:
        numba.set_num_threads(threads)
    truth = rig.ground_truth("cam0").xyz
    # How far the cell size moves the time: the same path with code cells of at least COARSE_CELL_PX camera px
    # (far fewer cells than the default, so the per-cell work nearly vanishes and what is left is the
    # per-pixel work: decode, cell sums, each pixel's match), and what it costs in accuracy.
    coarse = StereoTriangulator(rig.cameras["cam0"], rig.cameras["cam1"])
    coarse.cell_min_px = COARSE_CELL_PX
    t_coarse = _ms(lambda: coarse.triangulate(*decode_both().values()), repeats)
    points, median_mm, p99_mm = _error_stats(tri.triangulate(maps["cam0"], maps["cam1"]), truth)
    _, coarse_median_mm, coarse_p99_mm = _error_stats(coarse.triangulate(maps["cam0"], maps["cam1"]), truth)
    res: dict[str, Any] = {
        "shape": list(stacks["cam0"].shape), "render_s": render_s, "decode_ms": t_dec, "triangulate_ms": t_tri,
        "decode_triangulate_ms": t_all, "decode_triangulate_1thread_ms": t_all_1, "threads": threads,
        "points": points, "candidates": int(maps["cam0"].mask.sum()), "median_error_mm": median_mm,
        "floor_read_ms": t_read, "floor_read_parallel_ms": t_read_par, "floor_write_ms": t_write,
        "p99_error_mm": p99_mm, "coarse_cell_px": COARSE_CELL_PX, "coarse_decode_triangulate_ms": t_coarse,
        "coarse_median_error_mm": coarse_median_mm, "coarse_p99_error_mm": coarse_p99_mm,
    }  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for n, s in stacks.items():
            np.save(folder / f"{n}.npy", s)
        py = REPO / ".bench-venv" / "bin" / "python"
        if py.exists():
            out = subprocess.run([str(py), "-c", OPENCV_STACKS, str(folder / "cam0.npy"), str(folder / "cam1.npy"),
                                  str(max(3, repeats // 3))], capture_output=True, text=True, timeout=1800,
                                 check=False)  # fmt: skip
            if out.returncode == 0:
                res.update(json.loads(out.stdout.strip().splitlines()[-1]))
                res["speedup"] = res["opencv_decode_ms"] / t_all
            else:
                res["opencv_skipped"] = out.stderr.strip()[-300:]
        else:
            res["opencv_skipped"] = "no .bench-venv"
        # scan3d decode: a batch of five manifests of this capture, one process (the median of four after the first)
        calib = folder / "calibration.yaml"
        write_calibration(calib, Calibration({"cam0": rig.cameras["cam0"], "cam1": rig.cameras["cam1"]}))
        manifests = [write_manifest(folder / f"capture{k}.yaml", seq, ["cam0", "cam1"],
                                    stacks={"cam0": "cam0.npy", "cam1": "cam1.npy"}) for k in range(BATCH)]  # fmt: skip
        cmd = [sys.executable, "-m", "appliance", "decode", *map(str, manifests), "--calibration", str(calib),
               "--out", str(folder / "clouds"), "--timings"]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=False, cwd=REPO)
        lines = [json.loads(x) for x in out.stdout.splitlines() if x.startswith("{")]
        per = [x for x in lines if "capture" in x]
        if out.returncode == 0 and len(per) == BATCH:
            res["batch_ms"] = [round(x["total_ms"], 1) for x in per]
            res["batch_decode_triangulate_ms"] = [round(x["decode_ms"] + x["triangulate_ms"], 1) for x in per]
            later = statistics.median(res["batch_decode_triangulate_ms"][1:])
            res["batch_ratio_to_warm"] = later / t_all
        else:
            res["batch_skipped"] = (out.stderr.strip() or out.stdout.strip())[-300:]
        res.update(_bench_load_jpeg(folder, stacks, repeats))
    stacks.clear()  # the real-like capture's frames take their place in memory
    maps.clear()
    res.update(bench_reallike(repeats, res))
    return res


REAL_JPEG_QUALITY = 90
"""The real-like capture's frames go through JPEG at this quality (as the real capture's did)."""
REAL_BLUR_PX = (1.5, 1.6)
"""The real-like render's projector and camera blur (px): the half-size test's 0.75 and 0.8 px at full size."""


def _reallike_rig() -> Any:
    """The real capture of issue 27 on the virtual rig, at full size: two 1920x1280 cameras 1.4 m apart converging
    on a wall at 3.9 m and a 'statue' (sphere + box) at 2.75-3.35 m, a 1280x800 projector, 1.2 and 1.6 camera px
    per projector px, strong radial distortion (k3 8-9.5), blur that makes the finest stripes marginal (the
    geometry of tests/reconstruct/test_stereo_reallike.py at twice its size)."""
    from appliance.config.schema import (
        BoxObject,
        DeviceOptics,
        ImagingConfig,
        PlaneObject,
        SphereObject,
        VirtualRigConfig,
    )
    from appliance.sim.rig import VirtualRig

    fp = 1500.0
    cams = {
        "cam0": DeviceOptics(width=1920, height=1280, focal_px=1.15 * fp, dist=(-0.25, 0.6, 3e-4, -2e-4, 9.5),
                             position_mm=(-700.0, 0.0, 0.0), look_at_mm=(0.0, 0.0, 3200.0)),
        "cam1": DeviceOptics(width=1920, height=1280, focal_px=1.55 * fp, dist=(-0.2, 0.4, -2e-4, 1e-4, 8.0),
                             position_mm=(700.0, 30.0, 0.0), look_at_mm=(0.0, 0.0, 3200.0)),
    }  # fmt: skip
    proj = DeviceOptics(width=1280, height=800, focal_px=fp, dist=(0.02, 0.0, 0.0, 0.0, 0.0),
                        position_mm=(80.0, -250.0, 0.0), look_at_mm=(0.0, 0.0, 3200.0))  # fmt: skip
    scene = (
        PlaneObject(point_mm=(0.0, 0.0, 3900.0), normal=(0.05, 0.1, -1.0), texture=0.3),
        SphereObject(center_mm=(-100.0, -150.0, 3000.0), radius_mm=260.0, texture=0.2),
        BoxObject(center_mm=(150.0, 380.0, 3150.0), size_mm=(500.0, 450.0, 400.0), rotation_deg=(10.0, 30.0, 5.0)),
    )
    imaging = ImagingConfig(projector_blur_px=REAL_BLUR_PX[0], camera_blur_px=REAL_BLUR_PX[1])  # finest bits marginal
    return VirtualRig(VirtualRigConfig(projector=proj, cameras=cams, scene=scene, imaging=imaging))


def bench_reallike(repeats: int, synthetic: dict[str, Any]) -> dict[str, Any]:
    """The camera-camera line on the real-like render (issue 27): decode, match + triangulate (against the
    synthetic render's figure of the same run), OpenCV contrib's decode of the same frames, the two-core read
    floor, the both-seen share, and loading the capture's 88 JPEG frames (every core, then one thread)."""
    import cv2

    from appliance.config.schema import ReconstructionConfig
    from appliance.geometry.calibration_file import Calibration
    from appliance.patterns import BlackFrame, GrayFrame, Sequence, WhiteFrame
    from appliance.patterns.manifest import load_images
    from appliance.reconstruct.decode import decode, plan_decode
    from appliance.reconstruct.pipeline import Reconstructor
    from appliance.reconstruct.stereo import StereoTriangulator

    rig = _reallike_rig()
    frames: list[Any] = []
    for axis, bits in (("x", 11), ("y", 10)):  # OpenCV's layout: MSB first, each bit then its inverse
        for b in range(bits - 1, -1, -1):
            frames += [GrayFrame(axis, b, False), GrayFrame(axis, b, True)]
    frames += [WhiteFrame(), BlackFrame()]
    seq = Sequence(1280, 800, tuple(frames))
    res: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        paths: dict[str, list[Path]] = {}
        for n in ("cam0", "cam1"):
            paths[n] = []
            for i, img in enumerate(rig.render(seq, n)):
                paths[n].append(folder / f"{n}_{i:02d}.jpg")
                cv2.imwrite(str(paths[n][-1]), img, [cv2.IMWRITE_JPEG_QUALITY, REAL_JPEG_QUALITY])
        res["real_render_s"] = time.perf_counter() - t0
        runs = max(3, repeats // 3)
        res["real_load_frames"] = sum(map(len, paths.values()))
        res["real_load_jpeg_ms"] = _ms(lambda: [load_images(ps) for ps in paths.values()], runs)
        res["real_load_jpeg_1thread_ms"] = _ms(lambda: [load_images(ps, threads=1) for ps in paths.values()], runs)
        res["real_load_threads"] = len(os.sched_getaffinity(0))
        colour: dict[str, list[Path]] = {}  # the same frames saved by a colour camera (3 channels, 4:2:0 chroma)
        for n, ps in paths.items():
            colour[n] = [p.with_name("c" + p.name) for p in ps]
            for p, q in zip(ps, colour[n], strict=True):
                img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
                cv2.imwrite(str(q), cv2.merge([img, img, img]), [cv2.IMWRITE_JPEG_QUALITY, REAL_JPEG_QUALITY])
        res["real_load_colour_jpeg_ms"] = _ms(lambda: [load_images(ps) for ps in colour.values()], runs)
        stacks = {n: load_images(ps) for n, ps in paths.items()}  # the frames as the JPEG files give them
        plan = plan_decode(seq)
        tri = StereoTriangulator(rig.cameras["cam0"], rig.cameras["cam1"])

        def decode_both() -> dict[str, Any]:
            return {n: decode(s, plan) for n, s in stacks.items()}

        maps = decode_both()
        read_all = parallel_read_floor()
        res["real_floor_read_parallel_ms"] = _ms(lambda: [read_all(s) for s in stacks.values()], repeats)
        res["real_decode_ms"] = _ms(decode_both, repeats)
        res["real_triangulate_ms"] = _ms(lambda: tri.triangulate(maps["cam0"], maps["cam1"]), repeats)
        res["real_decode_triangulate_ms"] = _ms(lambda: tri.triangulate(*decode_both().values()), repeats)
        xyz = tri.triangulate(maps["cam0"], maps["cam1"])
        both = tri.report.both_seen
        res["real_both_seen"] = int(both)
        res["real_both_seen_share"] = tri.report.both_seen_points / both if both else float("nan")
        res["real_code"] = tri.report.code  # how the matcher saw the codes (quantised: code cells)
        res["real_rejected"] = dict(tri.report.as_dict().get("rejected", {}))  # type: ignore[call-overload]
        # the product's whole camera-camera path (the matcher, then the neighbour filter): its both-seen share
        rec = Reconstructor(Calibration({"cam0": rig.cameras["cam0"], "cam1": rig.cameras["cam1"]}), "xy",
                            ReconstructionConfig(mode="stereo", min_depth_mm=2000.0, max_depth_mm=5000.0), seq)
        seen = (rec.run(maps).stereo or {}).get("both_seen") or {}
        res["real_pipeline_both_seen_share"] = seen.get("share", float("nan"))  # type: ignore[union-attr]
        res["real_decoded"] = [int(m.mask.sum()) for m in maps.values()]
        points, median_mm, p99_mm = _error_stats(xyz, rig.ground_truth("cam0").xyz)
        res.update(real_points=points, real_median_error_mm=median_mm, real_p99_error_mm=p99_mm)
        if "triangulate_ms" in synthetic:
            res["real_triangulate_ratio"] = res["real_triangulate_ms"] / synthetic["triangulate_ms"]
        res["real_floor_ratio"] = res["real_decode_triangulate_ms"] / res["real_floor_read_parallel_ms"]
        py = REPO / ".bench-venv" / "bin" / "python"
        if py.exists():
            for n, st in stacks.items():
                np.save(folder / f"{n}.npy", st)
            out = subprocess.run([str(py), "-c", OPENCV_STACKS, str(folder / "cam0.npy"), str(folder / "cam1.npy"),
                                  str(max(3, repeats // 3))], capture_output=True, text=True, timeout=1800,
                                 check=False)  # fmt: skip
            if out.returncode == 0:
                got = json.loads(out.stdout.strip().splitlines()[-1])
                res["real_opencv_decode_ms"] = got["opencv_decode_ms"]
                res["real_speedup"] = got["opencv_decode_ms"] / res["real_decode_triangulate_ms"]
            else:
                res["real_opencv_skipped"] = out.stderr.strip()[-300:]
        else:
            res["real_opencv_skipped"] = "no .bench-venv"
    return res


def _bench_load_jpeg(folder: Path, stacks: dict[str, np.ndarray], repeats: int) -> dict[str, Any]:
    """Reading the capture's frames as a manifest's JPEG files (quality 95): one thread, then every core."""
    import cv2

    from appliance.patterns.manifest import load_images

    paths: dict[str, list[Path]] = {}
    for n, s in stacks.items():
        paths[n] = [folder / f"{n}_{i:02d}.jpg" for i in range(len(s))]
        for p, img in zip(paths[n], s, strict=True):
            cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    runs = max(3, repeats // 3)
    one = _ms(lambda: [load_images(ps, threads=1) for ps in paths.values()], runs)
    many = _ms(lambda: [load_images(ps) for ps in paths.values()], runs)
    return {"load_frames": sum(map(len, paths.values())), "load_jpeg_1thread_ms": one, "load_jpeg_ms": many,
            "load_threads": len(os.sched_getaffinity(0))}  # fmt: skip


def report_lines(res: dict[str, Any]) -> list[str]:
    """README lines of :func:`bench_stereo`."""
    if not res:
        return []
    lines = [
        "**Camera-camera** (2 cameras × 1920×1280, Gray code in OpenCV's layout: columns + rows with inverses "
        "+ white + black = 44 frames per camera, projector 1280×800, rendered by the virtual rig at ~1 m): "
        f"decode both {res['decode_ms']:.0f} ms, match + triangulate {res['triangulate_ms']:.0f} ms, together "
        f"**{res['decode_triangulate_ms']:.0f} ms** median warm; {res['points']} points of {res['candidates']} "
        f"decoded pixels, median error {res['median_error_mm']:.3f} mm against the rig's truth.",
    ]
    if "decode_triangulate_1thread_ms" in res:
        lines.append(
            f"On one core (numba threads 1 instead of {res['threads']}): "
            f"{res['decode_triangulate_1thread_ms']:.0f} ms, "
            f"{res['decode_triangulate_1thread_ms'] / res['decode_triangulate_ms']:.2f}× the figure above."
        )
    if "floor_read_ms" in res:
        lines.append(
            f"Memory floor on this machine: one pass reading the two stacks with both cores (numba) "
            f"{res.get('floor_read_parallel_ms', float('nan')):.0f} ms (single-threaded numpy `np.add.reduce`: "
            f"{res['floor_read_ms']:.0f} ms), one writing the organised cloud (`fill`) {res['floor_write_ms']:.0f} ms; "
            f"ratio decode + triangulate : two-core read floor "
            f"**{res['decode_triangulate_ms'] / res['floor_read_parallel_ms']:.1f}×**."
        )
    if "opencv_decode_ms" in res:
        lines.append(
            f"OpenCV contrib {res['opencv_version']} `GrayCodePattern.decode` on the same two stacks: "
            f"{res['opencv_decode_ms']:.0f} ms → ours (decode + triangulate) **{res['speedup']:.0f}× faster**."
        )
    elif "opencv_skipped" in res:
        lines.append(f"OpenCV comparison skipped: {res['opencv_skipped']}")
    if "coarse_decode_triangulate_ms" in res:
        against = (
            f" ({res['opencv_decode_ms'] / res['coarse_decode_triangulate_ms']:.0f}× OpenCV)"
            if "opencv_decode_ms" in res else ""
        )
        lines.append(
            f"The same with code cells of at least {res['coarse_cell_px']:.0f} camera px instead of the default "
            f"(the per-cell work nearly gone, the per-pixel work left): {res['coarse_decode_triangulate_ms']:.0f} ms"
            f"{against}, median / p99 error {res['coarse_median_error_mm']:.3f} / {res['coarse_p99_error_mm']:.2f} "
            f"mm against {res['median_error_mm']:.3f} / {res['p99_error_mm']:.2f} mm with the default cells."
        )
    if "batch_ms" in res:
        lines.append(
            f"`scan3d decode` of a batch of {len(res['batch_ms'])} such captures: decode + triangulate "
            f"{res['batch_decode_triangulate_ms']} "
            f"ms per capture (the command's `decode_ms` + `triangulate_ms`; total {res['batch_ms']} ms, with "
            "loading, the filters, the point cloud and the PLY); after the first, "
            f"**{res['batch_ratio_to_warm']:.2f}×** the warm figure."
        )
    if "load_jpeg_ms" in res:
        lines.append(
            f"Reading the {res['load_frames']} frames of one such capture from JPEG files (a manifest's `images`): "
            f"**{res['load_jpeg_ms']:.0f} ms** on {res['load_threads']} threads, "
            f"{res['load_jpeg_1thread_ms']:.0f} ms on one."
        )
    if "real_decode_ms" in res:
        vs_opencv = (
            f"; OpenCV contrib's `GrayCodePattern.decode` on the same frames {res['real_opencv_decode_ms']:.0f} ms "
            f"→ ours **{res['real_speedup']:.0f}× faster**" if "real_speedup" in res
            else f"; OpenCV skipped: {res.get('real_opencv_skipped', '')}"
        )
        vs_synthetic = (
            f" (**{res['real_triangulate_ratio']:.2f}×** the synthetic render's {res['triangulate_ms']:.0f} ms above)"
            if "real_triangulate_ratio" in res else ""
        )
        lines.append(
            "**Camera-camera, real-like render** (issue 27's real capture on the virtual rig: the same 1920×1280 "
            "cameras and 1280×800 projector, stripe 1 on both axes with inverses, 44 frames per camera through "
            f"JPEG quality {REAL_JPEG_QUALITY}, cameras 1.4 m apart converging on a wall and a statue at 2.75-3.9 m, "
            "1.2 and 1.6 camera px per projector px, k3 8-9.5, blur that makes the finest bits marginal): "
            f"decode both {res['real_decode_ms']:.0f} ms, match + triangulate {res['real_triangulate_ms']:.0f} ms"
            f"{vs_synthetic}, together **{res['real_decode_triangulate_ms']:.0f} ms**{vs_opencv}; "
            f"**{res['real_floor_ratio']:.1f}×** the two-core read floor of these stacks "
            f"({res['real_floor_read_parallel_ms']:.0f} ms). The matcher saw the codes as {res['real_code']}; "
            f"{res['real_points']} points, {100 * res['real_both_seen_share']:.1f} % of the {res['real_both_seen']} "
            f"pixels both cameras see ({100 * res['real_pipeline_both_seen_share']:.1f} % after the neighbour "
            f"filter of `scan3d decode`), median / p99 error {res['real_median_error_mm']:.3f} / "
            f"{res['real_p99_error_mm']:.2f} mm against the rig's truth."
        )
        lines.append(
            f"Loading that capture's {res['real_load_frames']} JPEG frames (a manifest's `images`, as `scan3d decode` "
            f"reads them): **{res['real_load_jpeg_ms']:.0f} ms** on {res['real_load_threads']} threads, "
            f"{res['real_load_jpeg_1thread_ms']:.0f} ms on one; saved as colour JPEGs, "
            f"{res['real_load_colour_jpeg_ms']:.0f} ms on {res['real_load_threads']} threads (decoded straight to "
            "grey: the chroma planes are not decoded)."
        )
    lines.append("")
    return lines
