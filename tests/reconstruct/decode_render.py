"""Synthetic camera frames of a pattern sequence with known projector coordinates (tests of the decoder)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from appliance.patterns.render import frame_intensity
from appliance.patterns.sequence import Sequence

H, W = 48, 64
Coord = Callable[[npt.NDArray[np.float64], npt.NDArray[np.float64]], npt.NDArray[np.float64]]


def u_true(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return 2.3 * x + 0.31 * y + 4.7 + 0.004 * x * x  # projector column seen at camera (x, y)


def v_true(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return 0.17 * x + 1.9 * y + 3.2


def grid() -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return xx, yy


def render(
    seq: Sequence,
    *,
    amp: float = 180.0,
    ambient: float = 15.0,
    noise: float = 1.0,
    dtype: type = np.uint8,
    shadow: tuple[slice, slice] | None = None,
    sub: int = 6,
    seed: int = 0,
    u_of: Coord = u_true,
    v_of: Coord = v_true,
) -> npt.NDArray[np.generic]:
    """Camera frames: each pixel integrates the projector image over its footprint (sub x sub samples)."""
    rng = np.random.default_rng(seed)
    xx, yy = grid()
    offsets = [((i + 0.5) / sub - 0.5, (j + 0.5) / sub - 0.5) for i in range(sub) for j in range(sub)]
    coords = [
        (
            np.clip(np.floor(u_of(xx + dx, yy + dy) + 0.5).astype(np.int64), 0, seq.width - 1),
            np.clip(np.floor(v_of(xx + dx, yy + dy) + 0.5).astype(np.int64), 0, seq.height - 1),
        )
        for dy, dx in offsets
    ]
    out = np.empty((len(seq), H, W), np.float64)
    for i, f in enumerate(seq.frames):
        img = frame_intensity(f, seq.width, seq.height)  # projector image, (height, width) in [0, 1]
        out[i] = np.mean([img[r, c] for c, r in coords], axis=0)
    light = ambient + amp * out
    if shadow is not None:
        light[:, shadow[0], shadow[1]] = ambient + 0.01 * amp * out[:, shadow[0], shadow[1]]
    light += rng.normal(0.0, noise, light.shape)
    top = float(np.iinfo(dtype).max)
    return np.clip(np.rint(light), 0, top).astype(dtype)
