"""Configuration schema and loader: defaults, line-mapped errors, the shipped config."""

from __future__ import annotations

from pathlib import Path

import pytest

from appliance.config import load_config, parse_config
from appliance.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def test_shipped_config_is_valid_and_virtual() -> None:
    cfg = load_config(REPO / "config" / "appliance.yaml")
    assert cfg.is_virtual
    assert list(cfg.cameras) == ["cam0"]


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
