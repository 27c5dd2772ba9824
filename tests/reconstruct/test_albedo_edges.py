"""The code shift at albedo edges, corrected: a dark pixel beside a bright one reads its neighbour's code too.

The frames here are made without the virtual rig: the pattern at the exact projector column of each camera
pixel, times the surface's albedo (a bright half beside a dark one), blurred by a Gaussian lens with OpenCV.
The end-to-end figures (the dark-and-shiny render with tune's three exposures) are in
``tests/commands/test_tune.py``.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from appliance.patterns.render import frame_intensity
from appliance.patterns.sequence import gray_phase_sequence
from appliance.reconstruct import _edge_kernels as _k
from appliance.reconstruct import albedo_edges
from appliance.reconstruct._hdr_kernels import choose_pass, clipped_near
from appliance.reconstruct.albedo_edges import AlbedoEdges
from appliance.reconstruct.decode import decode
from appliance.reconstruct.hdr import radiance
from appliance.reconstruct.types import Reason

H, W = 40, 64
SEQ = gray_phase_sequence(256, 160, "x", period=16)
EDGE = 30  # columns < EDGE bright, >= EDGE dark
BLUR = 0.5
SUB = 5  # samples per camera pixel (each way) before the lens blur


def _u_true(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return 1.8 * x + 0.1 * y + 20.0  # projector column seen at camera (x, y), pixel centres at integers


def _frames(dark: float = 0.25, bright: float = 0.95) -> npt.NDArray[np.uint8]:
    """Each frame sampled SUB x finer, times the albedo, blurred by the lens (sigma BLUR camera px), then read
    at the pixel centres; 200 DN at albedo 1 under white (a darker side than 0.25 falls under the decoder's
    shadow threshold here)."""
    ys, xs = np.mgrid[0 : H * SUB, 0 : W * SUB].astype(np.float64)
    x, y = (xs + 0.5) / SUB - 0.5, (ys + 0.5) / SUB - 0.5
    u = _u_true(x, y)
    albedo = np.where(x < EDGE - 0.5, bright, dark)
    out = np.empty((len(SEQ), H, W), np.uint8)
    for i, f in enumerate(SEQ.frames):
        img = frame_intensity(f, SEQ.width, SEQ.height)[0]  # a column pattern: any row
        cols = np.arange(SEQ.width, dtype=np.float64)
        light = 200.0 * albedo * np.interp(u, cols, img) + 2.0 * albedo
        blurred = cv2.GaussianBlur(light, (0, 0), BLUR * SUB, borderType=cv2.BORDER_REFLECT)
        centre = blurred[SUB // 2 :: SUB, SUB // 2 :: SUB]
        out[i] = np.clip(np.rint(centre), 0, 255).astype(np.uint8)
    return out


def _white(frames: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    return frames[next(i for i, f in enumerate(SEQ.frames) if getattr(f, "pattern", "") == "white")]


def _correct(frames: npt.NDArray[np.uint8], blur: float = BLUR) -> tuple[object, object, npt.NDArray[np.float32]]:
    """The decoded maps, a copy corrected in place, and the dense variance of the corrections."""
    maps = decode(frames, SEQ)
    fixed = dataclasses.replace(maps, u=maps.u.copy())
    edges = AlbedoEdges(H)
    edges.apply(fixed, _white(frames), blur, "x")
    var = np.zeros((H, W), np.float32)
    for r in range(H):
        k = slice(edges.offsets[r], edges.offsets[r + 1])
        assert np.all(np.diff(edges.cols[k]) > 0)  # ascending columns
        var[r, edges.cols[k]] = edges.variance[k]
    moved = np.abs(fixed.u - maps.u) > albedo_edges.REPORT_SHIFT_PX  # counted: moved by more than 0.05 px
    np.testing.assert_array_equal(edges.moved_rows, moved.sum(axis=1))
    assert edges.moved == int(moved.sum())
    return maps, fixed, var


def test_restore_gives_back_every_code_bit_for_bit() -> None:
    maps = decode(_frames(), SEQ)
    before = maps.u.copy()
    edges = AlbedoEdges(H)
    edges.apply(maps, _white(_frames()), BLUR, "x")
    assert not np.array_equal(maps.u, before, equal_nan=True)
    edges.restore()
    np.testing.assert_array_equal(maps.u, before)
    edges.restore()  # twice: nothing more
    np.testing.assert_array_equal(maps.u, before)


def test_the_dark_side_of_an_edge_reads_its_own_code_again() -> None:
    frames = _frames()
    maps, fixed, var = _correct(frames)
    white = _white(frames)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    truth = _u_true(xx, yy)
    raw = maps.u - truth  # type: ignore[attr-defined]
    cor = fixed.u - truth  # type: ignore[attr-defined]
    rows = slice(4, H - 4)
    near = raw[rows, EDGE - 1 : EDGE + 1]  # the last bright and the first dark column: most shifted
    assert np.all(near < -0.1) and near[:, 1].mean() < -0.35, near  # pulled towards the bright side's codes
    fixed_near = cor[rows, EDGE - 1 : EDGE + 1]
    assert np.abs(fixed_near).mean() <= 0.25 * np.abs(near).mean(), fixed_near
    # over the edge's six columns the RMS halves at least (a pixel two columns into the dark side, where the
    # level's slope is not resolved by its pixels, gets up to 0.12 px too much)
    band = (slice(4, H - 4), slice(EDGE - 3, EDGE + 3))
    assert np.sqrt(np.mean(cor[band] ** 2)) <= 0.5 * np.sqrt(np.mean(raw[band] ** 2))
    assert np.abs(cor[band]).max() <= 0.15, cor[band]
    # away from the edge the level is flat: no correction, no variance
    for cols in (slice(4, EDGE - 3), slice(EDGE + 4, W - 4)):
        np.testing.assert_array_equal(fixed.u[rows, cols], maps.u[rows, cols])  # type: ignore[attr-defined]
        assert not var[rows, cols].any()
    # the variance: the correction times (half + the centroid shift |d| in px), squared (the shift read back
    # from float32 codes: 1 %), both from the level's central slope; where the slope limit cut the shift the
    # variance stays that of the central slope's, more than the formula gives for the smaller shift applied
    level = white.astype(np.float64)
    gx = np.zeros_like(level)
    gy = np.zeros_like(level)
    gx[:, 1:-1] = (level[:, 2:] - level[:, :-2]) / 2
    gy[1:-1] = (level[2:] - level[:-2]) / 2
    d = np.minimum(BLUR**2 * np.hypot(gx, gy) / level, albedo_edges.MAX_SHIFT_PX)
    shift = (maps.u - fixed.u)[band].astype(np.float64)  # type: ignore[attr-defined]
    expected = ((albedo_edges.EDGE_SIGMA_SHARE + d[band]) * shift) ** 2
    limit = _k.SLOPE_LIMIT
    a, b = np.zeros_like(level), np.zeros_like(level)
    a[:, 1:-1], b[:, 1:-1] = level[:, 2:] - level[:, 1:-1], level[:, 1:-1] - level[:, :-2]
    cut = (a * b <= 0) | (np.abs(gx) > limit * np.minimum(np.abs(a), np.abs(b)))
    cut = cut[band] & (expected > 0)
    assert cut.any() and (~cut).sum() > cut.sum()  # the columns two into the dark side; the rest not
    np.testing.assert_allclose(var[band][~cut], expected[~cut], rtol=0.01, atol=1e-7)
    assert np.all(var[band][cut] >= 0.99 * expected[cut])
    assert fixed.v is maps.v  # type: ignore[attr-defined]  # v is not coded: left as it was
    assert fixed.mask is maps.mask  # type: ignore[attr-defined]


def test_no_blur_changes_nothing() -> None:
    maps, fixed, var = _correct(_frames(), blur=0.0)
    np.testing.assert_array_equal(fixed.u, maps.u)  # type: ignore[attr-defined]
    assert not var.any()


def test_an_even_surface_keeps_its_codes() -> None:
    maps, fixed, var = _correct(_frames(dark=0.95))
    np.testing.assert_array_equal(fixed.u, maps.u)  # type: ignore[attr-defined]
    assert not var.any()


def test_a_level_image_of_another_shape_is_refused() -> None:
    maps = decode(_frames(), SEQ)
    with pytest.raises(ValueError, match="must be"):
        AlbedoEdges(H).apply(maps, np.ones((H, W + 1), np.uint8), BLUR, "x")


def test_radiance_is_each_pixel_s_brightest_unclipped_pass_in_the_brightest_pass_s_scale() -> None:
    dark = np.array([[10, 60, 200]], np.uint8)
    mid = np.array([[40, 240, 255]], np.uint8)
    bright = np.array([[160, 255, 255]], np.uint8)
    got = radiance([dark, mid, bright], [1.0, 4.0, 16.0])
    np.testing.assert_allclose(got, [[160.0, 240.0 * 4.0, 200.0 * 16.0]])
    assert got.dtype == np.float32
    every = radiance([np.full((1, 2), 255, np.uint8)], [2.0])  # clipped in its only pass: that pass's value
    np.testing.assert_allclose(every, [[255.0, 255.0]])


@pytest.mark.parametrize("clean", [True, False])
def test_without_the_clean_neighbour_rule_a_pixel_takes_the_brightest_pass_that_did_not_clip_it(
    clean: bool,
) -> None:
    # two passes of a 3x3 patch: the bright pass clipped the centre's right neighbour, not the centre
    mask = np.ones((2, 3, 3), np.bool_)
    reason = np.zeros((2, 3, 3), np.uint8)
    reason[1, 1, 2] = Reason.SATURATED
    mask[1, 1, 2] = False
    choice = np.zeros((3, 3), np.uint8)
    out = np.zeros((3, 3), np.uint8)
    choose_pass(mask, reason, int(Reason.SATURATED), int(Reason.DECODED), int(Reason.MIXED), clean,
                np.empty((0, 0, 0), np.uint8), choice, out)  # fmt: skip
    # with the rule the centre comes from the darker pass (its bright pass had a clipped neighbour)
    assert choice[1, 1] == (0 if clean else 1)
    assert out[1, 1] == Reason.DECODED
    assert choice[1, 2] == 0  # the clipped pixel itself: the pass that did not clip it


@pytest.mark.parametrize("radius", [1, 2, 3, 4])
def test_blurrier_optics_widen_the_clean_rule(radius: int) -> None:
    # a 9x9 patch whose bright pass clipped one pixel 3 px right of the centre: the rule over a square of radius
    # 3 or more (optics that blur that far, decode_plan.CLEAN_SIGMAS x edge_blur_px) takes the centre from the
    # darker pass; the 8 neighbours (radius 1) and radius 2 do not see that pixel
    mask = np.ones((2, 9, 9), np.bool_)
    reason = np.zeros((2, 9, 9), np.uint8)
    reason[1, 4, 7] = Reason.SATURATED
    mask[1, 4, 7] = False
    near = np.empty((2, 9, 9), np.uint8)
    clipped_near(reason, int(Reason.SATURATED), radius, np.empty_like(near), near)
    rows = slice(4 - radius, 4 + radius + 1)
    cols = slice(7 - radius, min(7 + radius + 1, 9))
    expected = np.zeros((9, 9), np.uint8)
    expected[rows, cols] = 1
    np.testing.assert_array_equal(near[1], expected)
    assert not near[0].any()
    choice = np.zeros((9, 9), np.uint8)
    out = np.zeros((9, 9), np.uint8)
    choose_pass(mask, reason, int(Reason.SATURATED), int(Reason.DECODED), int(Reason.MIXED), True, near, choice,
                out)  # fmt: skip
    assert choice[4, 4] == (0 if radius >= 3 else 1) and out[4, 4] == Reason.DECODED
