"""The HDR fusion trusts a pass for a pixel only where none of its 8 neighbours clipped there: a clipped
neighbour's light, of unknown level, reaches the pixel through the lens blur (a bright-dark edge). Rule-level
cases on hand-made pass maps; the dark-and-shiny scene's figures are in tests/commands/test_tune.py."""

from __future__ import annotations

import numpy as np

from appliance.reconstruct.hdr import fuse_exposures
from appliance.reconstruct.types import DecodedMaps, Reason

SHAPE = (5, 7)


def _pass(value: float, decoded: np.ndarray, reason: np.ndarray) -> DecodedMaps:
    u = np.where(decoded, np.float32(value), np.float32(np.nan)).astype(np.float32)
    return DecodedMaps(u, u.copy(), decoded.copy(), np.where(decoded, 50.0, 0.0).astype(np.float32),
                       levels=np.zeros((2, *SHAPE), np.uint8), reason=reason.astype(np.uint8))


def test_a_pixel_next_to_a_clipped_one_takes_a_clean_darker_pass_or_says_why() -> None:
    # bright pass (index 1): everything decodes but pixel (2, 3), which clipped; dark pass (index 0): the
    # left half decodes, the right half is too dark
    bright_ok = np.ones(SHAPE, bool)
    bright_ok[2, 3] = False
    bright_reason = np.where(bright_ok, Reason.DECODED, Reason.SATURATED)
    dark_ok = np.zeros(SHAPE, bool)
    dark_ok[:, :3] = True
    dark_reason = np.where(dark_ok, Reason.DECODED, Reason.TOO_DARK)
    fused, choice = fuse_exposures([_pass(1.0, dark_ok, dark_reason), _pass(2.0, bright_ok, bright_reason)])
    assert fused.reason is not None
    near = np.zeros(SHAPE, bool)
    near[1:4, 2:5] = True
    near[2, 3] = False  # the clipped pixel itself
    far = ~near & bright_ok
    # far from the clip: the bright pass, whole
    assert (choice[far] == 1).all() and (fused.u[far] == 2.0).all() and fused.mask[far].all()
    # next to it, where the dark pass decodes (column 2): the dark pass's code
    left = near & dark_ok
    assert left.sum() == 3 and (choice[left] == 0).all() and (fused.u[left] == 1.0).all()
    # next to it, where the dark pass does not: no point, and the reason says why
    right = near & ~dark_ok
    assert right.sum() == 5
    assert (fused.reason[right] == Reason.MIXED).all() and not fused.mask[right].any()
    assert np.isnan(fused.u[right]).all() and (fused.quality[right] == 0).all()
    # the clipped pixel: the dark pass, which did not clip it (too dark there)
    assert choice[2, 3] == 0 and fused.reason[2, 3] == Reason.TOO_DARK
    assert np.array_equal(fused.mask, fused.reason == Reason.DECODED)


def test_a_pixel_every_pass_clipped_next_to_stays_mixed_and_one_clipped_everywhere_is_saturated() -> None:
    ok = np.ones(SHAPE, bool)
    ok[2, 3] = False
    reason = np.where(ok, Reason.DECODED, Reason.SATURATED)
    fused, _ = fuse_exposures([_pass(1.0, ok, reason), _pass(2.0, ok, reason)])
    assert fused.reason is not None
    assert fused.reason[2, 3] == Reason.SATURATED
    assert (fused.reason[1:4, 2:5].sum() - Reason.SATURATED) == 8 * Reason.MIXED
    assert fused.mask.sum() == ok.size - 9
