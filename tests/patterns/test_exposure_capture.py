"""``sequence.exposures_us``: the capture a scan would take (the sequence once per exposure), recorded as a
manifest with ``exposure_us`` per frame and decoded from it exactly as the streaming decoder decodes the frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.errors import PatternError
from appliance.patterns.from_config import build_capture, build_sequence
from appliance.patterns.manifest import read_manifest, write_manifest
from appliance.patterns.sequence import exposure_capture
from appliance.reconstruct.decode import DecodeParams
from appliance.reconstruct.hdr import HdrStreamingDecoder, decode_passes
from appliance.sim.rig import VirtualRig

RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16], exposures_us: [40000, 2500, 10000]}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 850, position_mm: [180, 0, 0], look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 160, height: 128, focal_px: 290, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
  scene:
    - {type: plane, point_mm: [0, 0, 640], normal: [0, 0.1, -1], albedo: 0.95}
    - {type: box, center_mm: [0, 0, 590], size_mm: [120, 90, 40], rotation_deg: [5, 15, 0], albedo: 0.03}
  imaging: {projector_gain_dn: 420, ambient_dn: 6}
"""


def test_a_configured_hdr_capture_records_and_decodes_as_it_streams(tmp_path: Path) -> None:
    cfg = parse_config(RIG, "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    one = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    capture, exposures = build_capture(cfg.sequence, rig.projector.width, rig.projector.height)
    assert exposures is not None
    assert len(capture) == 3 * len(one) and capture.frames[: len(one)] == one.frames
    assert [e for e, _ in exposures[:: len(one)]] == [40000.0, 2500.0, 10000.0]  # the configured order
    stack = np.concatenate([rig.render(one, "cam0", seed=k, exposure_us=e)
                            for k, e in enumerate(cfg.sequence.exposures_us)])  # fmt: skip
    np.save(tmp_path / "cam0.npy", stack)
    path = write_manifest(tmp_path / "hdr.yaml", capture, ["cam0"], stacks={"cam0": "cam0.npy"}, exposures=exposures)
    man = read_manifest(path)
    assert man.sequence.frames == capture.frames and man.exposures == exposures
    offline, choice, passes = decode_passes(man.load_stack("cam0"), man.sequence, man.exposures, DecodeParams())
    assert len(passes) == 3
    dec = HdrStreamingDecoder(capture, exposures, stack.shape[1:], stack.dtype)
    for i, frame in enumerate(stack):
        dec.push(i, frame)
    streamed = dec.finish()
    for key in ("u", "v", "mask", "quality", "levels", "reason"):
        assert np.array_equal(getattr(streamed, key), getattr(offline, key), equal_nan=key in "uv"), key
    assert dec.choice is not None and np.array_equal(dec.choice, choice)


def test_one_pass_without_exposures_and_bad_exposures() -> None:
    cfg = parse_config(RIG.replace(", exposures_us: [40000, 2500, 10000]", ""), "rig.yaml")
    capture, exposures = build_capture(cfg.sequence, 640, 400)
    assert exposures is None and capture == build_sequence(cfg.sequence, 640, 400)
    for bad, needle in (([], "at least one"), ([0.0], "> 0"), ([100.0, 100.0], "twice")):
        with pytest.raises(PatternError, match=needle):
            exposure_capture(capture, bad)
    with pytest.raises(PatternError, match="intensity"):
        exposure_capture(capture, [100.0], intensity=1.5)
