"""Finest resolvable bit: a projector finer than the camera decodes to the finest Gray bit that has contrast.

The virtual rig renders a 3840-px-wide projector seen by a 1280-px camera (about three projector columns per
camera pixel; camera blur sigma 2 px, about 6 projector px): the finest Gray bits blur to grey. Every decoded pixel must
then lie inside its (coarser) effective stripe of the exact projector coordinate (ground truth), instead of
every pixel being rejected.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.patterns.sequence import gray_code_sequence, gray_phase_sequence
from appliance.reconstruct.decode import DecodeParams, StreamingDecoder, decode, stripe_widths
from appliance.sim.rig import VirtualRig

RIG = """
virtual_rig:
  imaging: {camera_blur_px: 2.0}
  projector: {width: 3840, height: 400, focal_px: 4800, position_mm: [175, 0, 0], look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 1280, height: 96, focal_px: 1500, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
"""


@pytest.fixture(scope="module")
def rig() -> VirtualRig:
    return VirtualRig(parse_config(RIG, "rig.yaml").virtual_rig)


def test_projector_finer_than_the_camera_decodes_to_coarser_stripes(rig: VirtualRig) -> None:
    seq = gray_code_sequence(3840, 400, "x", stripe=1)
    frames = rig.render(seq, "cam0")
    gt = rig.ground_truth("cam0")
    lit = gt.lit & np.isfinite(gt.proj_uv[..., 0])

    strict = decode(frames, seq, DecodeParams(finest_bit=False))
    maps = decode(frames, seq)
    assert maps.levels is not None
    print(f"lit {lit.mean():.1%}: decoded at full resolution only {strict.mask.mean():.1%}, "
          f"to the finest resolvable bit {maps.mask.mean():.1%}; widths {stripe_widths(maps, seq)}")
    assert strict.mask.sum() < 0.05 * lit.sum()  # the finest stripes are not resolved: all-or-nothing fails
    assert maps.mask.sum() >= 0.8 * lit.sum()
    assert (maps.mask & ~lit).sum() <= 0.01 * maps.mask.sum()  # blur spills a little past the lit area

    # each pixel's coordinate is the centre of its effective stripe, and the truth lies inside it (plus
    # the blur of a pixel footprint, ~3 projector px, at the stripe's ends)
    good = maps.mask & lit
    lev = maps.levels[0][good].astype(np.int64)
    width = (1 << lev).astype(np.float64)
    err = np.abs(maps.u[good] - gt.proj_uv[..., 0][good])
    inside = err <= width / 2 + 2.0
    assert inside.mean() >= 0.99
    assert 4 <= np.median(width) <= 8  # coarser, but only as much as the optics need

    widths = stripe_widths(maps, seq)["x"]
    assert abs(sum(widths.values()) - 1.0) < 1e-9 and max(widths, key=widths.__getitem__) >= 4.0

    # streaming gives the same bits
    dec = StreamingDecoder(seq, maps.shape, frames.dtype)
    for i in range(len(seq)):
        dec.push(i, frames[i])
    stream = dec.finish()
    np.testing.assert_array_equal(stream.mask, maps.mask)
    assert np.array_equal(stream.u, maps.u, equal_nan=True)
    assert stream.levels is not None and np.array_equal(stream.levels, maps.levels)


def test_phase_sequence_keeps_full_resolution_where_it_resolves(rig: VirtualRig) -> None:
    """Gray + phase with a period the camera resolves: every pixel unwraps at full Gray resolution (level 0),
    and the phase gives sub-pixel coordinates."""
    seq = gray_phase_sequence(3840, 400, "x", period=48)
    frames = rig.render(seq, "cam0")
    gt = rig.ground_truth("cam0")
    maps = decode(frames, seq)
    assert maps.levels is not None
    assert maps.mask.mean() > 0.8
    assert np.all(maps.levels[0][maps.mask] == 0)
    err = np.abs(maps.u[maps.mask] - gt.proj_uv[..., 0][maps.mask])
    assert np.median(err) < 0.5
    assert stripe_widths(maps, seq) == {"x": {0.0: 1.0}}


def test_a_finer_period_without_modulation_falls_back_to_the_coarser_one(rig: VirtualRig) -> None:
    """Periods 96 and 8 projector px: the blur (~6 projector px) wipes out the 8-px fringes; pixels keep the
    96-px period's sub-pixel coordinate instead of being rejected."""
    seq = gray_phase_sequence(3840, 400, "x", periods=(96, 8))
    frames = rig.render(seq, "cam0")
    gt = rig.ground_truth("cam0")
    lit = gt.lit & np.isfinite(gt.proj_uv[..., 0])
    strict = decode(frames, seq, DecodeParams(finest_bit=False))
    maps = decode(frames, seq)
    print(f"lit {lit.mean():.1%}: decoded with both periods {strict.mask.mean():.1%}, "
          f"with the finest that has modulation {maps.mask.mean():.1%}")
    assert strict.mask.sum() < 0.05 * lit.sum()
    assert maps.mask.sum() >= 0.9 * lit.sum()
    good = maps.mask & lit
    err = np.abs(maps.u[good] - gt.proj_uv[..., 0][good])
    assert np.median(err) < 1.0 and np.percentile(err, 99) < 5.0


def _level_rule(weak: int, tol: int, nbits: int) -> tuple[int, bool]:
    """The rule, written plainly: <= tol weak bits keeps full resolution; otherwise drop the contiguous weak
    bits from bit 0 and allow <= tol weak bits above them."""
    if bin(weak).count("1") <= tol:
        return 0, True
    f = 0
    while f < nbits and weak >> f & 1:
        f += 1
    return f, f < nbits and bin(weak >> f).count("1") <= tol


@pytest.mark.parametrize("tol", [0, 1])
def test_level_rule_for_every_weak_bit_pattern(tol: int) -> None:
    from appliance.reconstruct import _decode_kernels as k

    nbits = 11
    weak = np.arange(1 << nbits, dtype=np.uint32)
    fl = np.empty_like(weak)
    ok = np.empty(weak.shape, np.bool_)
    k._gray_level(weak, tol, nbits, True, fl, ok)
    want = [_level_rule(int(w), tol, nbits) for w in weak]
    assert [int(f) for f, good in zip(fl, ok, strict=True) if good] == [f for f, good in want if good]
    np.testing.assert_array_equal(ok, [good for _, good in want])
    k._gray_level(weak, tol, nbits, False, fl, ok)  # finest_bit off: full resolution or nothing
    np.testing.assert_array_equal(ok, [bin(int(w)).count("1") <= tol for w in weak])
