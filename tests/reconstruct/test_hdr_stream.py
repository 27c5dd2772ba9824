"""Multi-exposure captures decoded as they stream in: the same maps as the offline decode of the whole capture.

A bright plane (albedo 0.95) and a black box (0.03) rendered by the virtual rig at three exposures (0.25x, 1x,
4x): the plane clips at 4x, the box is too dark at 0.25x. The frames are pushed in a shuffled order (passes
interleaved).
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.errors import DecodeError
from appliance.patterns.from_config import build_sequence
from appliance.patterns.sequence import Sequence
from appliance.reconstruct.decode import DecodeParams
from appliance.reconstruct.hdr import HdrStreamingDecoder, decode_passes
from appliance.reconstruct.types import Reason
from appliance.sim.rig import VirtualRig

RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 850, position_mm: [180, 0, 0], look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 575, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
  scene:
    - {type: plane, point_mm: [0, 0, 640], normal: [0, 0.1, -1], albedo: 0.95}
    - {type: box, center_mm: [0, 0, 590], size_mm: [120, 90, 40], rotation_deg: [5, 15, 0], albedo: 0.03}
  imaging: {projector_gain_dn: 420, ambient_dn: 6}
"""
EXPOSURES_US = (2500.0, 10000.0, 40000.0)


def _capture() -> tuple[Sequence, list[tuple[float, float]], np.ndarray]:  # type: ignore[type-arg]
    cfg = parse_config(RIG, "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    one = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    stacks = [rig.render(one, "cam0", seed=7 + k, exposure_us=e) for k, e in enumerate(EXPOSURES_US)]
    seq = Sequence(one.width, one.height, one.frames * len(EXPOSURES_US))
    exposures = [(e, 1.0) for e in EXPOSURES_US for _ in one.frames]
    return seq, exposures, np.concatenate(stacks)


def _bytes(m: object) -> list[bytes]:
    return [np.ascontiguousarray(getattr(m, k)).tobytes() for k in ("u", "v", "mask", "quality", "levels", "reason")]


@pytest.mark.parametrize("radius", [1, 4])
def test_streamed_hdr_equals_the_offline_decode(radius: int) -> None:
    # radius 4: the clean rule over a wider square (optics blurrier than the albedo correction handles)
    seq, exposures, stack = _capture()
    params = DecodeParams(clean_radius=radius)
    offline, choice, passes = decode_passes(stack, seq, exposures, params)
    assert [round(lv) for lv, _ in passes] == [2500, 10000, 40000]
    dec = HdrStreamingDecoder(seq, exposures, stack.shape[1:], stack.dtype, params)
    order = np.random.default_rng(3).permutation(len(seq))
    for scan in range(2):  # a second scan through the same buffers after reset()
        dec.reset()
        for i in order:
            dec.push(int(i), stack[i])
        assert dec.missing == []
        streamed = dec.finish()
        assert _bytes(streamed) == _bytes(offline), scan
        assert dec.choice is not None and np.array_equal(dec.choice, choice)
    # the fusion recovers what each pass loses: clipped on the plane at 4x, too dark on the box at 0.25x
    singles = []
    for _lv, idx in passes:
        one, _c, _p = decode_passes(stack[idx], Sequence(seq.width, seq.height, tuple(seq.frames[i] for i in idx)),
                                    [exposures[i] for i in idx], params)  # fmt: skip
        singles.append(one)
    assert singles[2].reason is not None and (singles[2].reason == Reason.SATURATED).mean() > 0.05
    dark = singles[0].reason
    assert dark is not None and ((dark != Reason.DECODED) & (dark != Reason.SATURATED)).mean() > 0.05
    assert streamed.mask.mean() > max(s.mask.mean() for s in singles) + 0.05
    if radius > 1:  # the wider square leaves more pixels beside the clipped plane "next to a clipped pixel"
        narrow, _c, _p = decode_passes(stack, seq, exposures, DecodeParams())
        assert narrow.reason is not None and streamed.reason is not None
        mixed = (streamed.reason == Reason.MIXED).sum()
        assert mixed >= (narrow.reason == Reason.MIXED).sum() and streamed.mask.sum() <= narrow.mask.sum()
        assert not np.array_equal(dec.choice, _c), "the wider square chose no other pass anywhere"


def test_borrowed_frames_are_named_in_capture_indices() -> None:
    seq, exposures, stack = _capture()
    offline, _choice, _passes = decode_passes(stack, seq, exposures, DecodeParams())
    dec = HdrStreamingDecoder(seq, exposures, stack.shape[1:], stack.dtype, borrow_frames=True)
    n = len(seq) // 3
    dec.push(2, stack[2])  # a Gray pattern frame of the first pass: held until its inverse arrives
    dec.push(n + 3, stack[n + 3])  # an inverse of the second pass
    assert dec.borrowed == {2, n + 3}
    dec.push(3, stack[3])
    assert dec.borrowed == {n + 3}
    for i in range(len(seq)):
        if i not in (2, 3, n + 3):
            dec.push(i, stack[i])
    assert dec.borrowed == frozenset()
    assert _bytes(dec.finish()) == _bytes(offline)


def test_missing_frames_are_named() -> None:
    seq, exposures, stack = _capture()
    dec = HdrStreamingDecoder(seq, exposures, stack.shape[1:], stack.dtype)
    for i in range(len(seq) - 1):
        dec.push(i, stack[i])
    with pytest.raises(DecodeError, match=f"first: \\[{len(seq) - 1}\\]"):
        dec.finish()
    with pytest.raises(DecodeError, match="frame index"):
        dec.push(len(seq), stack[0])


def test_passes_in_capture_order_share_one_decoder() -> None:
    """Passes that arrive one after another are decoded by one decoder in turn (memory of one pass's state, not
    three); a pass that starts before the last is complete takes a second; both give the offline maps."""
    seq, exposures, stack = _capture()
    offline, choice, _passes = decode_passes(stack, seq, exposures, DecodeParams())
    dec = HdrStreamingDecoder(seq, exposures, stack.shape[1:], stack.dtype, borrow_frames=True)
    for scan in range(2):
        dec.reset()
        for i in range(len(seq)):
            dec.push(i, stack[i])
        assert _bytes(dec.finish()) == _bytes(offline), scan
        assert dec.choice is not None and np.array_equal(dec.choice, choice)
        assert dec.held_decoders == 1, scan
    n = len(seq) // 3
    dec.reset()
    order = [*range(n - 1), n, n - 1, *range(n + 1, len(seq))]  # the second pass starts one frame early
    for i in order:
        dec.push(i, stack[i])
    assert _bytes(dec.finish()) == _bytes(offline)
    assert dec.held_decoders == 2
    with pytest.raises(DecodeError, match="pushed twice"):  # a frame of a finished pass, again
        dec.push(0, stack[0])
