"""A large inline mesh in the configuration (issue 28 item 6): its numeric lists are read by the JSON decoder
(``config.loader._lift_numeric_lists``) with the same result, the same errors and the same line numbers as the
YAML reading; lists YAML reads differently from JSON are left to YAML; a mesh over ~1 MB gets a line saying to
use a mesh file (``virtual_rig.scene.N.path``: PLY/OBJ/STL)."""

from __future__ import annotations

import contextlib
import io
import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance import cli
from appliance.config import parse_config
from appliance.config.loader import LIFT_MIN_CHARS, _lift_numeric_lists
from appliance.config.schema import AppConfig
from appliance.errors import ConfigError


def mesh_yaml(n: int, *, vertex: str = "[{x}.5, {y}.25, 6{z:02d}.0]", tail: str = "      albedo: 0.5\n") -> str:
    """A grid mesh of ``n`` vertices written inline, over several lines, as a person would paste it."""
    verts = [vertex.format(x=i % 100, y=i // 100, z=i % 97) for i in range(n)]
    tris = [f"[{i}, {i + 1}, {i + 2}]" for i in range(n - 2)]
    rows = ",\n        ".join(", ".join(verts[i:i + 8]) for i in range(0, n, 8))
    return ("sequence: {kind: gray_phase}\nvirtual_rig:\n  scene:\n    - type: mesh\n"
            f"      vertices_mm: [{rows}]\n      triangles: [{', '.join(tris)}]\n{tail}")


def yaml_only(text: str) -> AppConfig:
    """What the plain YAML reading makes of ``text`` (the reference)."""
    return AppConfig.model_validate(yaml.load(text, Loader=yaml.CSafeLoader))


def test_a_large_inline_mesh_reads_as_yaml_reads_it() -> None:
    text = mesh_yaml(6000)
    short, lifted = _lift_numeric_lists(text)
    assert len(lifted) == 2 and len(short) < 1000  # both lists were lifted
    assert short.count("\n") == text.count("\n")  # line numbers kept
    cfg = parse_config(text, "mesh.yaml")
    assert cfg == yaml_only(text)
    mesh = cfg.virtual_rig.scene[0]
    assert mesh.type == "mesh" and len(mesh.vertices_mm) == 6000 and mesh.albedo == 0.5
    assert mesh.vertices_mm[123] == (23.5, 1.25, 626.0) and mesh.triangles[7] == (7, 8, 9)
    assert isinstance(mesh.triangles[0][0], int)


@pytest.mark.parametrize(("vertex", "why"), [
    ("[{x}.5e+1, {y}.25, 600.0]", "an exponent"),
    ("[{x}.5, .{y}, 600.0]", "a leading dot (YAML: float, JSON: invalid)"),
    ("[{x}.5, 1_{y}, 600.0]", "a digit separator"),
    ("[{x}.5, 0{y}, 600.0]", "a leading zero (YAML 1.1: octal)"),
    ("comment", "a comment inside the list"),
])
def test_lists_yaml_reads_otherwise_are_left_to_yaml(vertex: str, why: str) -> None:
    if vertex == "comment":
        text = mesh_yaml(3000).replace("vertices_mm: [", "vertices_mm: [  # pasted from the CAD export\n        ")
    else:
        text = mesh_yaml(3000, vertex=vertex)
    assert len(text) > LIFT_MIN_CHARS
    lifted = _lift_numeric_lists(text)[1]
    assert all(len(v) < 3000 for v, _ in lifted.values()), why  # the vertices stay with YAML (triangles may go)
    try:
        reference: AppConfig | None = yaml_only(text)
    except ValueError:  # the reference refuses it (pydantic): then so must the loader
        reference = None
    if reference is None:
        with pytest.raises(ConfigError):
            parse_config(text, "mesh.yaml")
    else:
        assert parse_config(text, "mesh.yaml") == reference


def _error(text: str) -> str:
    with pytest.raises(ConfigError) as exc:
        parse_config(text, "mesh.yaml")
    return str(exc.value)


@pytest.mark.parametrize("case", ["short_vertex", "misspelt_key_after"])
def test_errors_are_the_yaml_reading_s_with_the_same_lines(case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bad vertex names the list's line; a misspelt key after the list keeps its own line number; both messages
    are word for word what the plain YAML reading gives."""
    if case == "short_vertex":
        text, where = mesh_yaml(3000).replace("[1.5, 0.25, 601.0]", "[1.5, 0.25]"), "mesh.yaml:5: "
        words = "virtual_rig.scene.0.vertices_mm.1"
    else:
        text = mesh_yaml(3000, tail="      albedoo: 0.5\n")
        where, words = f"mesh.yaml:{len(text.splitlines())}: ", "virtual_rig.scene.0.albedoo = 0.5: unknown key"
    assert _lift_numeric_lists(text)[1]
    fast = _error(text)
    monkeypatch.setattr("appliance.config.loader.LIFT_MIN_CHARS", 1 << 40)
    assert not _lift_numeric_lists(text)[1]
    assert fast == _error(text)
    assert fast.startswith(where + words), fast[:200]


def test_a_placeholder_inside_a_string_falls_back_to_yaml(monkeypatch: pytest.MonkeyPatch) -> None:
    """A numeric list that is only part of a plain scalar (YAML: one string) is read as YAML reads it."""
    numbers = ", ".join(f"[{i}, {i}]" for i in range(9000))
    text = f"sequence: {{kind: gray_phase}}\nserial: SN,[{numbers}]\n"
    assert _lift_numeric_lists(text)[1]  # lifted, but the placeholder lands inside the string ...
    fast = _error(text)
    assert "__scan3d_inline_list" not in fast and fast.startswith("mesh.yaml:2: serial = "), fast[:200]
    monkeypatch.setattr("appliance.config.loader.LIFT_MIN_CHARS", 1 << 40)
    assert fast == _error(text)  # ... so the text is read as it is


def test_validate_config_reads_a_big_inline_mesh_and_says_to_use_a_file(tmp_path: Path,
                                                                          caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "appliance.yaml"
    path.write_text(mesh_yaml(40_000))
    assert path.stat().st_size > 1024 * 1024
    out = io.StringIO()
    with caplog.at_level(logging.WARNING), contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = cli.main(["validate-config", str(path)])
    assert rc == 0 and ": valid." in out.getvalue(), out.getvalue()
    notes = [r.getMessage() for r in caplog.records if "inline mesh" in r.getMessage()]
    assert len(notes) == 1 and "40000 vertices" in notes[0] and "virtual_rig.scene.0.path" in notes[0], notes


def test_a_small_inline_mesh_gets_no_note(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        cfg = parse_config(mesh_yaml(500), "small.yaml")
    assert len(cfg.virtual_rig.scene[0].vertices_mm) == 500  # type: ignore[union-attr]
    assert not [r for r in caplog.records if "inline mesh" in r.getMessage()]
    assert np.asarray(cfg.virtual_rig.scene[0].vertices_mm).shape == (500, 3)  # type: ignore[union-attr]
