"""``code_grid`` (how a code map is quantised, measured in numba passes) against plain numpy on the same maps."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.reconstruct import _cell_kernels as K
from appliance.reconstruct import _stereo_kernels as C
from appliance.reconstruct.stereo import code_grid


def _stripe_map(step: float, origin: float, h: int = 240, w: int = 320, seed: int = 5) -> tuple[np.ndarray, ...]:
    """Stripe centres ``origin + k * step`` rising along x (0.6 projector px per camera px), a few pixels
    undecoded (NaN code, mask False) and a few on a stripe edge (a value between two centres)."""
    rng = np.random.default_rng(seed)
    x = np.arange(w)[None, :] * 0.6 + np.arange(h)[:, None] * 0.05
    code = (origin + step * np.floor((x - origin) / step + 0.5)).astype(np.float32)
    edge = rng.random((h, w)) < 0.002
    code[edge] += np.float32(0.37 * step)
    mask = rng.random((h, w)) > 0.1
    code[~mask] = np.nan
    return code, mask


def _numpy_samples(code: np.ndarray, mask: np.ndarray, stride: int) -> np.ndarray:
    vals = code[::stride, ::stride][mask[::stride, ::stride]]
    return vals[np.isfinite(vals)]


@pytest.mark.parametrize(("step", "origin"), [(1.0, 0.0), (3.0, 1.0), (8.0, 3.5), (16.0, 7.5)])
def test_quantised_codes_give_their_step_and_origin(step: float, origin: float) -> None:
    code, mask = _stripe_map(step, origin)
    grid = code_grid(code, mask)
    assert grid is not None and grid.quantised
    assert grid.step == pytest.approx(step) and grid.origin % step == pytest.approx(origin % step)
    d = np.abs(np.diff(code[::5].astype(np.float64), axis=1))
    assert grid.per_px == pytest.approx(float(d[d < 64.0].mean()), rel=1e-9)  # finite changes below 64


def test_continuous_and_sparse_codes() -> None:
    rng = np.random.default_rng(2)
    code, mask = _stripe_map(1.0, 0.0)
    phase = (code + rng.normal(0.0, 0.05, code.shape)).astype(np.float32)
    grid = code_grid(phase, mask)
    assert grid is not None and not grid.quantised and grid.step == 1.0
    assert code_grid(code[:20, :20], mask[:20, :20]) is None  # fewer than 100 samples


def test_sampling_and_half_pixel_counts_match_numpy() -> None:
    code, mask = _stripe_map(1.0, 0.0)
    for stride in (1, 3, 5):
        buf = np.empty(-(-code.shape[0] // stride) * -(-code.shape[1] // stride), np.float32)
        got = buf[: C.sample_codes(code, mask, stride, buf)]
        np.testing.assert_array_equal(got, _numpy_samples(code, mask, stride))
    vals = _numpy_samples(code, mask, 1)
    share, cnt = C.half_pixel_counts(vals)
    h2 = vals.astype(np.float64) * 2.0
    on = np.abs(h2 - np.rint(h2)) < 2e-3
    assert share == pytest.approx(on.mean())
    np.testing.assert_array_equal(cnt, np.bincount(np.rint(h2[on]).astype(np.intp), minlength=cnt.size))
    share, cnt = C.half_pixel_counts(vals - np.float32(500.0))  # negative codes: no counts, the caller sorts
    assert cnt.size == 0
    k = (vals.astype(np.float64) - 0.5) / 2.0
    assert C.on_grid_share(vals, 0.5, 2.0) == pytest.approx(np.mean(np.abs(k - np.round(k)) < 1e-3))


def test_codes_that_dropped_finest_bits_sit_on_the_grid_of_their_own_level() -> None:
    """Blur that makes the finest stripes marginal: pixels near a stripe edge drop 1 or 2 finest Gray bits and
    hold the centre of a 2- or 4-px stripe (``k + 0.5``, ``4 k + 1.5``), off the 1-px grid. Over 40 % of the
    values off it: taken for continuous codes on the values alone (the rule wants 99 % on the grid); with each
    pixel's level, quantised, step 1, origin 0. Continuous codes stay continuous with levels too."""
    rng = np.random.default_rng(7)
    code, mask = _stripe_map(1.0, 0.0)
    levels = np.zeros(code.shape, np.uint8)
    x = np.arange(code.shape[1])[None, :] * 0.6 + np.arange(code.shape[0])[:, None] * 0.05
    pick = rng.random(code.shape)
    one = mask & (pick < 0.25)
    two = mask & (pick >= 0.25) & (pick < 0.45)
    code[one] = (2.0 * np.floor(x[one] / 2.0) + 0.5).astype(np.float32)
    levels[one] = 1
    code[two] = (4.0 * np.floor(x[two] / 4.0) + 1.5).astype(np.float32)
    levels[two] = 2
    plain = code_grid(code, mask)
    assert plain is not None and not plain.quantised
    grid = code_grid(code, mask, levels=levels)
    assert grid is not None and grid.quantised and grid.step == 1.0 and grid.origin == 0.0, grid
    assert grid.per_px == pytest.approx(plain.per_px)
    assert grid.dropped == pytest.approx(0.45, abs=0.03) and plain.dropped == 0.0  # the matcher splits such codes
    phase = (code + rng.normal(0.0, 0.05, code.shape)).astype(np.float32)
    grid = code_grid(phase, mask, levels=levels)
    assert grid is not None and not grid.quantised
    vals = code[::5, ::5][mask[::5, ::5]]
    levs = levels[::5, ::5][mask[::5, ::5]]
    assert K.on_level_grid_share(vals, levs, 0.0, 1.0) > 0.99
    assert C.on_grid_share(vals, 0.0, 1.0) < 0.6
