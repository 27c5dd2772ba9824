"""Issue 28 through the configuration loader: duplicate keys, typed numbers, finite values, bounds, many
unknown keys, files that are not regular files. Every case is one ConfigError naming the file, line and rule."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from appliance.config import load_config, parse_config
from appliance.config.loader import MAX_PROBLEMS
from appliance.errors import ConfigError

# (YAML text, the line the error must name, words the message must hold)
CASES = [
    ("reconstruction:\n  max_depth_mm: 900\nsequence: {steps: 4}\nreconstruction:\n  min_depth_mm: 5\n", 4,
     "'reconstruction' is given twice (lines 1 and 4)"),
    ("sequence:\n  steps: 4\n  steps: 5\n", 3, "'steps' is given twice (lines 2 and 3)"),
    ("sequence: {steps: true}\n", 1, "sequence.steps = True: must be a whole number"),
    # a board of 1e308 mm squares (scan3d calibrate --square-mm refuses above 10 m; the config did not)
    ("calibration:\n  board: {type: chessboard, cols: 9, rows: 6, square_mm: 1.0e+308}\n", 2,
     "square_mm = 1e+308: Input should be less than or equal to 10000"),
    ("sequence: {steps: 2.5}\n", 1, "sequence.steps = 2.5: must be a whole number"),
    ("virtual_rig:\n  imaging:\n    seed: -1\n", 3, "virtual_rig.imaging.seed = -1"),
    ("virtual_rig:\n  imaging: {camera_blur_px: .inf}\n", 2, "camera_blur_px = inf: Input should be a finite"),
    ("virtual_rig:\n  imaging: {camera_blur_px: 1000}\n", 2, "less than or equal to 20"),
    ("virtual_rig:\n  imaging: {ambient_dn: .inf}\n", 2, "ambient_dn = inf"),
    ("virtual_rig:\n  imaging: {projector_gain_dn: .inf}\n", 2, "projector_gain_dn = inf"),
    ("virtual_rig:\n  imaging: {read_noise_dn: .inf}\n", 2, "read_noise_dn = inf"),
    ("virtual_rig:\n  imaging: {projector_blur_px: .nan}\n", 2, "projector_blur_px = nan"),
    ("virtual_rig:\n  imaging: {shot_noise: 1}\n", 2, "shot_noise = 1: must be true or false"),
    ("sequence: {periods_px: [1e30]}\n", 1, "periods_px"),
    ("sequence: {periods_px: [100000]}\n", 1, "from 4 to 8192"),
    ("virtual_rig:\n  scene:\n    - {type: sphere, center_mm: [0, .nan, 500], radius_mm: 30}\n", 3,
     "virtual_rig.scene.0.center_mm.1 = nan"),
    ("virtual_rig:\n  cameras:\n    cam0: {width: 10000, height: 10000, focal_px: 2000}\n", 3, "100 Mpx"),
    ("sequence: {exposures_us: [true, 100]}\n", 1, "sequence.exposures_us.0 = True: must be a whole number"),
    ("sequence: {exposures_us: [100, 200], intensities: [0.5]}\n", 1, "intensities: 1 value(s) for 2 exposures_us"),
    ("sequence: {exposures_us: [100], intensities: [0]}\n", 1, "intensities: 0.0 must be > 0 and at most 1"),
    ("sequence: {exposures_us: [100], intensities: [.nan]}\n", 1, "intensities"),
    ("sequence: {exposures_us: [100, 100], intensities: [0.5, 0.5]}\n", 1, "two passes have the same exposure"),
    ("sequence: {exposures_us: [100, 100]}\n", 1, "lists an exposure twice"),
    ("sequence:\n  periods_px: [64, 1e30]\n", 2, "sequence.periods_px.1 = '1e30': must be a whole number"),
    ('serial: "SN\\n42"\n', 1, "serial = 'SN\\n42': must be 1-64 letters"),
    # the second sweep: valid, then the scan gave 0 points / NaN rotations
    ("virtual_rig:\n  scene: []\n", 2, "virtual_rig.scene: an empty scene gives no points"),
    ("virtual_rig:\n  cameras:\n    cam0: {width: 160, height: 128, focal_px: 240, position_mm: [0, 0, 0],\n"
     "           look_at_mm: [0, 0, 0]}\n", 3, "look_at_mm [0.0, 0.0, 0.0] is 0 mm from position_mm"),
    # the re-sweep's leftover: an unknown policy came with pydantic's follow-on "at least 1 item" line
    ("service:\n  opcua:\n    security_policies: [Basic999]\n", 3,
     "security_policies.0 = 'Basic999': Input should be 'None'"),
    ("service:\n  opcua:\n    security_policies: []\n", 3, "security_policies: Tuple should have at least 1 item"),
]


@pytest.mark.parametrize(("text", "line", "words"), CASES, ids=[str(i) for i in range(len(CASES))])
def test_bad_values_are_one_line_naming_the_line(text: str, line: int, words: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_config(text, "appliance.yaml")
    msg = str(exc.value)
    assert "\n" not in msg, msg
    assert msg.startswith(f"appliance.yaml:{line}: "), msg
    assert words in msg, msg


def test_a_merge_key_is_not_a_duplicate() -> None:
    # a YAML merge (<<) may repeat a key on purpose; only explicit keys count
    cfg = parse_config("reconstruction:\n  <<: {max_depth_mm: 900}\n  max_depth_mm: 800\n", "a.yaml")
    assert cfg.reconstruction.max_depth_mm == 800


def test_forty_thousand_unknown_keys_stop_at_twenty_with_a_count() -> None:
    text = "".join(f"key{i}: {i}\n" for i in range(40_000))
    with pytest.raises(ConfigError) as exc:
        parse_config(text, "big.yaml")
    lines = str(exc.value).splitlines()
    assert len(lines) == MAX_PROBLEMS + 1
    assert lines[0] == "big.yaml:1: key0 = 0: unknown key (check its spelling against config/appliance.yaml)"
    assert lines[19].startswith("big.yaml:20: key19 = 19")
    assert "39980 more problems (40000 unknown keys in all)" in lines[-1]


def test_a_large_inline_mesh_is_read(tmp_path: Path) -> None:
    n = 5_000
    verts = ", ".join(f"[{i % 100}.5, {i // 100}.25, 600.0]" for i in range(n))
    tris = ", ".join(f"[{i}, {i + 1}, {i + 2}]" for i in range(n - 2))
    path = tmp_path / "mesh.yaml"
    path.write_text(f"virtual_rig:\n  scene:\n    - type: mesh\n      vertices_mm: [{verts}]\n"
                    f"      triangles: [{tris}]\n")
    cfg = load_config(path)
    assert len(cfg.virtual_rig.scene[0].vertices_mm) == n  # type: ignore[union-attr]


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "folder", "huge", "utf16"])
def test_only_regular_files_of_sane_size_are_read(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "appliance.yaml"
    if kind == "fifo":
        os.mkfifo(path)
        wanted = "is a FIFO (named pipe), not a regular file"
    elif kind == "dev_zero":
        path = Path("/dev/zero")
        wanted = "is a character device, not a regular file"
    elif kind == "folder":
        path.mkdir()
        wanted = "is a folder, not a regular file"
    elif kind == "huge":
        with open(path, "wb") as f:
            f.truncate(40 * 1024 * 1024)
        wanted = "too large for a configuration"
    else:
        path.write_bytes("sequence: {steps: 4}\n".encode("utf-16"))
        wanted = "UTF-16"
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    msg = str(exc.value)
    assert msg.startswith(str(path)) and wanted in msg and "\n" not in msg, msg


def test_the_config_watcher_rejects_a_fifo_without_blocking(tmp_path: Path) -> None:
    import asyncio

    from appliance.service.reload import ConfigWatcher

    path = tmp_path / "appliance.yaml"
    path.write_text("sequence: {steps: 4}\n")
    applied: list[object] = []
    rejected: list[str] = []

    async def apply(cfg: object) -> None:
        applied.append(cfg)

    async def scenario() -> tuple[bool, str]:
        watcher = ConfigWatcher(path, apply, rejected.append, poll_s=0)
        assert (await watcher.reload("start"))[0]
        path.unlink()
        os.mkfifo(path)  # the file replaced by a FIFO nobody writes to
        return await asyncio.wait_for(watcher.reload("file changed"), 10)

    ok, msg = asyncio.run(scenario())
    assert not ok and len(applied) == 1
    assert rejected == [msg] and "is a FIFO (named pipe), not a regular file" in msg and "\n" not in msg
