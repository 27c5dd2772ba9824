"""Gray against phase: where the phase frames see other light than the Gray frames (a second copy of the
pattern, shifted by half a period), a pixel whose phase lies farther than 3/4 stripe from its Gray stripe's
centre is dropped with reason "weak or inconsistent code", in the batch and the streaming decoder alike."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from decode_render import H, W, grid, render, u_true

from appliance.patterns.sequence import PhaseFrame, gray_phase_sequence
from appliance.reconstruct.decode import StreamingDecoder, decode
from appliance.reconstruct.types import Reason

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
