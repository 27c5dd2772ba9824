"""Scan orchestration on the virtual rig: streaming equals batch, failures fail one scan only, CLI commands."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from appliance.config import AppConfig, parse_config
from appliance.config.backends import SimCameraConfig
from appliance.errors import ScanError
from appliance.hardware.registry import build_rig
from appliance.reconstruct.decode import decode
from appliance.scan import FrameMemory, Scanner, load_calibration_for, scan_once

REPO = Path(__file__).resolve().parents[2]

SMALL = """
cameras: {cam0: {type: sim}}
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
reconstruction: {min_depth_mm: 300, max_depth_mm: 900}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 380], position_mm: [175, 0, 0],
              look_at_mm: [0, 40, 580]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 450, position_mm: [0, 0, 0], look_at_mm: [0, 0, 580]}
"""


def small_config() -> AppConfig:
    return parse_config(SMALL, "small.yaml")


def test_streaming_scan_equals_batch_decode() -> None:
    cfg = small_config()

    result, scanner = asyncio.run(scan_once(cfg))
    batch = decode(result.frames["cam0"], scanner.sequence, scanner.params)
    stream = result.maps["cam0"]
    np.testing.assert_array_equal(batch.mask, stream.mask)
    assert np.array_equal(batch.u, stream.u, equal_nan=True)
    assert np.array_equal(batch.quality, stream.quality, equal_nan=True)
    assert len(result.cloud) > 0.5 * result.maps["cam0"].mask.sum()


def _rss_anon_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1])
    raise AssertionError("no RssAnon in /proc/self/status")


def test_released_frames_read_zero_and_give_their_memory_back() -> None:
    mem = FrameMemory((8, 1000, 1000), np.dtype(np.uint8))  # frames of 1e6 bytes: not page multiples
    frames = mem.frames
    assert frames.shape == (8, 1000, 1000) and frames.dtype == np.uint8 and frames.flags.writeable
    before = _rss_anon_kb()
    frames[...] = np.arange(8, dtype=np.uint8)[:, None, None] + 1
    written = _rss_anon_kb()
    assert written - before > 7000  # 8 MB touched
    for i in range(0, 8, 2):
        mem.release(i)
    released = _rss_anon_kb()
    assert written - released > 3500  # four frames' whole pages are back (at most 2 pages each stay)
    for i in range(8):
        inner = frames[i, 5:-5]  # away from the partial pages shared with the neighbours
        assert (inner == (0 if i % 2 == 0 else i + 1)).all(), i
    frames[2] = 200  # a released frame is written again like any other
    assert (frames[2] == 200).all() and (frames[3] == 4).all()


def test_the_service_scanner_keeps_no_frames_and_scans_the_same() -> None:
    cfg = small_config()

    async def run(keep: bool) -> tuple[object, list[int]]:
        rig = build_rig(cfg)
        scanner = Scanner(cfg, rig, load_calibration_for(cfg, rig), keep_frames=keep)
        try:
            await scanner.warm_up()
            result = await scanner.scan()
            buf = scanner._buffers["cam0"]
            lit = [int(i) for i in np.flatnonzero(buf.reshape(buf.shape[0], -1).max(axis=1) > 0)]
            return result, lit
        finally:
            await scanner.close()

    kept, lit_kept = asyncio.run(run(True))
    lean, lit_lean = asyncio.run(run(False))
    assert len(lit_kept) == len(kept.frames["cam0"])  # type: ignore[attr-defined]
    assert lean.frames == {}  # type: ignore[attr-defined]
    white = next(i for i, f in enumerate(small_scanner_frames(cfg)) if type(f).__name__ == "WhiteFrame")
    assert lit_lean == [white]  # every frame but the white one (the points' intensity) was given back
    a, b = kept.cloud, lean.cloud  # type: ignore[attr-defined]
    assert len(a) == len(b) > 1000
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.intensity, b.intensity)


def small_scanner_frames(cfg: AppConfig) -> tuple[object, ...]:
    from appliance.scan import build_sequence

    proj = cfg.virtual_rig.projector
    return tuple(build_sequence(cfg.sequence, proj.width, proj.height).frames)


def test_dead_camera_fails_one_scan_and_the_next_succeeds(monkeypatch: pytest.MonkeyPatch) -> None:
    import appliance.scan as scan_mod

    cfg = small_config()
    monkeypatch.setattr(scan_mod, "FRAME_TIMEOUT_S", 0.5)
    monkeypatch.setattr(scan_mod, "FRAME_TIMEOUT_PER_FRAME_S", 0.05)

    async def run() -> None:
        rig = build_rig(cfg)
        scanner = Scanner(cfg, rig, load_calibration_for(cfg, rig))
        cam = rig.cameras["cam0"]
        try:
            cam.cfg = SimCameraConfig(fail_after_frames=5)  # type: ignore[attr-defined]
            with pytest.raises(ScanError, match=r"camera 'cam0' \(sim\): only 5 of \d+ frames.*frame 5"):
                await scanner.scan()
            cam.cfg = SimCameraConfig()  # type: ignore[attr-defined]  # the cable is back
            result = await scanner.scan()
            assert len(result.cloud) > 1000
        finally:
            await scanner.close()

    asyncio.run(run())


def test_scan_command_writes_cloud_sidecar_preview(tmp_path: Path) -> None:
    cfg_path = tmp_path / "small.yaml"
    cfg_path.write_text(SMALL)
    out = subprocess.run(
        [sys.executable, "-m", "appliance", "scan", "--config", str(cfg_path), "--out", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "error against ground truth" in out.stdout
    plys = list((tmp_path / "o").glob("*/*.ply"))
    assert len(plys) == 1
    ply = PlyData.read(str(plys[0]))
    assert ply["vertex"].count > 1000
    meta = json.loads(plys[0].with_suffix(".json").read_text())
    assert meta["counts"]["points"] == ply["vertex"].count
    assert meta["calibration_hash"] and "decode_finish_ms" in meta["timings_ms"]
    assert plys[0].with_suffix(".png").stat().st_size > 1000


def test_decode_command_on_a_recorded_capture(tmp_path: Path) -> None:
    """Record a virtual-rig scan as a manifest + calibration, decode it offline with the CLI."""
    from appliance.geometry.calibration_file import write_calibration
    from appliance.patterns import write_manifest
    from appliance.scan import virtual_calibration

    cfg = small_config()
    rig = build_rig(cfg)
    from appliance.patterns.from_config import build_sequence

    seq = build_sequence(cfg.sequence, rig.virtual.projector.width, rig.virtual.projector.height)
    np.save(tmp_path / "cam0.npy", rig.virtual.render(seq, "cam0"))
    man = write_manifest(tmp_path / "scan.yaml", seq, ["cam0"], stacks={"cam0": "cam0.npy"})
    write_calibration(tmp_path / "calib.yaml", virtual_calibration(rig.virtual))
    out = subprocess.run(
        [sys.executable, "-m", "appliance", "decode", str(man), "--calibration", str(tmp_path / "calib.yaml"),
         "--out", str(tmp_path / "c.ply"), "--maps", str(tmp_path / "m.npz"), "--timings"],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert out.returncode == 0, out.stderr
    lines = [json.loads(x) for x in out.stdout.strip().splitlines() if x.startswith("{")]
    timings, summary = lines[0], lines[-1]
    assert set(timings) == {"capture", "load_ms", "setup_ms", "decode_ms", "triangulate_ms", "filter_ms", "cloud_ms",
                            "write_ms", "total_ms"}  # fmt: skip
    assert summary["summary"] and summary["captures"] == 1
    maps = np.load(tmp_path / "m.npz")
    assert set(maps.files) == {"cam0_u", "cam0_v", "cam0_mask", "cam0_quality", "cam0_levels", "cam0_reason",
                               "cam0_fringe"}  # fmt: skip
    fringe, mask = maps["cam0_fringe"], maps["cam0_mask"]
    assert fringe.dtype == np.uint8 and not fringe[~mask].any()
    assert 70 <= np.median(fringe[mask]) <= 100  # a plain scene: nearly all its light carries the pattern
    v = PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    gt = rig.virtual.ground_truth("cam0")
    truth = gt.xyz[v["row"], v["col"]]
    err = np.linalg.norm(np.stack([v["x"], v["y"], v["z"]], 1) - truth, axis=1)
    assert np.median(err) < 0.3  # a small, coarse rig: sub-millimetre still


def test_decode_refuses_a_missing_gray_bit(tmp_path: Path) -> None:
    from appliance.patterns import Sequence, gray_phase_sequence, write_manifest
    from appliance.patterns.sequence import GrayFrame

    seq = gray_phase_sequence(640, 400, "x", period=16)
    frames = tuple(f for f in seq.frames if not (isinstance(f, GrayFrame) and f.bit == 3))
    seq2 = Sequence(640, 400, frames)
    np.save(tmp_path / "c.npy", np.zeros((len(frames), 8, 8), np.uint8))
    man = write_manifest(tmp_path / "m.yaml", seq2, ["c"], stacks={"c": "c.npy"})
    out = subprocess.run([sys.executable, "-m", "appliance", "decode", str(man), "--maps", str(tmp_path / "m.npz")],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 2
    assert "bit 3" in out.stderr


SMALL_TWO = SMALL.replace("cameras: {cam0: {type: sim}}", "cameras: {cam0: {type: sim}, cam1: {type: sim}}").replace(
    "reconstruction: {", "reconstruction: {mode: both, "
) + "    cam1: {width: 320, height: 256, focal_px: 450, position_mm: [-175, 0, 0], look_at_mm: [0, 0, 580]}\n"


def _kernel_variants() -> dict[str, int]:
    """Compiled (or cache-loaded) variants of every numba kernel of the package imported so far."""
    from numba.core.registry import CPUDispatcher

    return {f"{name}.{attr}": len(obj.signatures) for name, mod in list(sys.modules.items())
            if name.startswith("appliance") for attr, obj in list(vars(mod).items())
            if isinstance(obj, CPUDispatcher)}  # fmt: skip


def test_scans_after_the_warm_up_need_no_other_kernel_variant() -> None:
    """The warm-up runs every kernel a scan runs, with the same argument types: a variant first met in a
    scan is compiled there (a minute, and hundreds of MB, on a fresh cache) or loaded there (the service's
    memory peak). Two cameras fused, three scans of the same rig."""
    cfg = parse_config(SMALL_TWO, "small-two.yaml")
    rig = build_rig(cfg)
    scanner = Scanner(cfg, rig, load_calibration_for(cfg, rig), keep_frames=False)  # off the loop: tables

    async def run() -> tuple[dict[str, int], list[dict[str, int]], list[int]]:
        try:
            await scanner.warm_up()
            warm = _kernel_variants()
            after, points = [], []
            for _ in range(3):
                result = await scanner.scan()
                points.append(len(result.cloud))
                after.append(_kernel_variants())
            return warm, after, points
        finally:
            await scanner.close()

    warm, after, points = asyncio.run(run())
    assert min(points) > 1000, points  # the scans reconstruct
    for i, now in enumerate(after):
        new = {k: (warm.get(k, 0), n) for k, n in now.items() if n != warm.get(k, 0)}
        assert not new, f"scan {i + 1} needed kernel variants the warm-up did not make: {new}"
    # issue 26: an entry point that takes more than a dozen scalars takes a typed parameter object instead
    many = {k: n for k, n in _scalar_arguments().items() if n > 12 and not k.rsplit(".", 1)[1].startswith("_")}
    assert not many, f"kernel entry points a scan called with more than 12 scalar arguments: {many}"


def _scalar_arguments() -> dict[str, int]:
    """The most non-array arguments of any compiled variant of every numba kernel of the package."""
    from numba.core import types
    from numba.core.registry import CPUDispatcher

    return {f"{name}.{attr}": max(sum(not isinstance(a, types.Array) for a in sig) for sig in obj.signatures)
            for name, mod in list(sys.modules.items()) if name.startswith("appliance")
            for attr, obj in list(vars(mod).items()) if isinstance(obj, CPUDispatcher) and obj.signatures}  # fmt: skip


def test_stereo_tables_stay_contiguous_when_a_scan_needs_fewer_levels() -> None:
    """A scan with fewer code levels than an earlier one gets its crossing tables as C-contiguous arrays
    (a column slice of the kept one would be strided: another kernel variant, met mid-scan)."""
    from appliance.reconstruct.stereo import StereoTriangulator

    cfg = parse_config(SMALL_TWO, "small-two.yaml")
    rig = build_rig(cfg)
    cal = load_calibration_for(cfg, rig)
    tri = StereoTriangulator(cal.devices["cam0"], cal.devices["cam1"])
    wide = tri._table("c0", 700)
    narrow = tri._table("c0", 650)
    assert wide.shape == (tri.rect_shape[0], 700) and narrow.shape == (tri.rect_shape[0], 650)
    assert wide.flags.c_contiguous and narrow.flags.c_contiguous
    assert np.shares_memory(wide, narrow)  # the kept buffer, not a new one
