"""Sequence model, generators, projector images and manifest round trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.errors import ManifestError, PatternError
from appliance.patterns import (
    BlackFrame,
    GrayFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
    gray_bits_needed,
    gray_code_frames,
    gray_code_sequence,
    gray_phase_sequence,
    read_manifest,
    render_frame,
    write_manifest,
)
from appliance.patterns.render import frame_profile


@pytest.mark.parametrize("size,stripe,bits", [(1280, 1, 11), (1024, 1, 10), (1920, 100, 5), (1080, 100, 4),
                                              (800, 8, 7), (2, 1, 1), (1, 1, 1)])
def test_bits_needed(size: int, stripe: int, bits: int) -> None:
    assert gray_bits_needed(size, stripe) == bits


@pytest.mark.parametrize("stripe", [1, 3, 8])
def test_gray_images_decode_to_stripe_index(stripe: int) -> None:
    size = 300
    frames = gray_code_frames(size, "x", stripe=stripe, inverses=True)
    assert len(frames) == 2 * gray_bits_needed(size, stripe)
    # decode the projector images themselves: every column gets floor(c / stripe)
    code = np.zeros(size, np.int64)
    for f in frames:
        assert isinstance(f, GrayFrame)
        if f.inverted:
            continue
        bit = frame_profile(f, size) > 0.5
        inv = frame_profile(GrayFrame("x", f.bit, True, stripe), size) > 0.5
        assert np.all(bit != inv)
        code |= bit.astype(np.int64) << f.bit
    binary = code.copy()
    shift = code >> 1
    while shift.any():
        binary ^= shift
        shift >>= 1
    assert np.array_equal(binary, np.arange(size) // stripe)
    # adjacent stripes differ in exactly one bit (the Gray property)
    diff = code[1:] ^ code[:-1]
    assert set(np.unique([bin(int(d)).count("1") for d in diff])) <= {0, 1}


def test_phase_profile_matches_manifest_definition() -> None:
    f = PhaseFrame("y", period=16.0, step=1, steps=4, offset=0.3)
    c = np.arange(64)
    expected = 0.5 * (1 + np.cos(2 * np.pi * c / 16 + 0.3 + 2 * np.pi / 4))
    np.testing.assert_allclose(frame_profile(f, 64), expected)
    img = render_frame(f, 20, 64)
    assert img.shape == (64, 20) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[:, 0], np.rint(expected * 255).astype(np.uint8))


def test_gray_phase_sequence_uses_half_period_stripes() -> None:
    seq = gray_phase_sequence(1280, 800, "xy", period=16, steps=4)
    grays = [f for f in seq if isinstance(f, GrayFrame)]
    assert {f.stripe for f in grays} == {8}
    assert {f.bit for f in grays if f.axis == "x"} == set(range(gray_bits_needed(1280, 8)))
    assert sum(isinstance(f, PhaseFrame) for f in seq) == 8
    assert isinstance(seq.frames[0], WhiteFrame) and isinstance(seq.frames[1], BlackFrame)
    with pytest.raises(PatternError, match="period"):
        gray_phase_sequence(1280, 800, period=15)


def test_invalid_frames_are_refused() -> None:
    with pytest.raises(PatternError, match="steps"):
        PhaseFrame("x", 16, 0, 2)
    with pytest.raises(PatternError, match="axis"):
        GrayFrame("z", 1)  # type: ignore[arg-type]
    with pytest.raises(PatternError, match="stripe"):
        GrayFrame("x", 1, stripe=0)


def test_manifest_round_trip_images(tmp_path: Path) -> None:
    import cv2

    seq = gray_code_sequence(64, 32, "xy")
    names = []
    for i, f in enumerate(seq.frames):
        names.append(f"img/f{i:02d}.png")
        (tmp_path / "img").mkdir(exist_ok=True)
        cv2.imwrite(str(tmp_path / names[-1]), render_frame(f, 64, 32))
    path = write_manifest(tmp_path / "m.yaml", seq, ["cam0"], images={"cam0": names})
    man = read_manifest(path)
    assert man.sequence == seq
    stack = man.load_stack("cam0")
    assert stack.shape == (len(seq), 32, 64)
    np.testing.assert_array_equal(stack[5], render_frame(seq.frames[5], 64, 32))


def test_manifest_round_trip_stacks(tmp_path: Path) -> None:
    seq = gray_phase_sequence(64, 32, "x", period=8, steps=3)
    stack = np.stack([render_frame(f, 64, 32) for f in seq.frames])
    np.save(tmp_path / "cam1.npy", stack)
    path = write_manifest(tmp_path / "m.yaml", seq, ["cam1"], stacks={"cam1": "cam1.npy"})
    man = read_manifest(path)
    assert man.sequence == seq
    np.testing.assert_array_equal(man.load_stack("cam1"), stack)


def test_manifest_errors_name_the_problem(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("projector: {width: 64, height: 32}\ncameras: [cam0]\nframes:\n"
                 "  - {pattern: gray, axis: q, bit: 0, images: {cam0: a.png}}\n")
    with pytest.raises(ManifestError, match=r"frames\[0\].*axis = 'q'"):
        read_manifest(p)
    p.write_text("projector: {width: 64, height: 32}\ncameras: [cam0]\nframes:\n"
                 "  - {pattern: white, images: {cam0: missing.png}}\n")
    with pytest.raises(ManifestError, match=r"missing\.png"):
        read_manifest(p).load_stack("cam0")
    p.write_text("projector: {width: 64, height: 32}\ncameras: [cam0]\nframes:\n"
                 "  - {pattern: white, images: {cam1: a.png}}\n")
    with pytest.raises(ManifestError, match="no image for camera 'cam0'"):
        read_manifest(p)


def test_unknown_frame_kinds_are_kept(tmp_path: Path) -> None:
    p = tmp_path / "m.yaml"
    p.write_text("projector: {width: 64, height: 32}\ncameras: [c]\nstacks: {c: s.npy}\nframes:\n"
                 "  - {pattern: white}\n  - {pattern: dots, density: 3}\n")
    man = read_manifest(p)
    assert man.sequence.frames[1].pattern == "dots"
    assert Sequence(64, 32, man.sequence.frames).describe().startswith("64x32, 2 frames")
