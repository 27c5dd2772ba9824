"""Configuration schema and loader: defaults, line-mapped errors, the shipped config."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance.config import load_config, parse_config
from appliance.config.loader import check_files
from appliance.errors import ConfigError
from appliance.geometry.calibration_file import Calibration, write_calibration
from appliance.geometry.camera import CameraModel

REPO = Path(__file__).resolve().parents[2]


def test_shipped_config_is_valid_and_virtual() -> None:
    cfg = load_config(REPO / "config" / "appliance.yaml")
    assert cfg.is_virtual
    assert list(cfg.cameras) == ["cam0", "cam1"] and cfg.reconstruction.mode == "both"  # the product's rig
    assert list(cfg.virtual_rig.cameras) == ["cam0", "cam1"]


def test_error_names_file_line_path_value_and_rule() -> None:
    text = (
        "cameras:\n  cam0:\n    type: aravis\n    address: 127.0.0.2\n    exposure_us: -5\n"
        "calibration_file: c.yaml\n"
    )
    with pytest.raises(ConfigError) as exc:
        parse_config(text, "appliance.yaml")
    msg = str(exc.value)
    assert "appliance.yaml:5: cameras.cam0.exposure_us = -5" in msg
    assert "greater than 0" in msg


def test_unknown_key_is_rejected_with_its_line() -> None:
    with pytest.raises(ConfigError, match=r"appliance.yaml:3: sequence.stepz = 4: unknown key"):
        parse_config("sequence:\n  kind: gray\n  stepz: 4\n", "appliance.yaml")


def test_yaml_syntax_error_names_the_line() -> None:
    with pytest.raises(ConfigError, match=r"appliance.yaml:3: not valid YAML"):
        parse_config("sequence:\n  kind: [gray\n", "appliance.yaml")


def test_cross_field_rules() -> None:
    with pytest.raises(ConfigError, match="max_depth_mm"):
        parse_config("reconstruction: {min_depth_mm: 500, max_depth_mm: 100}")
    with pytest.raises(ConfigError, match=r"stereo.*two cameras"):
        parse_config("reconstruction: {mode: stereo}")
    with pytest.raises(ConfigError, match="calibration_file must be set"):
        parse_config("projector: {type: lightcrafter4500}")
    with pytest.raises(ConfigError, match="coarsest first"):
        parse_config("sequence: {periods_px: [16, 64]}")
    with pytest.raises(ConfigError, match=r"set reconstruction.normals: true"):
        parse_config("output: {normals: true}")
    assert parse_config("output: {normals: true}\nreconstruction: {normals: true}").output.normals


def test_missing_file() -> None:
    with pytest.raises(ConfigError, match="cannot be read"):
        load_config("/nonexistent/appliance.yaml")


@pytest.mark.parametrize(
    ("data", "wanted"),
    [
        (b"", "not a YAML mapping (empty)"),
        (b"# all commented out\n\n", "not a YAML mapping (empty)"),
        (b"\x00\x01\x02\x03PK\x03\x04", "not a YAML mapping (binary data"),
        (b"serial: caf\xe9\n", "not a YAML mapping (not UTF-8 text: byte 0xe9 at offset 11)"),
        (b"- cameras\n- output\n", ":1: not a YAML mapping (a list)"),
        (b"just words\n", ":1: not a YAML mapping (a single string)"),
        (b"[" * 20000, "nested too deeply"),
        (b"serial: \x07\n", "not valid YAML"),
    ],
    ids=["empty", "comments", "binary", "latin1", "list", "string", "deep", "control-char"],
)
def test_files_that_are_not_a_mapping_are_one_line_errors(tmp_path: Path, data: bytes, wanted: str) -> None:
    path = tmp_path / "appliance.yaml"
    path.write_bytes(data)
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}") and wanted in msg and "\n" not in msg, msg


def validate(path: Path) -> tuple[int, str]:
    r = subprocess.run(
        [sys.executable, "-m", "appliance", "validate-config", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    return r.returncode, r.stdout + r.stderr


def test_validate_config_refuses_binary_and_empty_files_in_one_line(tmp_path: Path) -> None:
    for name, data in (("empty.yaml", b""), ("binary.yaml", b"\xff\xd8\xff\xe0\x00\x10JFIF\x00")):
        path = tmp_path / name
        path.write_bytes(data)
        rc, out = validate(path)
        assert rc == 1 and "Traceback" not in out, out
        assert out.strip().count("\n") == 0 and "not a YAML mapping" in out, out


def test_validate_config_checks_the_files_it_names(tmp_path: Path) -> None:
    (tmp_path / "share").mkdir()
    cal = tmp_path / "calibration.yaml"
    doc = {
        "calibration_file": str(cal),
        "virtual_rig": {"scene": [{"type": "mesh", "path": "part.ply"}]},
        "output": {"directory": str(tmp_path / "share"), "spool_directory": str(tmp_path / "share" / "spool")},
    }
    path = tmp_path / "appliance.yaml"
    path.write_text(yaml.safe_dump(doc))
    rc, out = validate(path)
    assert rc == 1 and "Traceback" not in out, out
    assert f"calibration_file = '{cal}': does not exist" in out
    assert f"virtual_rig.scene.0.path = '{tmp_path / 'part.ply'}': does not exist" in out
    assert "output.spool_directory" in out and "is inside the share" in out
    # a calibration that reads (validate-config reads it as the service will at start)
    k = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    write_calibration(cal, Calibration({"cam0": CameraModel("cam0", k, np.zeros(5), 640, 480)}))
    (tmp_path / "part.ply").write_text("ply\n")
    doc["output"]["spool_directory"] = str(tmp_path / "spool")
    path.write_text(yaml.safe_dump(doc))
    rc, out = validate(path)
    assert rc == 0 and ": valid." in out, out


def test_check_files_finds_the_spool_equal_to_the_share(tmp_path: Path) -> None:
    cfg = parse_config(f"output: {{directory: {tmp_path}/s, spool_directory: {tmp_path}/s/}}\n", "a.yaml")
    (problem,) = check_files(cfg, "a.yaml")
    assert "is the share" in problem
