"""Property-based fuzz of the file loaders (issue 28): whatever a configuration, manifest or calibration file
holds, loading it either succeeds or raises one ApplianceError; never another exception, never a hang.

Each property runs a bounded number of examples with a per-example deadline; the whole file stays well
under a minute on the 2-core test machine.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.config import load_config, parse_config
from appliance.errors import ApplianceError
from appliance.geometry.calibration_file import Calibration, read_calibration, write_calibration
from appliance.geometry.camera import CameraModel
from appliance.patterns.manifest import read_manifest

REPO = Path(__file__).resolve().parents[2]
SHIPPED = (REPO / "config" / "appliance.yaml").read_text()

FUZZ = settings(max_examples=60, deadline=timedelta(seconds=3), derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

# scalars as YAML gives them, the awkward ones included
SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.sampled_from(["x", "y", "gray", "phase", "white", "sim", ".inf", "-.nan", "1e30", "0x10", "~", "yes"]),
)
CONFIG_KEYS = st.sampled_from(["sequence", "steps", "periods_px", "kind", "axes", "reconstruction", "mode",
                               "virtual_rig", "imaging", "seed", "camera_blur_px", "cameras", "cam0", "width",
                               "height", "focal_px", "output", "directory", "service", "type", "scene",
                               "bit_depth", "exposures_us", "inverses", "zzz"])


def _tree(keys: st.SearchStrategy[str]) -> st.SearchStrategy[Any]:
    return st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                         st.dictionaries(keys, inner, max_size=4)),
                        max_leaves=20)


@pytest.fixture(scope="module")
def folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="fuzz") as d:
        yield Path(d)


def _mutate(text: str, data: st.DataObject) -> str:
    """``text`` with a few characters replaced, inserted or removed."""
    chars = list(text)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, max(len(chars) - 1, 0)))
        op = data.draw(st.sampled_from(["replace", "insert", "delete"]))
        c = data.draw(st.sampled_from(list(":-[]{}#&*!|>'\"\t\n 0123456789.eE%@`\x00\ufeff")))
        if op == "replace" and chars:
            chars[i] = c
        elif op == "insert":
            chars.insert(i, c)
        elif chars:
            del chars[i]
    return "".join(chars)


@FUZZ
@given(doc=st.dictionaries(CONFIG_KEYS, _tree(CONFIG_KEYS), max_size=5))
def test_any_config_document_is_valid_or_one_config_error(doc: dict[str, Any]) -> None:
    text = yaml.safe_dump(doc, allow_unicode=True)
    try:
        parse_config(text, "fuzz.yaml")
    except ApplianceError as exc:
        assert str(exc).startswith("fuzz.yaml"), str(exc)


@FUZZ
@given(data=st.data())
def test_a_damaged_shipped_config_is_valid_or_one_config_error(folder: Path, data: st.DataObject) -> None:
    path = folder / "appliance.yaml"
    raw = _mutate(SHIPPED, data).encode("utf-8", "surrogatepass")
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw)))]  # cut short
    path.write_bytes(raw)
    try:
        load_config(path)
    except ApplianceError as exc:
        assert str(exc).startswith(str(path)), str(exc)


MANIFEST_KEYS = st.sampled_from(["pattern", "axis", "bit", "inverted", "stripe", "period", "step", "steps",
                                 "offset", "images", "exposure_us", "intensity", "cam0", "width", "height"])


def _frame() -> st.SearchStrategy[dict[str, Any]]:
    value = st.one_of(SCALARS, st.integers(0, 12), st.sampled_from(["x", "y"]))
    return st.fixed_dictionaries(
        {"pattern": st.sampled_from(["gray", "phase", "white", "black", "other", 3, None])},
        optional={k: value for k in ["axis", "bit", "inverted", "stripe", "period", "step", "steps", "offset",
                                     "exposure_us", "intensity"]} | {"images": st.just({"cam0": "f.png"})},
    )


@FUZZ
@given(projector=st.dictionaries(st.sampled_from(["width", "height", "depth"]), SCALARS, max_size=3),
       frames=st.one_of(st.lists(_frame(), max_size=6), _tree(MANIFEST_KEYS)),
       extra=st.dictionaries(st.sampled_from(["bit_depth", "stacks", "zzz"]), SCALARS, max_size=2))
def test_any_manifest_is_read_or_one_manifest_error(folder: Path, projector: dict[str, Any], frames: Any,
                                                    extra: dict[str, Any]) -> None:
    path = folder / "scan.yaml"
    doc = {"projector": projector, "cameras": ["cam0"], "frames": frames, **extra}
    path.write_text(yaml.safe_dump(doc, allow_unicode=True))
    try:
        man = read_manifest(path)
    except ApplianceError as exc:
        assert str(exc).startswith(str(path)), str(exc)
    else:
        assert all(math.isfinite(getattr(f, "period", 1.0)) for f in man.sequence.frames)


def _good_calibration(folder: Path) -> str:
    k = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    devices = {"cam0": CameraModel("cam0", k, np.zeros(5), 640, 480, np.eye(3), np.zeros(3), 0.2),
               "projector": CameraModel("projector", k, np.zeros(5), 640, 480, np.eye(3),
                                        np.array([100.0, 0, 0]), 0.3)}
    path = folder / "good_calibration.yaml"
    write_calibration(path, Calibration(devices))
    return path.read_text()


@FUZZ
@given(data=st.data())
def test_a_damaged_calibration_is_read_or_one_calibration_error(folder: Path, data: st.DataObject) -> None:
    good = _good_calibration(folder)
    tokens = good.split(" ")
    for _ in range(data.draw(st.integers(1, 3))):  # whole tokens swapped for awkward ones
        i = data.draw(st.integers(0, len(tokens) - 1))
        tokens[i] = data.draw(st.sampled_from(["u", "s", ".nan", ".inf", "-1", "1e308", '"bad"', "[]", "{}",
                                               "0", "3", "d", "%YAML:1.0\n", "~", "x:", "- 1"]))
    text = " ".join(tokens)
    if data.draw(st.booleans()):
        text = _mutate(text, data)
    path = folder / "calibration.yaml"
    path.write_text(text, errors="surrogatepass")
    try:
        read_calibration(path, (640, 480))
    except ApplianceError as exc:
        assert str(exc).startswith(str(path)), str(exc)
