"""Structured-light decoding against synthetic renderings with known projector coordinates."""

from __future__ import annotations

import importlib

import numpy as np
import numpy.typing as npt
import pytest
from decode_render import H, W, render
from decode_render import grid as _grid
from decode_render import u_true as _u_true
from decode_render import v_true as _v_true

from appliance.errors import DecodeError, PatternError
from appliance.patterns.sequence import (
    BlackFrame,
    Frame,
    GrayFrame,
    OtherFrame,
    Sequence,
    WhiteFrame,
    gray_code_frames,
    gray_code_sequence,
    gray_phase_sequence,
    phase_shift_frames,
)
from appliance.reconstruct.decode import (
    DecodedMaps,
    DecodeParams,
    StreamingDecoder,
    decode,
    empty_maps,
    plan_decode,
)


def _same(a: DecodedMaps, b: DecodedMaps) -> bool:
    return all(
        np.array_equal(getattr(a, k).view(np.uint8), getattr(b, k).view(np.uint8))
        for k in ("u", "v", "mask", "quality", "reason", "fringe")
    )


def _stream(
    seq: Sequence, frames: npt.NDArray[np.generic], seed: int, params: DecodeParams, borrow: bool = False
) -> DecodedMaps:
    dec = StreamingDecoder(seq, (H, W), frames.dtype, params, borrow_frames=borrow)
    for i in np.random.default_rng(seed).permutation(len(seq)):
        dec.push(int(i), frames[i])
    return dec.finish()


# --------------------------------------------------------------------------------------------------
# Accuracy against ground truth
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stripe", [1, 4])
def test_gray_only_gives_stripe_centres_within_half_a_stripe(stripe: int) -> None:
    seq = gray_code_sequence(256, 128, "xy", stripe=stripe)
    maps = decode(render(seq), seq)
    xx, yy = _grid()
    assert maps.mask.mean() > 0.97
    for got, truth in ((maps.u, _u_true(xx, yy)), (maps.v, _v_true(xx, yy))):
        ok = np.isfinite(got)
        # stripe centres: (k + 0.5) * stripe - 0.5, integers for stripe 1
        np.testing.assert_array_equal(((got[ok] + 0.5) / stripe - 0.5) % 1.0, 0.0)
        err = np.abs(got[ok] - truth[ok])
        # a pixel sees ~2.3 projector pixels: on a stripe edge it may take the neighbouring stripe
        assert np.mean(err <= stripe / 2 + 0.5) > 0.97
        assert err.max() <= stripe / 2 + 1.5


@pytest.mark.parametrize(("period", "stripe"), [(16, 8), (16, 16), (20, 10)])
def test_gray_phase_is_subpixel_on_both_axes(period: int, stripe: int) -> None:
    frames: list[Frame] = [WhiteFrame(), BlackFrame()]
    for axis, size in (("x", 320), ("y", 160)):
        frames += gray_code_frames(size, axis, stripe=stripe)  # type: ignore[arg-type]
        frames += phase_shift_frames(axis, period, 4)  # type: ignore[arg-type]
    seq = Sequence(320, 160, tuple(frames))
    maps = decode(render(seq, noise=1.5), seq)
    xx, yy = _grid()
    assert maps.mask.mean() > 0.99
    for got, truth in ((maps.u, _u_true(xx, yy)), (maps.v, _v_true(xx, yy))):
        err = (got - truth)[maps.mask]
        assert np.sqrt(np.mean(err**2)) < 0.1
        assert np.abs(err).max() < 0.5  # no period jumps
    assert np.all(maps.quality[maps.mask] > 20.0)
    assert np.all(maps.quality[~maps.mask] == 0.0)


def test_three_step_phase_with_offset() -> None:
    # the phaseshift_graycode_objects layout: 3 steps, offset -2π/3, Gray stripe = period
    frames: list[Frame] = [*gray_code_frames(320, "x", stripe=20)]
    frames += phase_shift_frames("x", 20, 3, offset=-2 * np.pi / 3)  # type: ignore[arg-type]
    seq = Sequence(320, 160, (WhiteFrame(), BlackFrame(), *frames))
    maps = decode(render(seq, noise=0.5), seq)
    xx, yy = _grid()
    err = (maps.u - _u_true(xx, yy))[maps.mask]
    assert maps.mask.mean() > 0.99
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert np.all(np.isnan(maps.v))


def test_multi_period_coarse_to_fine() -> None:
    seq = gray_phase_sequence(512, 256, "xy", periods=(64, 16))
    plan = plan_decode(seq)
    assert [(p.period, p.source) for p in plan.phase if p.axis == "x"] == [(64, "gray"), (16, "period 64")]
    assert {g.stripe for g in plan.gray} == {32}
    maps = decode(render(seq, noise=1.5), seq)
    xx, yy = _grid()
    assert maps.mask.mean() > 0.99
    for got, truth in ((maps.u, _u_true(xx, yy)), (maps.v, _v_true(xx, yy))):
        err = (got - truth)[maps.mask]
        assert np.sqrt(np.mean(err**2)) < 0.1
        assert np.abs(err).max() < 0.5


def test_unit_frequency_phase_unwraps_without_gray() -> None:
    # a period covering the whole axis needs no Gray code; it unwraps the finer one
    frames = (WhiteFrame(), BlackFrame(), *phase_shift_frames("x", 320, 4), *phase_shift_frames("x", 32, 4))
    seq = Sequence(300, 160, frames)
    plan = plan_decode(seq)
    assert [p.source for p in plan.phase] == ["axis", "period 320"]
    maps = decode(render(seq, noise=0.5), seq)
    xx, yy = _grid()
    err = (maps.u - _u_true(xx, yy))[maps.mask]
    assert maps.mask.mean() > 0.99
    assert np.sqrt(np.mean(err**2)) < 0.1


def test_uint16_data() -> None:
    seq = gray_phase_sequence(512, 256, "xy", periods=(64, 16))
    frames = render(seq, amp=180.0 * 256, ambient=15.0 * 256, noise=256.0, dtype=np.uint16)
    maps = decode(frames, seq)
    xx, yy = _grid()
    err = (maps.u - _u_true(xx, yy))[maps.mask]
    assert maps.mask.mean() > 0.99
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert maps.quality[maps.mask].min() > 20.0 * 256  # quality in DN of the data


def test_shadow_is_masked_and_threshold_adapts() -> None:
    seq = gray_phase_sequence(320, 160, "x", period=16)
    shadow = (slice(10, 30), slice(5, 25))
    xx, yy = _grid()
    for ambient, noise in ((10.0, 1.0), (60.0, 4.0)):  # dark room; bright ambient light, more noise
        maps = decode(render(seq, ambient=ambient, noise=noise, shadow=shadow), seq)
        assert not maps.mask[shadow].any()
        assert np.isnan(maps.u[shadow]).all()
        lit = np.ones((H, W), bool)
        lit[shadow] = False
        assert maps.mask[lit].mean() > 0.99
        err = (maps.u - _u_true(xx, yy))[maps.mask]
        assert np.sqrt(np.mean(err**2)) < 0.15


def test_low_contrast_pattern_is_rejected() -> None:
    # a region lit by white but where the fringes are washed out (e.g. strong subsurface scattering)
    seq = gray_phase_sequence(320, 160, "x", period=16)
    frames = render(seq).astype(np.float64)
    white = frames[0, 5:20, 5:20].copy()
    black = frames[1, 5:20, 5:20].copy()
    frames[2:, 5:20, 5:20] = (white + black) / 2 + 0.04 * (frames[2:, 5:20, 5:20] - (white + black) / 2)
    maps = decode(np.rint(frames).astype(np.uint8), seq)
    assert not maps.mask[5:20, 5:20].any()
    assert maps.mask[25:, 25:].mean() > 0.99


def test_without_white_black_and_without_inverses() -> None:
    xx, yy = _grid()
    no_wb = Sequence(320, 160, (*gray_code_frames(320, "x", stripe=8), *phase_shift_frames("x", 16, 4)))
    maps = decode(render(no_wb), no_wb)
    err = (maps.u - _u_true(xx, yy))[maps.mask]
    assert maps.mask.mean() > 0.99 and np.sqrt(np.mean(err**2)) < 0.1
    no_inv = Sequence(
        320, 160, (WhiteFrame(), BlackFrame(), *gray_code_frames(320, "x", stripe=8, inverses=False),
                   *phase_shift_frames("x", 16, 4)),
    )  # fmt: skip
    maps = decode(render(no_inv), no_inv)
    err = (maps.u - _u_true(xx, yy))[maps.mask]
    assert maps.mask.mean() > 0.99 and np.sqrt(np.mean(err**2)) < 0.1


def test_frame_order_does_not_matter() -> None:
    seq = gray_phase_sequence(320, 160, "xy", period=16)
    frames = render(seq)
    order = np.random.default_rng(3).permutation(len(seq))
    shuffled = Sequence(seq.width, seq.height, tuple(seq.frames[i] for i in order))
    assert _same(decode(frames, seq), decode(frames[order], shuffled))


def test_decode_into_preallocated_outputs() -> None:
    seq = gray_phase_sequence(320, 160, "xy", period=16)
    frames = render(seq, shadow=(slice(0, 12), slice(0, 20)))  # unlit pixels at the start of rows
    frames[:, 30:33] = frames[-1, 30:33]  # and whole unlit rows (every frame black there)
    out = empty_maps((H, W))
    assert out.levels is not None
    out.u[...], out.v[...], out.mask[...], out.quality[...], out.levels[...] = 7.0, 7.0, True, 3.0, 9  # stale
    got = decode(frames, plan_decode(seq), out=out)
    assert got is out
    fresh = decode(frames, seq)
    assert _same(out, fresh)
    assert fresh.levels is not None and np.array_equal(out.levels, fresh.levels)
    assert not out.mask[:12, :20].any() and not out.mask[30:33].any()
    assert np.isnan(out.u[30:33]).all() and not out.quality[30:33].any() and not out.levels[:, 30:33].any()
    with pytest.raises(DecodeError, match=r"out\.u"):
        decode(frames, seq, out=empty_maps((H, W + 1)))


# --------------------------------------------------------------------------------------------------
# Refusals and the plan
# --------------------------------------------------------------------------------------------------


def test_missing_gray_bit_is_named() -> None:
    frames = [
        f for f in gray_code_sequence(1920, 1080, "x").frames if not (isinstance(f, GrayFrame) and f.bit == 7)
    ]
    with pytest.raises(PatternError, match=r"gray code axis x: bit 7 is missing \(bits present: 0-6, 8-10"):
        plan_decode(Sequence(1920, 1080, tuple(frames)))


def test_phase_without_unwrapping_source_is_refused() -> None:
    seq = Sequence(320, 160, (WhiteFrame(), BlackFrame(), *phase_shift_frames("x", 16, 4)))
    with pytest.raises(
        PatternError, match=r"phase x period 16: cannot be unwrapped: axis x has no Gray code"
    ):
        plan_decode(seq)
    wide = Sequence(320, 160, (*gray_code_frames(320, "x", stripe=32), *phase_shift_frames("x", 16, 4)))
    with pytest.raises(PatternError, match=r"stripe \(32 px\) is wider than the period"):
        plan_decode(wide)
    ratio = Sequence(4096, 160, (*phase_shift_frames("x", 4096, 4), *phase_shift_frames("x", 8, 4)))
    with pytest.raises(PatternError, match=r"period 8: cannot be unwrapped: the next coarser period 4096"):
        plan_decode(ratio)


def test_missing_phase_step_and_missing_inverse_threshold_are_refused() -> None:
    frames = (*gray_code_frames(320, "x", stripe=8), *phase_shift_frames("x", 16, 4)[:3])
    with pytest.raises(PatternError, match=r"phase x period 16: step\(s\) 3 of 4 missing"):
        plan_decode(Sequence(320, 160, frames))
    no_ref = (*gray_code_frames(320, "x", inverses=False),)
    with pytest.raises(PatternError, match=r"bit \d+ has no inverse frame and the sequence has no white"):
        plan_decode(Sequence(320, 160, no_ref))


def test_ignored_frames_are_listed() -> None:
    seq = gray_code_sequence(320, 160, "x")
    extra = (OtherFrame("checkerboard", (("size", "8"),)), seq.frames[5], WhiteFrame())
    plan = plan_decode(Sequence(320, 160, seq.frames + extra))
    n = len(seq)
    assert plan.axes == ("x",)
    assert any(s.startswith(f"frame {n}: pattern 'checkerboard'") for s in plan.ignored)
    assert any(s.startswith(f"frame {n + 1}: duplicate of frame 5") for s in plan.ignored)
    assert any(s.startswith(f"frame {n + 2}: duplicate of frame 0") for s in plan.ignored)
    frames = render(Sequence(320, 160, seq.frames + extra[1:]))
    frames = np.concatenate([frames[:n], np.zeros((1, H, W), np.uint8), frames[n:]])
    maps = decode(frames, Sequence(320, 160, seq.frames + extra))
    assert maps.ignored == plan.ignored
    assert maps.mask.mean() > 0.97


def test_bad_frames_are_refused() -> None:
    seq = gray_code_sequence(320, 160, "x")
    with pytest.raises(DecodeError, match=r"must be \(20, height, width\)"):
        decode(np.zeros((3, H, W), np.uint8), seq)
    with pytest.raises(DecodeError, match="dtype float32"):
        decode(np.zeros((len(seq), H, W), np.float32), seq)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------------
# Streaming equals batch, bit for bit
# --------------------------------------------------------------------------------------------------


def _sequences() -> list[tuple[str, Sequence]]:
    no_inv = Sequence(
        320, 160, (*gray_code_frames(320, "x", stripe=8, inverses=False), *phase_shift_frames("x", 16, 4),
                   BlackFrame(), WhiteFrame()),
    )  # fmt: skip
    no_wb = Sequence(320, 160, (*gray_code_frames(160, "y", stripe=8), *phase_shift_frames("y", 16, 3, 0.4)))
    return [
        ("gray-only", gray_code_sequence(256, 128, "xy")),
        ("multi-period", gray_phase_sequence(512, 256, "xy", periods=(64, 16))),
        ("no-inverse", no_inv),
        ("no-white-black", no_wb),
    ]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize(("name", "seq"), _sequences())
def test_streaming_equals_batch_bit_for_bit(name: str, seq: Sequence, dtype: type) -> None:
    scale = 1.0 if dtype == np.uint8 else 257.0
    frames = render(seq, amp=180 * scale, ambient=20 * scale, noise=3.0 * scale, dtype=dtype,
                    shadow=(slice(0, 12), slice(0, 12)), seed=7)  # fmt: skip
    params = DecodeParams()
    batch = decode(frames, seq, params)
    assert batch.mask.mean() > 0.8, name
    for seed in (0, 1, 2):
        assert _same(_stream(seq, frames, seed, params), batch), (name, seed)
        # frames kept by reference (a scan's buffer) instead of copied: the same maps
        assert _same(_stream(seq, frames, seed, params, borrow=True), batch), (name, seed, "borrowed")


@pytest.mark.parametrize(("name", "seq"), _sequences()[1:])
def test_integer_phase_sums_equal_float_sums_bit_for_bit(
    name: str, seq: Sequence, monkeypatch: pytest.MonkeyPatch
) -> None:
    """8-bit frames sum their phase steps in int32 (units of the coefficient quantum); the maps must be those of
    the float64 sums, bit for bit (three- and four-step sets, offsets, two periods, with and without white)."""
    dec = importlib.import_module("appliance.reconstruct.decode_batch")  # where decode() looks _int_sums up

    t = plan_decode(seq).tables
    assert dec._int_sums(t, 255), name  # 8-bit: the integer path is the one taken
    assert not dec._int_sums(t, 65535), name  # 16-bit sums could leave int32: float64
    frames = render(seq, amp=180, ambient=20, noise=3.0, shadow=(slice(0, 12), slice(0, 12)), seed=3)
    ints = decode(frames, seq)
    monkeypatch.setattr(dec, "_int_sums", lambda tables, maxval: False)
    floats = decode(frames, seq)
    assert floats.mask.mean() > 0.8, name
    assert _same(ints, floats), name
    assert ints.levels is not None and floats.levels is not None
    assert np.array_equal(ints.levels, floats.levels), name


def test_streaming_reset_and_errors() -> None:
    seq = gray_phase_sequence(320, 160, "x", period=16)
    frames = render(seq)
    dec = StreamingDecoder(seq, (H, W))
    for i in range(len(seq) - 2):
        dec.push(i, frames[i])
    n = len(seq)
    with pytest.raises(
        DecodeError, match=rf"2 frame\(s\) not pushed: {n - 2} \(phase x period 16 step 2/4\), {n - 1}"
    ):
        dec.finish()
    with pytest.raises(DecodeError, match="pushed twice"):
        dec.push(0, frames[0])
    with pytest.raises(DecodeError, match="must be"):
        dec.push(len(seq) - 1, frames[0].astype(np.uint16))
    dec.reset()
    other = render(seq, seed=11, noise=2.0)
    for i in reversed(range(len(seq))):
        dec.push(i, other[i])
    assert _same(dec.finish(), decode(other, seq))
