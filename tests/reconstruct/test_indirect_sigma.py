"""Light that came another way: the decoder's fringe share and the sigma it adds.

A pixel lit directly by the pattern shows a phase modulation that is a fixed share of its white - black range
(the optics' blur sets it). Light that reaches it by another path (diffuse interreflection, averaged over many
projector pixels) adds to the range but not to the modulation, so the share drops; such light may shift the
code, and the point's sigma says by how much (``uncertainty.fringe_variance_table``). The end-to-end figures
(a matte concave corner with exact truth) are in ``tests/accuracy/test_hard_scenes.py``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from decode_render import H, W, render
from procam_geometry import codes, procam_rig, triangulator, true_points

from appliance.patterns.sequence import gray_code_sequence, gray_phase_sequence
from appliance.reconstruct.decode import DecodeParams, StreamingDecoder, decode
from appliance.reconstruct.types import DecodedMaps, Reason
from appliance.reconstruct.uncertainty import (
    FRINGE_MAX_INDIRECT,
    FRINGE_MIN_PIXELS,
    FRINGE_TOLERANCE,
    CodeNoise,
    code_noise_for_sequence,
    fringe_variance_table,
)

SEQ = gray_phase_sequence(256, 160, "x", period=16)
REGION = (slice(10, 40), slice(8, 40))


def _frames(indirect: float) -> npt.NDArray[np.uint8]:
    """The direct pattern (amplitude 120 DN); in the region plus ``indirect`` DN of light the pattern reaches
    by another way, averaged out: all of it under white, none under black, half under every coded frame
    (each projects half its pixels)."""
    direct = render(SEQ, amp=120.0, ambient=10.0, noise=1.0, seed=4).astype(np.float64)
    for i, f in enumerate(SEQ.frames):
        level = {"white": 1.0, "black": 0.0}.get(getattr(f, "pattern", ""), 0.5)
        direct[i, REGION[0], REGION[1]] += level * indirect
    return np.clip(np.rint(direct), 0, 255).astype(np.uint8)


def _stream(frames: npt.NDArray[np.uint8]) -> DecodedMaps:
    dec = StreamingDecoder(SEQ, (H, W), np.uint8, DecodeParams())
    for i in np.random.default_rng(1).permutation(len(SEQ)):
        dec.push(int(i), frames[i])
    return dec.finish()


def test_indirect_light_lowers_the_fringe_share_alike_in_batch_and_streaming() -> None:
    frames = _frames(indirect=120.0)  # as much light again as the direct pattern's
    batch = decode(frames, SEQ)
    stream = _stream(frames)
    assert batch.fringe is not None and stream.fringe is not None
    assert np.array_equal(batch.fringe, stream.fringe)
    inside = np.zeros((H, W), bool)
    inside[REGION] = True
    ok = batch.mask
    assert ok[inside].mean() > 0.95 and ok[~inside].mean() > 0.95
    clean = np.median(batch.fringe[ok & ~inside])
    lit_twice = np.median(batch.fringe[ok & inside])
    assert 80 <= clean <= 100, clean  # the render's pixel footprint blurs the 16 px fringe a little
    assert abs(lit_twice / clean - 0.5) < 0.03, (lit_twice, clean)  # range doubled, modulation the same
    assert not batch.fringe[~ok].any()  # 0 where undecoded


def test_a_gray_only_code_has_no_fringe_share() -> None:
    seq = gray_code_sequence(256, 160, "x")
    frames = render(seq, amp=120.0, ambient=10.0, noise=1.0, seed=2)
    maps = decode(frames, seq)
    assert maps.mask.mean() > 0.9
    assert maps.fringe is not None and not maps.fringe.any()
    assert code_noise_for_sequence(seq).period_px == 0.0
    assert code_noise_for_sequence(SEQ).period_px == 16.0


def _hist(values: dict[int, int]) -> npt.NDArray[np.int64]:
    h = np.zeros(256, np.int64)
    for k, n in values.items():
        h[k] = n
    return h


def test_the_table_is_zero_within_the_tolerance_and_the_phase_bound_beyond() -> None:
    hist = _hist({0: 10**6, 80: 3000, 90: 5000, 95: 3000})  # bin 0 (undecoded) is not counted
    got = fringe_variance_table(hist, 16.0)
    assert got is not None
    table, median = got
    assert median == pytest.approx(0.90)
    # within the tolerance of the median (and above it): no bias
    assert not table[math.ceil(100 * 0.9 * (1 - FRINGE_TOLERANCE)) :].any()
    # half the median: half the light indirect, less the tolerance: e = 0.4, phase bound 0.4 / 0.6 rad
    e = 1.0 - 0.45 / 0.90 - FRINGE_TOLERANCE
    assert table[45] == pytest.approx((16.0 / (2 * math.pi) * e / (1 - e)) ** 2)
    assert np.all(np.diff(table[:90]) <= 0)  # the less fringe, the more bias
    cap = FRINGE_MAX_INDIRECT / (1 - FRINGE_MAX_INDIRECT)
    assert table[0] == pytest.approx((16.0 / (2 * math.pi) * cap) ** 2)


def test_no_table_without_a_phase_code_or_with_too_few_pixels() -> None:
    assert fringe_variance_table(_hist({90: 10**5}), 0.0) is None
    assert fringe_variance_table(_hist({90: FRINGE_MIN_PIXELS - 1}), 16.0) is None
    with pytest.raises(ValueError, match=r"\(256,\)"):
        fringe_variance_table(np.zeros(255, np.int64), 16.0)


def test_the_bias_widens_sigma_by_the_table_and_max_sigma_drops_with_its_reason() -> None:
    _cam, proj, _ = procam_rig("h")
    truth = true_points("h", "plane")
    maps = codes(proj, truth, "x")
    h, w = maps.shape
    maps.reason = np.where(maps.mask, 0, int(Reason.SHADOW)).astype(np.uint8)
    fringe = np.where(maps.mask, 90, 0).astype(np.uint8)
    fringe[:, : w // 4] = np.where(maps.mask[:, : w // 4], 45, 0)  # a quarter of the image half indirect
    maps.fringe = fringe
    noise = CodeNoise(16 * np.sqrt(2 / 4) / np.pi, 0.0, 2.0, 25.0, 16.0)
    tri = triangulator("h", "x")
    sigma = np.empty((h, w), np.float32)
    counts = np.empty(h + 1, np.int64)
    depth, counts = tri.triangulate_depth(maps, noise=noise, sigma_out=sigma, counts=counts)
    before = sigma.copy()
    kept_before = int(counts.sum())
    dropped = np.zeros(h, np.int64)
    median = tri.indirect_bias(maps, depth, sigma, noise, None, dropped)
    assert median == pytest.approx(0.90)
    assert not dropped.any()
    clean = np.isfinite(before) & (fringe == 90)
    assert clean.sum() > 1000 and np.array_equal(sigma[clean], before[clean])  # at the median: unchanged
    half = np.isfinite(before) & (fringe == 45)
    assert half.sum() > 1000
    table, _ = fringe_variance_table(np.bincount(fringe.ravel(), minlength=256), 16.0) or (None, None)
    assert table is not None
    su2n = noise.sigma_px(maps.quality[half]) ** 2
    want = before[half] * np.sqrt(1.0 + table[45] / su2n)
    np.testing.assert_allclose(sigma[half], want, rtol=1e-5)
    assert np.all(sigma[half] > 3 * before[half])
    # a sigma limit between the two: the widened points go, with reason "filtered", and are counted per row
    limit = float(0.5 * (np.nanmax(before) + np.nanmin(sigma[half])))
    assert np.nanmax(before) < limit
    reason = maps.reason.copy()
    sigma2 = before.copy()
    depth2 = depth.copy()
    dropped2 = np.zeros(h, np.int64)
    tri.indirect_bias(maps, depth2, sigma2, noise, None, dropped2, limit, reason)
    gone = np.isfinite(depth) & ~np.isfinite(depth2)
    assert gone.sum() == dropped2.sum() == np.count_nonzero(sigma[half] > limit) > 1000
    assert np.all(reason[gone] == Reason.FILTERED)
    assert np.array_equal(dropped2, gone.sum(axis=1))
    assert kept_before == int(np.isfinite(depth).sum())
