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
    # the second sweep: kept as an unknown pattern kind and ignored, or images ignored for stacks, with exit 0
    ("pattern_number", lambda t, c: t.replace("pattern: white", "pattern: 5", 1), ("pattern = 5", "must be a name")),
    ("pattern_null", lambda t, c: t.replace("pattern: white", "pattern: null", 1), ("pattern = None",)),
    ("stacks_and_images", lambda t, c: t.replace("cameras: [cam0]\n", "cameras: [cam0]\nstacks: {cam0: s.npy}\n", 1),
     ("frames[0]", "'stacks' too")),
    # the re-sweep's leftover: images of a camera left out of cameras: were dropped without a word
    ("images_of_an_unlisted_camera", lambda t, c: t.replace("{cam0: ", "{cam9: x.png, cam0: ", 1),
     ("frames[0]", "['cam9'] are not in cameras", "add them to cameras:")),
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
    # the second sweep: OpenCV kept one of two keys silently; its messages span lines
    ("camera_twice", lambda t: t + "cam0:\n   rms: 0.\n", ("'cam0' is given twice (lines 3 and",)),
    ("K_twice", lambda t: t.replace("   dist: !!opencv-matrix", "   K: [1, 0, 0]\n   dist: !!opencv-matrix", 1),
     ("'K' is given twice (lines 4 and 9)",)),
    ("K_short", lambda t: t.replace("      rows: 3\n      cols: 3\n      dt: d\n      data: [",
                                    "      rows: 3\n      cols: 3\n      dt: d\n      data: [ 1. ]\n      old: [", 1),
     ("cam0.K: unreadable",)),
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


@pytest.mark.parametrize("case", ["state_is_a_file", "socket_too_long", "share_is_a_file", "share_has_nul",
                                  "socket_is_a_file"])
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
    elif case == "socket_is_a_file":  # scan3d run refuses to replace it; validate-config said valid
        service["control_socket"], words = str(blocker), "a file that is not a socket is there"
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


def test_run_refuses_a_read_only_state_folder_even_as_root(tmp_path: Path) -> None:
    """``scan3d run`` whose state folder is on a read-only filesystem stops at start with one line. A chmod
    proves nothing as root (root writes through the mode bits), so the folder is a read-only tmpfs mounted in a
    mount namespace of the command's own (``unshare -m``: private, gone with the process)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro tmpfs '{ro}'"],
                           capture_output=True, text=True, timeout=30, check=False)  # fmt: skip
    if probe.returncode != 0:
        pytest.skip(f"no private read-only mount here (unshare -m + mount): {probe.stderr.strip()[:200]}")
    service = {"state_directory": str(ro), "control_socket": str(tmp_path / "ctl.sock")}
    output = {"directory": str(tmp_path / "share"), "spool_directory": str(tmp_path / "spool"), "preview": False}
    config = tmp_path / "appliance.yaml"
    config.write_text(RIG + yaml.safe_dump({"service": service, "output": output}))
    env = {**os.environ, "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))}
    cmd = (f"mount -t tmpfs -o ro tmpfs '{ro}' && exec '{sys.executable}' -m appliance run --config '{config}' "
           "--scans 1")
    done = subprocess.run(["unshare", "-m", "sh", "-c", cmd], capture_output=True, text=True, timeout=120,
                          cwd=REPO, env=env, check=False)  # fmt: skip
    said = done.stdout + done.stderr
    lines = [ln for ln in said.splitlines() if ln.strip() and "compiling the numba kernels" not in ln]
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in said, said
    assert all(w in lines[0] for w in ("service.state_directory", str(ro), "is not writable", "writable folder")), \
        lines[0]
    assert not (tmp_path / "ctl.sock").exists()  # never listened, so never said ready
    assert list(ro.iterdir()) == []  # the mount was the command's own: the folder beneath is untouched


@pytest.mark.parametrize("where", ["config", "option"])
def test_run_with_a_socket_path_too_long_is_one_line(tmp_path: Path, where: str) -> None:
    """``scan3d run`` whose control socket path does not fit a unix socket (the config's or --control-socket's)
    stops at start with one line naming the path and the limit, not bind's traceback."""
    long = tmp_path / ("s" * 120) / "c.sock"
    service = {"state_directory": str(tmp_path / "state"),
               "control_socket": str(long if where == "config" else tmp_path / "c.sock")}
    output = {"directory": str(tmp_path / "share"), "spool_directory": str(tmp_path / "spool"), "preview": False}
    config = tmp_path / "appliance.yaml"
    config.write_text(RIG + yaml.safe_dump({"service": service, "output": output}))
    extra = ["--control-socket", str(long)] if where == "option" else []
    done = _scan3d("run", "--config", str(config), "--scans", "1", *extra, timeout=120)
    said = done.stdout + done.stderr
    lines = [ln for ln in said.splitlines() if ln.strip() and "compiling the numba kernels" not in ln]
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in said, said
    assert str(long) in lines[0] and "longer than a unix socket path" in lines[0], lines[0]


@pytest.mark.parametrize("case", ["out_is_the_manifest", "maps_is_the_calibration", "out_is_maps",
                                  "preview_is_a_frame", "manifest_twice"])
def test_an_output_that_is_an_input_is_refused(capture: dict[str, Path], tmp_path: Path, case: str) -> None:
    """``scan3d decode`` never writes over its own inputs (the manifest, the calibration, a frame: a cloud's
    preview goes beside it as .png) nor writes one file twice; the line names both roles."""
    folder = tmp_path / "cap"
    folder.mkdir()
    for p in capture["folder"].iterdir():
        if p.suffix == ".png" or p.name in ("scan.yaml", "calibration.yaml"):
            (folder / p.name).write_bytes(p.read_bytes())
    manifest, calib = folder / "scan.yaml", folder / "calibration.yaml"
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    argv = ["decode", str(manifest), *([str(manifest)] if case == "manifest_twice" else []), "--calibration",
            str(calib)]
    argv += {"out_is_the_manifest": ["--out", str(manifest)],
             "maps_is_the_calibration": ["--maps", str(calib)],
             "out_is_maps": ["--out", str(tmp_path / "x.out"), "--maps", str(tmp_path / "x.out")],
             "preview_is_a_frame": ["--out", str(folder / "f05.ply")],
             "manifest_twice": ["--out", str(tmp_path / "o")]}[case]
    words = {"out_is_the_manifest": "--out", "maps_is_the_calibration": "is also --calibration",
             "out_is_maps": "is also --out", "preview_is_a_frame": "is also a frame of the capture",
             "manifest_twice": "is given twice"}[case]
    rc, err = _run(argv)
    _one_line(rc, err, words)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert not (tmp_path / "x.out").exists() and not (tmp_path / "o").exists()


def test_an_empty_npy_stack_is_one_line(capture: dict[str, Path], tmp_path: Path) -> None:
    (tmp_path / "cam0.npy").write_bytes(b"")
    manifest = tmp_path / "scan.yaml"
    manifest.write_text("projector: {width: 160, height: 100}\ncameras: [cam0]\nstacks: {cam0: cam0.npy}\n"
                        "frames:\n- {pattern: white}\n- {pattern: black}\n")
    rc, err = _run(["decode", str(manifest), "--calibration", str(capture["calibration"]),
                    "--out", str(tmp_path / "o.ply")])
    _one_line(rc, err, "cam0.npy", "cannot be read")
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("case", ["out_is_an_input", "out_is_a_folder", "out_under_a_file", "input_fifo",
                                  "input_missing", "input_not_an_image", "square_1e308"])
def test_calibrate_camera_refuses_bad_paths_before_any_work(tmp_path: Path, case: str) -> None:
    """``scan3d calibrate camera`` (a subprocess: OpenCV's own log lines go to the process's stderr) checks its
    --out before it reads an image and reads only regular files: one line, no OpenCV log, no hang, the input
    image untouched."""
    photo = tmp_path / "pose0.png"
    photo.write_bytes(b"not really a photo\n")
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    (tmp_path / "folder").mkdir()
    image, out, square = str(photo), str(tmp_path / "c.yaml"), "25"
    if case == "out_is_an_input":
        out = str(photo)
    elif case == "out_is_a_folder":
        out = str(tmp_path / "folder")
    elif case == "out_under_a_file":
        out = str(blocker / "c.yaml")
    elif case == "input_fifo":
        os.mkfifo(tmp_path / "fifo.png")
        image = str(tmp_path / "fifo.png")
    elif case == "input_missing":
        image = str(tmp_path / "nope.png")
    elif case == "square_1e308":
        square = "1e308"
    words = {"out_is_an_input": "is also a board image", "out_is_a_folder": "is a folder",
             "out_under_a_file": "its folder cannot be made", "input_fifo": "not a regular file",
             "input_missing": "No such file", "input_not_an_image": "not an image OpenCV can read",
             "square_1e308": "square_mm = 1e+308"}[case]
    done = _scan3d("calibrate", "camera", image, "--square-mm", square, "--out", out, timeout=60)
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert words in lines[0], lines[0]
    assert photo.read_bytes() == b"not really a photo\n" and blocker.read_text() == "x"
    assert not (tmp_path / "c.yaml").exists()


@pytest.mark.parametrize("case", ["nul", "only_header", "twice"])
def test_validate_config_reads_the_calibration_file(capture: dict[str, Path], tmp_path: Path, case: str) -> None:
    """The service reads calibration_file at every start: validate-config reads it too (a readable file that
    is not a calibration was 'valid'; a NUL in the path was a traceback)."""
    calib = tmp_path / "calibration.yaml"
    text = capture["calibration"].read_text()
    calib.write_text({"nul": text, "only_header": "%YAML:1.0\n", "twice": text + "cam0:\n   rms: 0.\n"}[case])
    path = tmp_path / "appliance.yaml"
    where = str(tmp_path / "cal\x00ibration.yaml") if case == "nul" else str(calib)
    path.write_text(yaml.safe_dump({"calibration_file": where}))
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["validate-config", str(path)])
    lines = [ln for ln in out.getvalue().splitlines() if ln.strip()]
    assert rc == 1 and len(lines) == 1 and "Traceback" not in out.getvalue(), out.getvalue()
    words = {"nul": "holds a NUL character", "only_header": "holds no device maps", "twice": "given twice"}[case]
    assert "calibration_file" in lines[0] and words in lines[0], lines[0]


COUNT_CASES = [
    (["run", "--scans", "0"], "--scans 0: must be at least 1"),
    (["run", "--scans", "-1"], "--scans -1: must be at least 1"),
    (["grab", "--camera", "cam0", "--frames", "0", "--out", "{tmp}/g"], "--frames 0: must be at least 1"),
    (["patterns", "--width", "0", "--out", "{tmp}/p"], "--width 0: must be from 16 to 10000"),
    (["patterns", "--width", "-160", "--out", "{tmp}/p"], "--width -160"),
    (["patterns", "--height", "1000000", "--out", "{tmp}/p"], "--height 1000000"),
    (["patterns", "--config", "{tmp}/missing.yaml", "--out", "{tmp}/p"], "configuration file not found"),
    (["simulate-camera", "--packet-loss", "2"], "--packet-loss 2.0: must be a share from 0 to 1"),
    (["simulate-camera", "--packet-loss", "nan"], "--packet-loss nan"),
]


@pytest.mark.parametrize(("argv", "words"), COUNT_CASES, ids=[" ".join(c[0][:3]) for c in COUNT_CASES])
def test_counts_and_sizes_out_of_range_are_one_line(tmp_path: Path, argv: list[str], words: str) -> None:
    """The sweep: run --scans 0 ran for ever, grab --frames 0 and patterns --width 0 (the configured width)
    did nothing or something else with exit 0, a negative or huge width was a traceback, a named config that
    does not exist fell back to the defaults, simulate-camera served with a packet loss of 2 or NaN."""
    config = tmp_path / "rig.yaml"
    config.write_text(SMALL_RIG)
    args = [a.format(tmp=tmp_path) for a in argv]
    if "--config" not in args:
        args[1:1] = ["--config", str(config)]
    rc, err = _run(args)
    _one_line(rc, err, words)
    assert not (tmp_path / "g").exists() and not (tmp_path / "p").exists()


@pytest.mark.parametrize("victim", ["config", "calibration"])
def test_verify_never_writes_its_report_over_an_input(capture: dict[str, Path], tmp_path: Path, victim: str) -> None:
    """The sweep: ``scan3d verify --out rig.yaml`` scanned for 30 s, then replaced the configuration with the
    HTML report (exit 1: the figures). Now refused before any scan, every input byte-identical."""
    calib = tmp_path / "calibration.yaml"
    calib.write_bytes(capture["calibration"].read_bytes())
    config = tmp_path / "rig.yaml"
    config.write_text(SMALL_RIG + f"calibration_file: {calib}\n")
    before = {p: p.read_bytes() for p in (config, calib)}
    rc, err = _run(["verify", "--config", str(config), "--out", str(config if victim == "config" else calib)])
    _one_line(rc, err, "which is the configuration" if victim == "config" else "which is calibration_file")
    assert {p: p.read_bytes() for p in (config, calib)} == before


@pytest.mark.parametrize("option", ["--maps", "--out", "--report"])
def test_an_output_under_a_file_says_so(capture: dict[str, Path], tmp_path: Path, option: str) -> None:
    """An output whose folder is a plain file: the line says 'is a file, not a folder' (was 'File exists')."""
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    rc, err = _run(["decode", str(capture["manifest"]), "--calibration", str(capture["calibration"]),
                    option, str(blocker / "x.npz")])
    _one_line(rc, err, f"{blocker}: is a file, not a folder; check {option}")
    assert blocker.read_text() == "x"
