"""``scan3d decode`` offline: no configuration needed, the mode from the calibration, batches, reports, and one
clear line for bad input.

Captures are recorded from the virtual rig (manifest + exact calibration), so clouds are checked against
its ground truth.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from plyfile import PlyData

from appliance import cli
from appliance.config import parse_config
from appliance.config.schema import ReconstructionConfig
from appliance.errors import ConfigError
from appliance.geometry.calibration_file import Calibration, read_calibration, write_calibration
from appliance.patterns.manifest import write_manifest
from appliance.reconstruct.defaults import default_depth_range_mm
from appliance.replay import choose_decode_mode
from appliance.scan import build_sequence, virtual_calibration
from appliance.sim.rig import VirtualRig

RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 380], position_mm: [175, 0, 0],
              look_at_mm: [0, 40, 580]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 450, position_mm: [0, 0, 0], look_at_mm: [0, 0, 580]}
    cam1: {width: 320, height: 256, focal_px: 450, position_mm: [-120, 0, 0], look_at_mm: [0, 0, 580]}
"""


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Two recorded captures (the same scene, different noise) of both cameras, and calibration files."""
    folder = tmp_path_factory.mktemp("capture")
    cfg = parse_config(RIG, "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    seq = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    manifests = []
    for k in range(2):
        for cam in ("cam0", "cam1"):
            np.save(folder / f"s{k}_{cam}.npy", rig.render(seq, cam, seed=10 + k))
        manifests.append(write_manifest(folder / f"scan{k}.yaml", seq, ["cam0", "cam1"],
                                        stacks={c: f"s{k}_{c}.npy" for c in ("cam0", "cam1")}))  # fmt: skip
    np.save(folder / "one.npy", rig.render(seq, "cam0", seed=3))
    one = write_manifest(folder / "one.yaml", seq, ["cam0"], stacks={"cam0": "one.npy"})
    full = virtual_calibration(rig)
    calibs = {
        "procam": Calibration({"cam0": full.devices["cam0"], "projector": full.devices["projector"]}),
        "stereo": Calibration({"cam0": full.devices["cam0"], "cam1": full.devices["cam1"]}),
        "both": full,
    }
    files = {}
    for name, c in calibs.items():
        files[name] = folder / f"{name}.yaml"
        write_calibration(files[name], c)
    return {"folder": folder, "rig": rig, "manifests": manifests, "one": one, "calib": files, "models": calibs}


def _decode(*args: Any) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["decode", *[str(a) for a in args]])
    return rc, out.getvalue(), err.getvalue()


def _errors_mm(rig: VirtualRig, ply: Path, cameras: tuple[str, ...] = ("cam0", "cam1")) -> np.ndarray[Any, Any]:
    """Distance of every point to the truth seen by its source pixel (mm)."""
    v = PlyData.read(str(ply))["vertex"]
    cam = np.asarray(v["camera"]) if "camera" in v.data.dtype.names else np.zeros(len(v), np.int64)
    truth = np.empty((len(v), 3))
    for i, name in enumerate(cameras):
        sel = cam == i
        truth[sel] = rig.ground_truth(name).xyz[v["row"][sel], v["col"][sel]]
    return np.linalg.norm(np.stack([v["x"], v["y"], v["z"]], 1) - truth, axis=1)  # type: ignore[no-any-return]


def test_mode_follows_the_calibration(capture: dict[str, Any]) -> None:
    m = capture["models"]
    assert choose_decode_mode(m["procam"], ["cam0"]) == "projector"
    assert choose_decode_mode(m["stereo"], ["cam0", "cam1"]) == "stereo"
    assert choose_decode_mode(m["both"], ["cam0", "cam1"]) == "both"
    assert choose_decode_mode(m["both"], ["cam0"]) == "projector"  # one camera of the manifest: no pair
    assert choose_decode_mode(m["both"], ["cam0", "cam1"], "stereo") == "stereo"
    with pytest.raises(ConfigError, match="no 'projector'; use --mode stereo"):
        choose_decode_mode(m["stereo"], ["cam0", "cam1"], "projector")
    with pytest.raises(ConfigError, match="needs two cameras"):
        choose_decode_mode(m["procam"], ["cam0"], "stereo")
    with pytest.raises(ConfigError, match="no projector: nothing to triangulate"):
        choose_decode_mode(Calibration({"cam0": m["procam"].devices["cam0"]}), ["cam0"])


def test_depth_range_from_the_geometry(capture: dict[str, Any]) -> None:
    rig: VirtualRig = capture["rig"]
    cam, proj = capture["models"]["both"].devices["cam0"], capture["models"]["both"].devices["projector"]
    near, far = default_depth_range_mm([cam], [proj])
    depth = rig.ground_truth("cam0").depth
    assert near < np.nanmin(depth) and far > np.nanmax(depth)
    assert 50 < near < 500 and 1000 < far < 20_000  # what a 175 mm baseline can triangulate


def test_camera_projector_without_config(capture: dict[str, Any], tmp_path: Path) -> None:
    rc, out, err = _decode(capture["one"], "--calibration", capture["calib"]["procam"], "--out", tmp_path / "c.ply",
                           "--report", tmp_path / "r.json")  # fmt: skip
    assert rc == 0, err
    assert "mode projector" in out
    err_mm = _errors_mm(capture["rig"], tmp_path / "c.ply")
    assert len(err_mm) > 20_000 and np.median(err_mm) < 0.3
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["counts"]["points"] == len(err_mm)
    assert report["counts"]["cameras"]["cam0"]["decoded_pixels"] > len(err_mm)
    assert report["extra"]["mode"] == "projector"
    assert report["calibration_hash"] == read_calibration(capture["calib"]["procam"]).hash()
    assert set(report["timings_ms"]) >= {"load_ms", "setup_ms", "decode_ms", "triangulate_ms", "write_ms"}
    near, far = report["extra"]["depth_range_mm"]
    assert near < 500 < 700 < far


def test_camera_camera_without_config(capture: dict[str, Any], tmp_path: Path) -> None:
    rc, out, err = _decode(capture["manifests"][0], "--calibration", capture["calib"]["stereo"], "--out", tmp_path)
    assert rc == 0, err
    assert "mode stereo" in out
    err_mm = _errors_mm(capture["rig"], tmp_path / "scan0.ply")
    assert len(err_mm) > 10_000 and np.median(err_mm) < 1.0


def test_both_and_its_override(capture: dict[str, Any], tmp_path: Path) -> None:
    rc, out, err = _decode(capture["manifests"][0], "--calibration", capture["calib"]["both"], "--out",
                           tmp_path / "b.ply", "--report", tmp_path / "b.json")  # fmt: skip
    assert rc == 0, err
    mode = json.loads((tmp_path / "b.json").read_text())["extra"]["mode"]
    fused = "both" in ReconstructionConfig.model_fields["mode"].annotation.__args__  # type: ignore[union-attr]
    assert mode == ("both" if fused else "projector")
    if not fused:
        assert "note: mode both" in out
    rc, out, err = _decode(capture["manifests"][0], "--calibration", capture["calib"]["both"], "--mode", "stereo",
                           "--out", tmp_path / "s.ply")  # fmt: skip
    assert rc == 0 and "mode stereo" in out, err


def test_batch_builds_once_and_writes_one_cloud_per_capture(
    capture: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import appliance.reconstruct.pipeline as pipeline

    built: list[int] = []
    real = pipeline.Reconstructor

    class Counting(real):  # type: ignore[misc, valid-type]
        def __init__(self, *a: Any, **k: Any) -> None:
            built.append(1)
            super().__init__(*a, **k)

    monkeypatch.setattr(pipeline, "Reconstructor", Counting)
    rc, out, err = _decode(*capture["manifests"], "--calibration", capture["calib"]["procam"], "--mode", "projector",
                           "--out", tmp_path / "clouds", "--maps", tmp_path / "maps", "--timings")  # fmt: skip
    # the procam calibration has no cam1: both captures fail with one line each, nothing is built
    assert rc == 2 and len(err.strip().splitlines()) == 2 and "cam1" in err
    assert "Traceback" not in err and not built
    rc, out, err = _decode(*capture["manifests"], "--calibration", capture["calib"]["both"], "--mode", "projector",
                           "--out", tmp_path / "clouds", "--maps", tmp_path / "maps", "--timings")  # fmt: skip
    assert rc == 0, err
    assert len(built) == 1  # ray tables and reconstruction buffers: once for the batch
    lines = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
    assert [x["capture"] for x in lines[:-1]] == ["scan0", "scan1"]
    assert lines[-1]["summary"] and lines[-1]["captures"] == 2
    for k in range(2):
        assert (tmp_path / "maps" / f"scan{k}.npz").exists()
        assert np.median(_errors_mm(capture["rig"], tmp_path / "clouds" / f"scan{k}.ply")) < 0.3


def test_config_only_overrides_reconstruction(capture: dict[str, Any], tmp_path: Path) -> None:
    cfg = tmp_path / "recon.yaml"
    # hardware entries are never needed, and never touched when present
    cfg.write_text("cameras: {cam0: {type: aravis, address: 127.0.0.254}}\n"
                   "reconstruction: {min_depth_mm: 560, max_depth_mm: 640, min_neighbours: 0}\n")  # fmt: skip
    rc, _, err = _decode(capture["one"], "--calibration", capture["calib"]["procam"], "--config", cfg,
                         "--out", tmp_path / "c.ply", "--report", tmp_path / "r.json")  # fmt: skip
    assert rc == 0, err
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["extra"]["depth_range_mm"] == [560.0, 640.0]
    z = PlyData.read(str(tmp_path / "c.ply"))["vertex"]["z"]
    assert z.min() >= 560 and z.max() <= 640


@pytest.mark.parametrize(
    ("make_args", "needle"),
    [
        (lambda c, t: [t / "absent.yaml"], "absent.yaml: cannot be read"),
        (lambda c, t: [c["one"], "--calibration", t / "nope.yaml"], "nope.yaml: calibration file not found"),
        (lambda c, t: [c["one"], "--out", t / "x.ply"], "--out needs --calibration"),
        (lambda c, t: [*c["manifests"], "--report", t / "r.json"], "--report writes the sidecar of one capture"),
        (lambda c, t: [*c["manifests"], "--calibration", c["calib"]["both"], "--out", t / "x.ply"],
         "several manifests need a folder"),
        (lambda c, t: [c["one"], "--calibration", c["calib"]["stereo"], "--mode", "projector"],
         "no 'projector'; use --mode stereo"),
    ],
)
def test_bad_input_gets_one_line(capture: dict[str, Any], tmp_path: Path, make_args: Any, needle: str) -> None:
    rc, _, err = _decode(*make_args(capture, tmp_path))
    assert rc == 2
    assert needle in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err


def test_a_bad_reconstruction_setting_names_file_line_and_key(capture: dict[str, Any], tmp_path: Path) -> None:
    cfg = tmp_path / "recon.yaml"
    cfg.write_text("output: {whatever: 1}\nreconstruction:\n  min_depth_mm: -5\n")
    rc, _, err = _decode(capture["one"], "--calibration", capture["calib"]["procam"], "--config", cfg)
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert f"{cfg}:3: reconstruction.min_depth_mm = -5" in err


@pytest.mark.parametrize("on_disk", [False, True])
def test_a_first_run_says_it_compiles_the_kernels(
    capture: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, on_disk: bool
) -> None:
    import appliance._numba_cache as nc

    monkeypatch.setattr(nc, "kernels_on_disk", lambda kernel: (on_disk, "/var/cache/scan3d/src-x"))
    rc, out, err = _decode(capture["one"], "--calibration", capture["calib"]["procam"], "--out", tmp_path / "c.ply")
    assert rc == 0, err
    assert "cloud:" in out  # the usual output follows either way
    note = "scan3d decode: compiling the numba kernels for this version"
    assert (note in err) is not on_disk, err
    if not on_disk:
        assert "/var/cache/scan3d/src-x" in err and err.count("\n") == 1  # one line, then the usual output
