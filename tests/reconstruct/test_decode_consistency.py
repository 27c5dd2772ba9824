"""Gray against phase: where the phase frames see other light than the Gray frames (a second copy of the
pattern, shifted by half a period), a pixel whose phase lies farther than 3/4 stripe from its Gray stripe's
centre is dropped with reason "weak or inconsistent code", in the batch and the streaming decoder alike."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from decode_render import H, W, grid, render, u_true

from appliance.patterns.sequence import PhaseFrame, gray_phase_sequence
from appliance.reconstruct.decode import StreamingDecoder, decode
from appliance.reconstruct.types import DecodedMaps, Reason

SEQ = gray_phase_sequence(256, 160, "x", period=16)  # Gray stripe 8 px
STRIPE = 8.0


def _shifted(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return u_true(x, y) + 8.0  # half a period


def test_gray_and_phase_that_disagree_drop_the_pixel() -> None:
    direct = render(SEQ, seed=4)
    ghost = render(SEQ, seed=4, u_of=_shifted)
    region = (slice(10, 40), slice(8, 56))
    frames = direct.copy()
    phase = [i for i, f in enumerate(SEQ.frames) if isinstance(f, PhaseFrame)]
    for i in phase:  # in the region the phase frames show the shifted copy; Gray, white, black the direct one
        frames[i][region] = ghost[i][region]
    maps = decode(frames, SEQ)
    stream = StreamingDecoder(SEQ, (H, W))
    for i in range(len(SEQ)):
        stream.push(i, frames[i])
    streamed = stream.finish()
    assert maps.reason is not None and streamed.reason is not None
    assert np.array_equal(maps.mask, streamed.mask) and np.array_equal(maps.reason, streamed.reason)
    xx, yy = grid()
    u = u_true(xx, yy)
    centre = (np.floor((u + 0.5) / STRIPE) + 0.5) * STRIPE - 0.5  # the true Gray stripe's centre
    mid = np.abs(u - centre) < 1.5  # mid-stripe: the shifted phase is > 6.5 px (3/4 stripe + noise) from it
    inside = np.zeros((H, W), bool)
    inside[region] = True
    # mid-stripe pixels of the region: dropped, saying why; nothing outside the region is lost
    assert np.mean(maps.mask[inside & mid]) < 0.02
    assert np.mean(maps.reason[inside & mid] == Reason.WEAK_CODE) > 0.98
    assert (inside & mid).sum() > 200
    assert np.mean(maps.mask[~inside]) > 0.97
    assert np.nanmax(np.abs(maps.u - u)[~inside & maps.mask]) < 0.5


# --- two phase frequencies against each other -----------------------------------------------------------------

SEQ2 = gray_phase_sequence(256, 160, "x", periods=[64, 16])  # Gray stripe 32 px; the 64 px phase unwraps the 16 px


def _two_frequencies(shift_px: float) -> tuple[DecodedMaps, DecodedMaps, npt.NDArray[np.bool_]]:
    """Frames in which, inside a region, only the finer (16 px) phase frames show a copy shifted by ``shift_px``:
    the batch and the streaming decode, and the region."""
    direct = render(SEQ2, seed=5)
    ghost = render(SEQ2, seed=5, u_of=lambda x, y: u_true(x, y) + shift_px)
    region = (slice(10, 40), slice(8, 56))
    frames = direct.copy()
    for i, f in enumerate(SEQ2.frames):
        if isinstance(f, PhaseFrame) and f.period == 16:
            frames[i][region] = ghost[i][region]
    stream = StreamingDecoder(SEQ2, (H, W))
    for i in range(len(SEQ2)):
        stream.push(i, frames[i])
    inside = np.zeros((H, W), bool)
    inside[region] = True
    return decode(frames, SEQ2), stream.finish(), inside


def test_two_phase_frequencies_that_disagree_drop_the_pixel() -> None:
    # 7 px of a 16 px period: the finer phase unwraps to ~7 px from the coarser estimate, past 0.35 periods (5.6 px)
    maps, streamed, inside = _two_frequencies(7.0)
    assert maps.reason is not None and streamed.reason is not None
    assert np.array_equal(maps.mask, streamed.mask) and np.array_equal(maps.reason, streamed.reason)
    assert np.mean(maps.mask[inside]) < 0.02
    assert np.mean(maps.reason[inside] == Reason.WEAK_CODE) > 0.98
    assert np.mean(maps.mask[~inside]) > 0.97
    xx, yy = grid()
    err = np.abs(maps.u - u_true(xx, yy))[~inside & maps.mask]
    assert np.nanmax(err) < 0.5


def test_two_phase_frequencies_within_the_margin_keep_the_pixel() -> None:
    # 3 px (0.19 periods): within what a noisy coarser estimate may be off, so the pixel stays (with the finer phase)
    maps, _streamed, inside = _two_frequencies(3.0)
    assert np.mean(maps.mask[inside]) > 0.95
