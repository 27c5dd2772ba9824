"""The virtual rig's light of XOR code frames: the projector images' pixels, blurred edges in their places."""

from __future__ import annotations

import numpy as np

from appliance.patterns.render import frame_profile
from appliance.patterns.sequence import GrayFrame
from appliance.sim.render import projected_light


def test_xor_frame_light_is_the_projector_image_and_blurs_at_both_bits_edges() -> None:
    size = 512
    u = np.arange(size, dtype=np.float64)
    v = np.full(size, 10.0)
    for frame in (GrayFrame("x", 3, False, 8, 0), GrayFrame("x", 5, True, 8, 1)):
        sharp = projected_light(frame, u, v, size, 64)
        np.testing.assert_allclose(sharp[1:-1], frame_profile(frame, size)[1:-1], atol=1e-12)
        # blurred: half way at each edge (where the projected image changes), unchanged far from the edges
        blurred = projected_light(frame, u + 0.5, v, size, 64, projector_blur_px=0.7)[:-2]
        prof = frame_profile(frame, size)
        edges = np.flatnonzero(np.diff(prof) != 0)
        assert edges.size > 0
        np.testing.assert_allclose(blurred[edges], 0.5, atol=1e-6)
        far = np.ones(size - 2, bool)
        far[:6] = False  # the projector image's own (blurred) border
        for e in edges:
            far[max(e - 4, 0):e + 6] = False
        np.testing.assert_allclose(blurred[far], prof[:-2][far], atol=1e-6)
