"""XOR codes (Gupta et al. 2011): generation, projector images, configuration and manifest round trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.errors import ManifestError, PatternError
from appliance.patterns import GrayFrame, gray_code_frames, gray_phase_sequence, read_manifest, write_manifest
from appliance.patterns.from_config import build_sequence
from appliance.patterns.render import frame_profile


def _gray(size: int, stripe: int) -> np.ndarray:
    code = np.arange(size) // stripe
    return code ^ (code >> 1)


@pytest.mark.parametrize(("stripe", "base"), [(1, 0), (8, 0), (8, 1), (3, 2)])
def test_xor_frames_show_the_bit_xor_the_base_and_keep_its_fine_stripes(stripe: int, base: int) -> None:
    size = 640
    frames = gray_code_frames(size, "x", stripe=stripe, xor_base=base)
    plain = gray_code_frames(size, "x", stripe=stripe)
    assert len(frames) == len(plain)  # the same frame count as the plain Gray code
    gray = _gray(size, stripe)
    base_run = stripe << (base + 1)  # the width of the base bit's stripes (projector px)
    for f in frames:
        assert isinstance(f, GrayFrame)
        want = ((gray >> f.bit) & 1) ^ (((gray >> base) & 1) if f.bit > base else 0)
        got = frame_profile(f, size)
        np.testing.assert_array_equal(got, 1 - want if f.inverted else want)
        assert f.xor_with == (base if f.bit > base else None)
        if f.bit >= base:
            # every pattern at or above the base changes at least every base stripe: none is coarse
            runs = np.diff(np.flatnonzero(np.diff(got) != 0))
            assert runs.max() <= base_run


def test_xor_base_must_leave_a_coarser_bit() -> None:
    with pytest.raises(PatternError, match=r"xor base bit 7: must be in 0\.\.5"):
        gray_code_frames(1024, "x", stripe=8, xor_base=7)  # 7 bits
    with pytest.raises(PatternError, match="xor_with = 3: must be another bit"):
        GrayFrame("x", 3, xor_with=3)


def test_configuration_selects_xor_codes() -> None:
    text = "sequence: {kind: gray_phase, axes: xy, periods_px: [16], code: xor, xor_base_bit: 1}\n"
    seq = build_sequence(parse_config(text, "a.yaml").sequence, 1280, 800)
    plain_cfg = parse_config("sequence: {kind: gray_phase, periods_px: [16]}\n", "b.yaml")
    plain = build_sequence(plain_cfg.sequence, 1280, 800)
    grays = [f for f in seq.frames if isinstance(f, GrayFrame)]
    assert {f.xor_with for f in grays if f.bit > 1} == {1}
    assert all(f.xor_with is None for f in grays if f.bit <= 1)
    assert {f.axis for f in grays} == {"x", "y"}
    assert "xor bit 1" in seq.describe()
    assert len(build_sequence(parse_config(text.replace("xy", "x"), "c.yaml").sequence, 1280, 800)) == len(plain)
    assert all(f.xor_with is None for f in plain.frames if isinstance(f, GrayFrame))


def test_manifest_round_trips_xor_with(tmp_path: Path) -> None:
    seq = gray_phase_sequence(256, 64, "xy", period=16, xor_base=0)
    stack = np.zeros((len(seq), 8, 8), np.uint8)
    np.save(tmp_path / "c.npy", stack)
    path = write_manifest(tmp_path / "m.yaml", seq, ["cam0"], stacks={"cam0": "c.npy"})
    assert "xor_with: 0" in path.read_text()
    assert read_manifest(path).sequence == seq


def test_manifest_refuses_a_bad_xor_with(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("projector: {width: 64, height: 32}\ncameras: [cam0]\nframes:\n"
                 "  - {pattern: gray, axis: x, bit: 2, xor_with: 2, images: {cam0: a.png}}\n")
    with pytest.raises(ManifestError, match="xor_with = 2: must be another bit"):
        read_manifest(p)
    p.write_text("projector: {width: 64, height: 32}\ncameras: [cam0]\nframes:\n"
                 "  - {pattern: gray, axis: x, bit: 2, xor_with: fine, images: {cam0: a.png}}\n")
    with pytest.raises(ManifestError, match="xor_with = 'fine': must be a whole number"):
        read_manifest(p)
