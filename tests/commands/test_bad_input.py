"""Issue 28 through the commands a person runs: each bad manifest, calibration, frame or configuration is
exit status 2 and exactly one line on stderr naming the file, no traceback, in time; nothing is written.

The cases that used to hang (a FIFO or /dev/zero given as a file) run ``scan3d`` in a subprocess with a
timeout, so a regression fails instead of hanging the suite.
"""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from appliance import cli
from appliance.config import parse_config
from appliance.geometry.calibration_file import write_calibration
from appliance.patterns.from_config import build_sequence
from appliance.patterns.manifest import write_manifest
from appliance.scan import virtual_calibration
from appliance.sim.rig import VirtualRig

REPO = Path(__file__).resolve().parents[2]

RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 160, height: 100, focal_px: 220, position_mm: [60, 0, 0], look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 120, height: 96, focal_px: 180, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
"""


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A small good capture (PNG frames, manifest, calibration) that each case spoils a copy of."""
    folder = tmp_path_factory.mktemp("bad_input")
    cfg = parse_config(RIG, "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    seq = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    stack = rig.render(seq, "cam0")
    names = []
    for i, img in enumerate(stack):
        names.append(f"f{i:02d}.png")
        cv2.imwrite(str(folder / names[-1]), img)
    manifest = write_manifest(folder / "scan.yaml", seq, ["cam0"], images={"cam0": names})
    calib = folder / "calibration.yaml"
    write_calibration(calib, virtual_calibration(rig))
    return {"folder": folder, "manifest": manifest, "calibration": calib}


def _run(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = cli.main(argv)
    return rc, err.getvalue()


def _one_line(rc: int, err: str, *words: str) -> None:
    # the one-time note that the numba kernels are being compiled (a cold cache) is not a message about the input
    lines = [ln for ln in err.splitlines() if ln.strip() and "compiling the numba kernels" not in ln]
    assert rc == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], lines[0]


def test_the_good_capture_decodes(capture: dict[str, Path], tmp_path: Path) -> None:
    rc, err = _run(["decode", str(capture["manifest"]), "--calibration", str(capture["calibration"]),
                    "--out", str(tmp_path / "cloud.ply")])
    assert rc == 0, err
    assert (tmp_path / "cloud.ply").stat().st_size > 1000


# (case, how the manifest text is spoilt, words of the one line)
MANIFEST_CASES: list[tuple[str, Callable[[str, dict[str, Path]], str | bytes], tuple[str, ...]]] = [  # type: ignore[type-arg]
    ("binary", lambda t, c: b"\x00\x01\x02" * 100, ("binary data",)),
    ("utf16", lambda t, c: t.encode("utf-16"), ("UTF-16",)),
    ("deep", lambda t, c: "a: " + "[" * 3000 + "]" * 3000 + "\n", ("nested too deeply",)),
    ("bit_inf", lambda t, c: t.replace("bit: 0", "bit: .inf", 1), ("bit = inf", "whole number")),
    ("bit_true", lambda t, c: t.replace("bit: 0", "bit: true", 1), ("bit = True", "whole number")),
    ("bit_fraction", lambda t, c: t.replace("bit: 0", "bit: 2.5", 1), ("bit = 2.5", "whole number")),
    ("bit_twice", lambda t, c: t.replace("  bit: 0\n", "  bit: 0\n  bit: 1\n", 1), ("'bit' is given twice",)),
    ("width_nan", lambda t, c: t.replace("width: 160", "width: .nan", 1), ("projector.width = nan",)),
    ("offset_nan", lambda t, c: t.replace("  steps: 4\n", "  steps: 4\n  offset: .nan\n", 1),
     ("offset = nan", "finite")),
    ("steps_huge", lambda t, c: t.replace("steps: 4", "steps: 1000000000", 1), ("steps = 1000000000",)),
    ("projector_16", lambda t, c: t.replace("width: 160", "width: 16", 1).replace("height: 100", "height: 16", 1),
     ("calibrated at 160x100", "16x16")),
    ("too_big", lambda t, c: t + "#" * (11 * 1024 * 1024), ("too large for a manifest",)),
]


@pytest.mark.parametrize(("case", "spoil", "words"), MANIFEST_CASES, ids=[c[0] for c in MANIFEST_CASES])
def test_a_bad_manifest_is_one_line(capture: dict[str, Path], tmp_path: Path, case: str,
                                    spoil: Callable[[str, dict[str, Path]], str | bytes],
                                    words: tuple[str, ...]) -> None:
    text = capture["manifest"].read_text()
    bad = spoil(text, capture)
    path = capture["folder"] / f"bad_{case}.yaml"
    if isinstance(bad, bytes):
        path.write_bytes(bad)
    else:
        assert bad != text, "the spoiling did not apply"
        path.write_text(bad)
    out = tmp_path / "out"
    rc, err = _run(["decode", str(path), "--calibration", str(capture["calibration"]), "--out", str(out)])
    # the projector's size is judged against the calibration, which the line names
    _one_line(rc, err, str(capture["calibration"] if case == "projector_16" else path), *words)
    assert not out.exists() or not any(out.iterdir())


CALIBRATION_CASES: list[tuple[str, Callable[[str], str], tuple[str, ...]]] = [
    ("only_header", lambda t: "%YAML:1.0\n", ("holds no device maps",)),
    ("dt_u", lambda t: t.replace("dt: d", "dt: u", 1), ("dt: u", "float64")),
    ("rms_bad", lambda t: t.replace("rms:", 'rms: "bad"\n   old_rms:', 1), ("rms = 'bad'",)),
    ("no_camera", lambda t: t.replace("cam0:", "camX:", 1), ("cam0", "no entry")),
]


@pytest.mark.parametrize(("case", "spoil", "words"), CALIBRATION_CASES, ids=[c[0] for c in CALIBRATION_CASES])
def test_a_bad_calibration_is_one_line(capture: dict[str, Path], tmp_path: Path, case: str,
                                       spoil: Callable[[str], str], words: tuple[str, ...]) -> None:
    text = capture["calibration"].read_text()
    bad = spoil(text)
    assert bad != text
    path = tmp_path / "calibration.yaml"
    path.write_text(bad)
    out = tmp_path / "out"
    rc, err = _run(["decode", str(capture["manifest"]), "--calibration", str(path), "--out", str(out)])
    _one_line(rc, err, *words)
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("cut", ["png", "jpeg", "empty"])
def test_a_truncated_frame_is_refused_with_its_name(capture: dict[str, Path], tmp_path: Path, cut: str) -> None:
    folder = tmp_path / "cap"
    folder.mkdir()
    doc = yaml.safe_load(capture["manifest"].read_text())
    for f in doc["frames"]:
        src = capture["folder"] / f["images"]["cam0"]
        (folder / src.name).write_bytes(src.read_bytes())
    victim = folder / doc["frames"][3]["images"]["cam0"]
    if cut == "jpeg":
        img = cv2.imread(str(victim), cv2.IMREAD_UNCHANGED)
        ok, enc = cv2.imencode(".jpg", img)
        assert ok
        victim = victim.with_suffix(".jpg")
        victim.write_bytes(enc.tobytes()[: len(enc) * 3 // 4])
        doc["frames"][3]["images"]["cam0"] = victim.name
    elif cut == "png":
        data = victim.read_bytes()
        victim.write_bytes(data[: len(data) * 2 // 3])
    else:
        victim.write_bytes(b"")
    manifest = folder / "scan.yaml"
    manifest.write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, err = _run(["decode", str(manifest), "--calibration", str(capture["calibration"]),
                    "--out", str(tmp_path / "out.ply")])
    _one_line(rc, err, "frame 3", victim.name)
    assert not (tmp_path / "out.ply").exists()


CONFIG_CASES = [
    ("duplicate", "reconstruction:\n  max_depth_mm: 900\nreconstruction:\n  min_depth_mm: 5\n",
     ("'reconstruction' is given twice (lines 1 and 3)",)),
    ("seed", "virtual_rig:\n  imaging: {seed: -1}\n", ("seed = -1",)),
    ("blur_inf", "virtual_rig:\n  imaging: {camera_blur_px: .inf}\n", ("camera_blur_px = inf",)),
    ("periods", "sequence: {periods_px: [1e30]}\n", ("periods_px",)),
    ("camera_10k", "virtual_rig:\n  cameras:\n    cam0: {width: 10000, height: 10000, focal_px: 2000}\n",
     ("100 Mpx",)),
]


@pytest.mark.parametrize(("case", "text", "words"), CONFIG_CASES, ids=[c[0] for c in CONFIG_CASES])
def test_validate_config_refuses_in_one_line(tmp_path: Path, case: str, text: str, words: tuple[str, ...]) -> None:
    path = tmp_path / "appliance.yaml"
    path.write_text(text)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["validate-config", str(path)])
    text = out.getvalue()
    assert rc == 1  # validate-config reports on stdout, exit 1
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in text, text
    assert all(w in lines[0] for w in words), lines[0]


@pytest.mark.parametrize("case", ["state_is_a_file", "socket_too_long", "share_is_a_file", "share_has_nul"])
def test_validate_config_checks_what_the_service_needs(tmp_path: Path, case: str) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")
    service = {"state_directory": str(tmp_path / "state"), "control_socket": "/tmp/scan3d-test.sock"}
    output = {"directory": str(tmp_path / "share"), "spool_directory": str(tmp_path / "spool")}
    if case == "state_is_a_file":
        service["state_directory"], words = str(blocker), "service.state_directory"
    elif case == "socket_too_long":
        service["control_socket"], words = str(tmp_path / ("s" * 120) / "c.sock"), "longer than a unix socket path"
    elif case == "share_is_a_file":
        output["directory"], words = str(blocker / "scans"), "is a file, not a folder"
    else:
        output["directory"], words = str(tmp_path / "sha\x00re"), "NUL"
    path = tmp_path / "appliance.yaml"
    path.write_text(yaml.safe_dump({"service": service, "output": output}))
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["validate-config", str(path)])
    lines = [ln for ln in out.getvalue().splitlines() if ln.strip()]
    assert rc == 1 and len(lines) == 1 and "Traceback" not in out.getvalue(), out.getvalue()
    assert words in lines[0], lines[0]


def _scan3d(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))}
    return subprocess.run([sys.executable, "-m", "appliance", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, env=env, check=False)


def test_files_that_never_end_do_not_hang_the_commands(capture: dict[str, Path], tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    os.mkfifo(tmp_path / "stack.npy")
    os.mkfifo(tmp_path / "mesh.obj")
    meshed = tmp_path / "meshed.yaml"
    meshed.write_text("virtual_rig:\n  scene:\n    - {type: mesh, path: mesh.obj}\n")
    stacked = tmp_path / "stacked.yaml"
    stacked.write_text("projector: {width: 64, height: 32}\ncameras: [cam0]\nstacks: {cam0: stack.npy}\n"
                       "frames:\n- {pattern: white}\n- {pattern: black}\n")
    for args in (["validate-config", str(fifo)],
                 ["decode", str(fifo), "--calibration", str(capture["calibration"])],
                 ["decode", str(capture["manifest"]), "--calibration", "/dev/zero"],
                 ["decode", str(capture["manifest"]), "--config", str(fifo)],
                 ["scan", "--config", str(fifo)],
                 ["run", "--config", str(fifo)],
                 ["decode", str(stacked)],
                 ["validate-config", str(meshed)],
                 ["scan", "--config", str(meshed)]):
        done = _scan3d(*args)
        said = done.stdout + done.stderr
        lines = [ln for ln in said.splitlines() if ln.strip() and "compiling the numba kernels" not in ln]
        assert done.returncode != 0 and len(lines) == 1, said
        assert "not a regular file" in lines[0] and "Traceback" not in said, lines[0]


def test_a_batch_whose_outputs_would_collide_is_refused_before_any_work(capture: dict[str, Path],
                                                                        tmp_path: Path) -> None:
    twins = []
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        twins.append(tmp_path / sub / "scan.yaml")
        twins[-1].write_text(capture["manifest"].read_text().replace("{cam0: f", "{cam0: ../../" +
                                                                     capture["folder"].name + "/f"))
    out = tmp_path / "out"
    rc, err = _run(["decode", *map(str, twins), "--calibration", str(capture["calibration"]), "--out", str(out)])
    _one_line(rc, err, str(twins[0]), str(twins[1]), "scan.ply")
    assert not out.exists()


def test_maps_on_a_full_disk_keep_the_old_file(capture: dict[str, Path], tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    maps = tmp_path / "x.npz"
    maps.write_bytes(b"the maps of yesterday")
    real = np.savez_compressed

    def full_disk(f: object, **arrays: object) -> None:
        real(io.BytesIO(), **arrays)  # type: ignore[arg-type]
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", full_disk)
    rc, err = _run(["decode", str(capture["manifest"]), "--maps", str(maps)])
    _one_line(rc, err, str(maps), "No space left on device")
    assert maps.read_bytes() == b"the maps of yesterday"
    assert [p.name for p in tmp_path.iterdir()] == ["x.npz"]


SMALL_RIG = RIG + "output: {preview: false}\n"


@pytest.mark.parametrize("case", ["count_0", "out_is_a_file", "out_has_nul", "out_under_a_file"])
def test_scan_checks_its_output_before_it_captures(tmp_path: Path, case: str) -> None:
    config = tmp_path / "rig.yaml"
    config.write_text(SMALL_RIG)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    argv = ["scan", "--config", str(config), "--no-compare", "--out", str(tmp_path / "scans")]
    words = {"count_0": "--count 0", "out_is_a_file": "is a file, not a folder",
             "out_has_nul": "NUL", "out_under_a_file": "is a file, not a folder"}[case]
    if case == "count_0":
        argv += ["--count", "0"]
    else:
        argv[-1] = {"out_is_a_file": str(blocker), "out_has_nul": str(tmp_path / "sc\x00ans"),
                    "out_under_a_file": str(blocker / "scans")}[case]
    rc, err = _run(argv)
    _one_line(rc, err, words)


@pytest.mark.slow  # a whole scan in a fresh process (numba kernels loaded or compiled): 10-100 s here
def test_a_scan_that_cannot_be_written_is_spooled(tmp_path: Path) -> None:
    import datetime as dt

    config = tmp_path / "rig.yaml"
    config.write_text(SMALL_RIG.replace("output: {preview: false}",
                                        f"output: {{preview: false, spool_directory: '{tmp_path / 'spool'}'}}"))
    scans = tmp_path / "scans"
    scans.mkdir()  # the output folder passes the check before the capture ...
    today = dt.datetime.now(dt.UTC).date()
    for day in (today, today + dt.timedelta(days=1)):
        (scans / f"{day:%Y-%m-%d}").write_text("a file where the day's folder goes\n")  # ... its day folder fails
    # a subprocess: the loop guard of the suite is not what this test is about
    done = _scan3d("scan", "--config", str(config), "--no-compare", "--out", str(scans), timeout=300)
    lines = [ln for ln in done.stderr.splitlines() if ln.strip() and "compiling the numba" not in ln]
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert "kept in the spool" in lines[0], lines[0]
    entries = [p for p in (tmp_path / "spool").iterdir() if not p.name.startswith(".")]
    assert len(entries) == 1
    assert sorted(p.suffix for p in entries[0].iterdir()) == [".json", ".json", ".ply"]


WHITE0 = REPO.parent / "shared" / "data" / "procam_graycode_calib" / "capture_0" / "graycode_40.png"


@pytest.mark.skipif(not WHITE0.is_file(), reason=f"test data {WHITE0} is absent")
def test_one_calibration_image_given_four_times_counts_once(tmp_path: Path) -> None:
    out = io.StringIO()
    err = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["calibrate", "camera", *[str(WHITE0)] * 4, "--board", "chessboard", "--cols", "9",
                       "--rows", "7", "--square-mm", "75", "--out", str(tmp_path / "c.yaml")])
    assert out.getvalue().count("counted once") == 3
    _one_line(rc, err.getvalue(), "only 1 usable views of 1")  # not four views of one pose
    assert not (tmp_path / "c.yaml").exists()


def test_calibrate_with_an_infinite_square_is_one_line(tmp_path: Path) -> None:
    rc, err = _run(["calibrate", "camera", str(WHITE0), "--square-mm", "inf", "--out", str(tmp_path / "c.yaml")])
    _one_line(rc, err, "square_mm", "finite")


def test_a_calibration_report_on_a_full_disk_leaves_no_empty_png(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    from appliance.calibration import report
    from appliance.errors import OutputError

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report.os, "fsync", full)
    with pytest.raises(OutputError, match="No space left on device"):
        report._write_whole(tmp_path / "cam0_residuals.png", b"\x89PNG" + b"\x00" * 100)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("case", ["state_is_a_file", "spool_under_a_file"])
def test_run_refuses_to_start_without_its_local_folders(tmp_path: Path, case: str) -> None:
    """``scan3d run`` with a state folder that is a file (or a spool under one) stops at start with one line and
    a non-zero exit (systemd shows the unit failed) instead of saying ready and failing every scan."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")
    service = {"state_directory": str(tmp_path / "state"), "control_socket": str(tmp_path / "ctl.sock")}
    output = {"directory": str(tmp_path / "share"), "spool_directory": str(tmp_path / "spool"), "preview": False}
    if case == "state_is_a_file":
        service["state_directory"], key, bad = str(blocker), "service.state_directory", str(blocker)
    else:
        output["spool_directory"] = bad = str(blocker / "spool")
        key = "output.spool_directory"
    config = tmp_path / "appliance.yaml"
    config.write_text(RIG + yaml.safe_dump({"service": service, "output": output}))
    done = _scan3d("run", "--config", str(config), "--scans", "1", timeout=120)
    said = done.stdout + done.stderr
    lines = [ln for ln in said.splitlines() if ln.strip() and "compiling the numba kernels" not in ln]
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in said, said
    assert all(w in lines[0] for w in (key, bad, "is a file, not a folder", "writable folder")), lines[0]
    assert not (tmp_path / "ctl.sock").exists()  # never listened, so never said ready
    assert blocker.read_text() == "not a folder\n"
