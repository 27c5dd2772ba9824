"""XOR codes in the batch and the streaming decoder: accuracy against ground truth, bit-identical outputs, the
base-edge rule (every XOR bit flips where the base does) and the plan's checks."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from decode_render import H, W, grid, render, u_true, v_true

from appliance.errors import PatternError
from appliance.patterns.sequence import (
    BlackFrame,
    Frame,
    GrayFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
    gray_code_frames,
    gray_code_sequence,
    gray_phase_sequence,
    phase_shift_frames,
)
from appliance.reconstruct.decode import DecodedMaps, StreamingDecoder, decode, plan_decode
from appliance.reconstruct.types import Reason


def _same(a: DecodedMaps, b: DecodedMaps) -> bool:
    assert a.levels is not None and b.levels is not None
    return all(
        np.array_equal(np.asarray(getattr(a, k)).view(np.uint8), np.asarray(getattr(b, k)).view(np.uint8))
        for k in ("u", "v", "mask", "quality", "reason", "levels")
    )


def _stream(seq: Sequence, frames: npt.NDArray[np.generic], seed: int = 1) -> DecodedMaps:
    dec = StreamingDecoder(seq, (H, W), frames.dtype)
    for i in np.random.default_rng(seed).permutation(len(seq)):
        dec.push(int(i), frames[i])
    return dec.finish()


@pytest.mark.parametrize(("base", "dtype"), [(0, np.uint8), (1, np.uint8), (0, np.uint16)])
def test_xor_gray_phase_is_subpixel_and_streaming_equals_batch(base: int, dtype: type) -> None:
    seq = gray_phase_sequence(512, 256, "xy", period=16, xor_base=base)
    scale = 256.0 if dtype == np.uint16 else 1.0
    frames = render(seq, amp=180.0 * scale, ambient=15.0 * scale, noise=1.5 * scale, dtype=dtype)
    maps = decode(frames, seq)
    xx, yy = grid()
    # pixels within ~0.1 projector px of a base edge (every 16 px per axis here, a pixel seeing 2 px) have no
    # XOR code; the plain Gray code decodes them
    assert maps.mask.mean() > 0.95
    for got, truth in ((maps.u, u_true(xx, yy)), (maps.v, v_true(xx, yy))):
        err = (got - truth)[maps.mask]
        assert np.sqrt(np.mean(err**2)) < 0.1
        assert np.abs(err).max() < 0.5  # no stripe or period jumps
    assert _same(maps, _stream(seq, frames))


def test_xor_gray_only_gives_stripe_centres() -> None:
    seq = gray_code_sequence(256, 128, "xy", stripe=4, xor_base=0)
    frames = render(seq)
    maps = decode(frames, seq)
    xx, yy = grid()
    assert maps.mask.mean() > 0.9  # base edges every 8 px per axis, each pixel seeing ~2 px
    for got, truth in ((maps.u, u_true(xx, yy)), (maps.v, v_true(xx, yy))):
        ok = np.isfinite(got)
        np.testing.assert_array_equal(((got[ok] + 0.5) / 4 - 0.5) % 1.0, 0.0)
        # at a stripe edge (of any bit, the base's included) a pixel may take the neighbouring stripe
        assert np.abs(got[ok] - truth[ok]).max() <= 4 / 2 + 1.5
    assert _same(maps, _stream(seq, frames, seed=5))


def _on_base_edges(offset: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Camera pixels centred ``offset`` projector px right of an edge of Gray bit 0 (stripe 8: edges at
    16 m + 7.5), each seeing 0.83 projector px: the base bit and every XOR bit have (almost) no contrast."""

    def u_of(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        xc = np.floor(x + 0.5)
        return 7.5 + offset + 16.0 * (xc % 30) + (x - xc) + 0.0 * y

    return u_of(*grid()), u_of  # type: ignore[return-value]


@pytest.mark.parametrize("streaming", [False, True])
def test_a_pixel_on_a_base_edge_keeps_its_code_where_the_signs_are_clear(streaming: bool) -> None:
    # 11 of 20 footprint samples right of the edge: the base and XOR contrasts are 0.1 of white - black, below
    # the relative floor (0.15: weak) but above half of it (not faint); the plain Gray code has only bit 0 weak
    truth, u_of = _on_base_edges(0.05)
    for xor in (None, 0):
        seq = gray_phase_sequence(512, 64, "x", period=16, xor_base=xor)
        frames = render(seq, noise=0.5, u_of=u_of, seed=3, sub=20)
        maps = _stream(seq, frames) if streaming else decode(frames, seq)
        assert maps.mask.mean() > 0.97, xor
        assert np.abs(maps.u - truth)[maps.mask].max() < 0.5, xor


@pytest.mark.parametrize("streaming", [False, True])
def test_a_pixel_exactly_on_a_base_edge_is_dropped_not_guessed(streaming: bool) -> None:
    # exactly on the edge the base and every XOR frame equal their inverses: which side each XOR bit belongs
    # to is unknowable, so the pixel is dropped ("weak or inconsistent code"), never decoded to a wrong stripe
    truth, u_of = _on_base_edges(0.0)
    seq = gray_phase_sequence(512, 64, "x", period=16, xor_base=0)
    frames = render(seq, noise=0.5, u_of=u_of, seed=3)
    maps = _stream(seq, frames) if streaming else decode(frames, seq)
    assert maps.reason is not None
    assert maps.mask.mean() < 0.2
    assert np.all(maps.reason[~maps.mask] == Reason.WEAK_CODE)
    assert np.all(np.abs(maps.u - truth)[maps.mask] < 0.5)
    # the plain Gray code decodes those pixels (one weak bit)
    plain = gray_phase_sequence(512, 64, "x", period=16)
    pmaps = decode(render(plain, noise=0.5, u_of=u_of, seed=3), plain)
    assert pmaps.mask.mean() > 0.97


def test_xor_and_plain_give_identical_maps_on_a_clean_render() -> None:
    # away from the base edges the two codes carry the same information: the same coordinates, bit for bit
    plain = gray_phase_sequence(512, 256, "x", period=16)
    xor = gray_phase_sequence(512, 256, "x", period=16, xor_base=0)
    a = decode(render(plain, noise=0.0), plain)
    b = decode(render(xor, noise=0.0), xor)
    same = a.mask & b.mask
    assert same.mean() > 0.97
    np.testing.assert_array_equal(a.u[same], b.u[same])


def test_plan_checks_xor_frames() -> None:
    def seq_of(*grays: Frame) -> Sequence:
        return Sequence(64, 8, (WhiteFrame(), BlackFrame(), *grays))

    good = gray_code_frames(64, "x", stripe=8, xor_base=0)
    plan = plan_decode(seq_of(*good))
    assert (plan.gray[0].xor_base, plan.gray[0].xor_bits) == (0, (1, 2))
    # two bases on one axis
    mixed = [GrayFrame("x", 2, False, 8, 0), GrayFrame("x", 1, False, 8, 0), GrayFrame("x", 0, False, 8, 1)]
    with pytest.raises(PatternError, match=r"XORed with different bits \[0, 1\]"):
        plan_decode(seq_of(*mixed))
    # a base outside the code
    outside = [GrayFrame("x", 2, False, 8, 5), GrayFrame("x", 1, False, 8), GrayFrame("x", 0, False, 8)]
    with pytest.raises(PatternError, match="xor_with = 5: the base bit must be one of the code's 3 bits"):
        plan_decode(seq_of(*outside))
    # pattern and inverse disagree
    odd = [GrayFrame("x", 2, False, 1, 0), GrayFrame("x", 2, True, 1), GrayFrame("x", 1), GrayFrame("x", 0)]
    with pytest.raises(PatternError, match="bit 2's pattern and inverse disagree on xor_with"):
        plan_decode(Sequence(8, 8, (WhiteFrame(), BlackFrame(), *odd)))
    # stripe = period: the edge-aware unwrapping is not available to XOR codes
    edge = (*gray_code_frames(320, "x", stripe=20, xor_base=0), *phase_shift_frames("x", 20, 4))
    with pytest.raises(PatternError, match="XOR-coded Gray code needs a stripe of at most half the period"):
        plan_decode(Sequence(320, 8, (WhiteFrame(), BlackFrame(), *edge)))
    # a plain frame and an XOR frame of one bit: the plain one decodes, the other is said to be unused
    both = seq_of(*gray_code_frames(64, "x", stripe=8), GrayFrame("x", 2, False, 8, 0))
    plan = plan_decode(both)
    assert plan.gray[0].xor_bits == ()
    assert any("xor bit 0" in s and "unused" in s for s in plan.ignored)


@pytest.mark.parametrize("white_black", [True, False])
def test_xor_frames_without_inverses(white_black: bool) -> None:
    # single XOR frames thresholded at (white + black) / 2, or without white and black at the phase set's mean
    seq = gray_phase_sequence(512, 256, "x", period=16, inverses=False, xor_base=0)
    if not white_black:
        seq = Sequence(seq.width, seq.height, tuple(f for f in seq.frames if isinstance(f, GrayFrame | PhaseFrame)))
    frames = render(seq, noise=1.0)
    maps = decode(frames, seq)
    xx, yy = grid()
    assert maps.mask.mean() > 0.9
    err = (maps.u - u_true(xx, yy))[maps.mask]
    assert np.abs(err).max() < 0.5
    assert _same(maps, _stream(seq, frames, seed=9))
