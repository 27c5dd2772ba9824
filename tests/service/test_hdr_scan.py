"""HDR scans: ``sequence.exposures_us`` in the configuration makes every scan capture one pass per exposure.

The virtual rig's scene has a bright plane (albedo 0.95: it clips at 10 ms) and a black box (albedo 0.03: too
dark at 2.5 ms). One exposure gives one or the other; three (2.5, 10, 40 ms), fused per pixel as the frames
stream in, give both; so does a short pass taken by dimming the projector (``sequence.intensities``). Checked
where a person meets it: ``scan3d scan`` with a configuration file (accuracy against the rig's ground truth,
the sidecar's record of the passes), the service (a triggered scan's sidecar and cloud, by exposures and by
a dimmed pass), the same frames decoded offline by ``scan3d decode`` (the same cloud, bit for bit), and a camera
that cannot set its exposure (one line).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
from pathlib import Path
from typing import Any

import e2e_helpers as e2e
import numpy as np
import pytest
import yaml

from appliance import cli
from appliance.config import parse_config
from appliance.geometry.calibration_file import write_calibration
from appliance.hardware import sim
from appliance.hardware.registry import build_rig
from appliance.output.ply import read_ply_vertices
from appliance.patterns.manifest import write_manifest
from appliance.reconstruct.types import PointCloud
from appliance.scan import Scanner, load_calibration_for, scan_once, virtual_calibration
from appliance.service import daemon as D
from appliance.sim.accuracy import compare_to_ground_truth
from appliance.sim.rig import VirtualRig

HDR_US = [2500, 10_000, 40_000]

VIRTUAL_RIG: dict[str, Any] = {
    "projector": {"width": 640, "height": 400, "focal_px": 850, "position_mm": [180, 0, 0],
                  "look_at_mm": [0, 0, 600]},
    "cameras": {"cam0": {"width": 320, "height": 256, "focal_px": 575, "position_mm": [0, 0, 0],
                         "look_at_mm": [0, 0, 600]}},
    "scene": [
        {"type": "plane", "point_mm": [0, 0, 640], "normal": [0, 0.1, -1], "albedo": 0.95},
        {"type": "box", "center_mm": [0, 0, 590], "size_mm": [120, 90, 40], "rotation_deg": [5, 15, 0],
         "albedo": 0.03},
    ],
    "imaging": {"projector_gain_dn": 420, "ambient_dn": 6},
}  # fmt: skip


#: the short pass taken by dimming the projector to a quarter (a LightCrafter's LED currents) at the middle exposure
DIMMED = {"exposures_us": [10_000, 10_000, 40_000], "intensities": [0.25, 1.0, 1.0]}


def _config(tmp: Path, name: str, exposures: list[int], intensities: list[float] | None = None) -> Path:
    doc = {
        "cameras": {"cam0": {"type": "sim"}},
        "sequence": {"kind": "gray_phase", "axes": "x", "periods_px": [16], "exposures_us": exposures,
                     **({"intensities": intensities} if intensities else {})},
        "reconstruction": {"min_depth_mm": 300, "max_depth_mm": 900},
        "virtual_rig": VIRTUAL_RIG,
        "service": {"state_directory": str(tmp / f"state-{name}")},
    }
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _cli(*args: object) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main([str(a) for a in args])
    return rc, out.getvalue()


def _sidecar(folder: Path) -> dict[str, Any]:
    (path,) = folder.rglob("*.json")
    return json.loads(path.read_text())  # type: ignore[no-any-return]


def _cloud(ply: Path) -> PointCloud:
    v = read_ply_vertices(ply)
    n = len(v)
    return PointCloud(np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32), v["row"].astype(np.int32),
                      v["col"].astype(np.int32), np.zeros(n, np.uint8), np.zeros(n, np.uint8),
                      np.zeros(n, np.float32))  # fmt: skip


def test_scan_command_with_three_exposures_reconstructs_the_dark_and_the_bright(tmp_path: Path) -> None:
    truth: dict[str, dict[str, Any]] = {}
    sidecars: dict[str, dict[str, Any]] = {}
    for name, exposures, levels in (("short", [2500], None), ("long", [40_000], None), ("hdr", HDR_US, None),
                                    ("dimmed", DIMMED["exposures_us"], DIMMED["intensities"])):
        rc, text = _cli("scan", "--config", _config(tmp_path, name, exposures, levels), "--out", tmp_path / name)
        assert rc == 0, text
        sidecars[name] = _sidecar(tmp_path / name)
        truth[name] = sidecars[name]["extra"]["ground_truth"]
        print(name, {k: truth[name][k] for k in ("points", "rms_mm", "share_over_1mm", "completeness")})
    short, long_, hdr = truth["short"], truth["long"], truth["hdr"]
    # the short pass gets the plane (the box too dark), the long one the box (the plane clipped); HDR both
    assert hdr["completeness"] >= 0.95
    assert hdr["completeness"] >= max(short["completeness"], long_["completeness"]) + 0.08
    # accuracy against the truth: as good as the short pass on the plane, the box's points (albedo 0.03) a
    # little noisier (measured: RMS 0.333 mm against 0.303 mm, 0.72 % beyond 1 mm)
    assert hdr["rms_mm"] <= 1.3 * short["rms_mm"]
    assert hdr["share_over_1mm"] <= 0.015
    # the sidecar says how it was captured: the exposures, and what each pass gave
    block = sidecars["hdr"]["extra"]["hdr"]
    assert block["exposures_us"] == [float(e) for e in HDR_US]
    assert block["frames"] == 3 * block["frames_per_pass"] == 3 * sidecars["hdr"]["sequence"]["frames"]
    passes = block["cameras"]["cam0"]["passes"]
    assert [p["exposure_us"] for p in passes] == [2500.0, 10_000.0, 40_000.0]  # darkest first
    decoded = sidecars["hdr"]["counts"]["cameras"]["cam0"]["decoded_pixels"]
    assert sum(p["decoded_pixels"] for p in passes) == decoded
    assert sum(p["pixel_share"] for p in passes) == pytest.approx(1.0, abs=1e-5)
    assert passes[0]["decoded_share"] > 0.6 and passes[2]["decoded_share"] > 0.08  # the plane, the box
    assert "hdr" not in sidecars["short"]["extra"] or len(sidecars["short"]["extra"]["hdr"]["exposures_us"]) == 1
    # the short pass by a dimmed projector instead (sequence.intensities): the same dark and bright parts
    dimmed = truth["dimmed"]
    assert dimmed["completeness"] >= 0.95 and dimmed["share_over_1mm"] <= 0.015
    assert dimmed["rms_mm"] <= 1.3 * short["rms_mm"]
    block = sidecars["dimmed"]["extra"]["hdr"]
    assert block["exposures_us"] == DIMMED["exposures_us"] and block["intensities"] == DIMMED["intensities"]
    passes = block["cameras"]["cam0"]["passes"]
    assert [(p["exposure_us"], p["intensity"]) for p in passes] == [(10_000, 0.25), (10_000, 1.0), (40_000, 1.0)]
    assert passes[0]["decoded_share"] > 0.6  # the plane, from the dimmed pass


@pytest.mark.parametrize("passes", ["exposures", "intensities"])
def test_service_scan_is_hdr_when_the_configuration_says_so(tmp_path: Path, passes: str) -> None:
    """A triggered scan of the service captures every pass: by exposures (2.5, 10, 40 ms), or with the short
    pass taken by dimming the projector (10 ms at 0.25, 10 ms, 40 ms), and the projector is set back to full
    intensity after it."""
    sequence: dict[str, Any] = {"kind": "gray_phase", "axes": "x", "periods_px": [16]}
    if passes == "exposures":
        sequence["exposures_us"] = HDR_US
    else:
        sequence.update(DIMMED)
    cfg = e2e.write_config(tmp_path, virtual_rig=VIRTUAL_RIG, sequence=sequence)
    scans: list[dict[str, Any]] = []
    exposures: list[float | None] = []
    intensities: list[float | None] = []

    async def body(svc: D.Service) -> None:
        assert svc.scanner is not None and svc.scanner.n_passes == 3
        scans.append(await e2e.scan_once(svc))
        assert svc.rig is not None
        exposures.extend(getattr(c, "exposure_us", None) for c in svc.rig.cameras.values())
        projector = svc.rig.projector
        assert isinstance(projector, sim.SimProjector)
        intensities.append(projector.world.intensity)

    rc, _svc = e2e.run_in_process(cfg, body)
    assert rc == 0 and scans[0]["ok"], scans
    assert exposures == [40_000.0]  # the camera was left at the last pass's exposure
    files = [Path(f) for f in scans[0]["files"]]
    side = json.loads(next(f for f in files if f.suffix == ".json").read_text())
    block = side["extra"]["hdr"]
    if passes == "exposures":
        assert block["exposures_us"] == [float(e) for e in HDR_US] and "intensities" not in block
        assert intensities == [None]  # never dimmed: never sent an intensity
    else:
        assert block["exposures_us"] == DIMMED["exposures_us"] and block["intensities"] == DIMMED["intensities"]
        pass_list = block["cameras"]["cam0"]["passes"]
        assert [(p["exposure_us"], p["intensity"]) for p in pass_list] == [(10_000, 0.25), (10_000, 1.0),
                                                                           (40_000, 1.0)]  # fmt: skip
        assert pass_list[0]["decoded_share"] > 0.6  # the bright plane, from the dimmed pass
        assert intensities == [1.0]  # set back to full after the scan
    rig = VirtualRig(parse_config(cfg.read_text(), str(cfg)).virtual_rig)
    report = compare_to_ground_truth(_cloud(next(f for f in files if f.suffix == ".ply")), rig, ["cam0"])
    print(passes, report.line())
    assert report.completeness >= 0.95 and report.share_over_1mm <= 0.015


@pytest.mark.parametrize("passes", ["exposures", "intensities"])
def test_hdr_scan_equals_the_offline_decode_of_its_recording(tmp_path: Path, passes: str) -> None:
    if passes == "exposures":
        cfg = parse_config(_config(tmp_path, "hdr", HDR_US).read_text(), "hdr.yaml")
    else:  # the recording's frames say exposure_us and intensity: the offline decode groups the same passes
        dimmed = _config(tmp_path, "hdr", DIMMED["exposures_us"], DIMMED["intensities"])
        cfg = parse_config(dimmed.read_text(), "hdr.yaml")
    result, scanner = asyncio.run(scan_once(cfg))
    if passes == "intensities":  # the projector dimmed for the first pass: a quarter of the light in its white frame
        assert scanner.exposures is not None and scanner.exposures[0] == (10_000.0, 0.25)
        n = len(scanner.sequence)
        white = next(i for i, f in enumerate(scanner.sequence.frames) if type(f).__name__ == "WhiteFrame")
        black = next(i for i, f in enumerate(scanner.sequence.frames) if type(f).__name__ == "BlackFrame")
        frames = result.frames["cam0"].astype(np.float64)
        lit = [frames[k * n + white] - frames[k * n + black] for k in (0, 1)]  # the projector's light alone
        sel = (lit[1] > 20) & (lit[1] < 200)  # unclipped in the full pass
        ratio = float(np.median(lit[0][sel] / lit[1][sel]))
        print(f"dimmed / full projector light: {ratio:.3f}")
        assert 0.22 <= ratio <= 0.28
        assert isinstance(scanner.rig.projector, sim.SimProjector)
        assert scanner.rig.projector.world.intensity == 1.0  # set back to full after the scan
    assert scanner.exposures is not None and len(scanner.capture) == 3 * len(scanner.sequence)
    stack = result.frames["cam0"]
    np.save(tmp_path / "cam0.npy", stack)
    write_manifest(tmp_path / "capture.yaml", scanner.capture, ["cam0"], stacks={"cam0": "cam0.npy"},
                   exposures=scanner.exposures)  # fmt: skip
    write_calibration(tmp_path / "cal.yaml", virtual_calibration(scanner.rig.virtual))
    rc, text = _cli("decode", tmp_path / "capture.yaml", "--calibration", tmp_path / "cal.yaml",
                    "--config", tmp_path / "hdr.yaml", "--out", tmp_path / "offline.ply",
                    "--report", tmp_path / "offline.json")  # fmt: skip
    assert rc == 0, text
    assert "3 exposure passes fused" in text
    offline = read_ply_vertices(tmp_path / "offline.ply")
    cloud = result.cloud
    assert len(cloud) > 50_000 and len(offline) == len(cloud)
    np.testing.assert_array_equal(np.stack([offline["x"], offline["y"], offline["z"]], 1), cloud.xyz)
    np.testing.assert_array_equal(offline["row"], cloud.row)
    np.testing.assert_array_equal(offline["col"], cloud.col)
    report = json.loads((tmp_path / "offline.json").read_text())
    assert report["extra"]["hdr"] == json.loads(json.dumps(result.capture))  # the same passes, the same shares


def test_the_service_scanner_gives_back_every_frame_but_the_white_ones(tmp_path: Path) -> None:
    cfg = parse_config(_config(tmp_path, "hdr", HDR_US).read_text(), "hdr.yaml")

    async def go() -> tuple[np.ndarray, list[int]]:
        def make() -> Scanner:
            rig = build_rig(cfg)
            return Scanner(cfg, rig, load_calibration_for(cfg, rig), keep_frames=False)  # as the service has it

        scanner = await asyncio.to_thread(make)
        try:
            result = await scanner.scan()
            assert result.frames == {} and len(result.cloud) > 50_000
            frames = scanner._releasable["cam0"].frames  # the scan's buffer: given-back frames read as zeros
            n = len(scanner.sequence)
            whites = [k * n + i for k in range(3) for i, f in enumerate(scanner.sequence.frames)
                      if type(f).__name__ == "WhiteFrame"]  # fmt: skip
            # (a frame's partial pages at its ends stay mapped: its middle rows are what was given back)
            held = [i for i in range(frames.shape[0]) if frames[i, 16:-16].any()]
            return np.asarray(held), whites
        finally:
            await scanner.close()

    held, whites = asyncio.run(go())
    assert len(whites) == 3 and held.tolist() == whites  # one white frame per pass, for the grey image


@pytest.mark.parametrize(
    ("device", "control", "said"),
    [
        (sim.SimCamera, "set_exposure", ["camera 'cam0' (sim): cannot set its exposure",
                                         "sequence.exposures_us = [2500, 10000, 40000]",
                                         "remove sequence.exposures_us"]),
        # as the hdmi backend: it shows what it is given
        (sim.SimProjector, "set_intensity", ["projector (sim): cannot set its intensity between passes",
                                             "sequence.intensities = [0.25, 1.0, 1.0]",
                                             "remove sequence.intensities"]),
    ],
)  # fmt: skip
def test_a_device_without_the_control_a_capture_needs_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, device: type, control: str, said: list[str]
) -> None:
    monkeypatch.delattr(device, control)
    if control == "set_exposure":
        config = _config(tmp_path, "hdr", HDR_US)
    else:
        config = _config(tmp_path, "dimmed", DIMMED["exposures_us"], DIMMED["intensities"])
    rc, text = _cli("scan", "--config", config, "--out", tmp_path / "o")
    assert rc == 2 and "Traceback" not in text
    lines = [line for line in text.splitlines() if line.startswith("scan3d scan:")]
    assert len(lines) == 1, text
    assert all(words in lines[0] for words in said), lines[0]
    assert not list((tmp_path / "o").rglob("*.ply"))
