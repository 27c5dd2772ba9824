"""The preview's parts: the area downscale of a depth map (against a brute-force reference with exact
fractions, and OpenCV's INTER_AREA), the bitmap font, the colour map and the picture's layout."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import numpy.typing as npt
import pytest

from appliance.output.font import CAP_H, CHARACTERS, GLYPH_W, LINE_H, draw_text, text_size
from appliance.output.preview import MIN_COVERAGE, NO_POINT_BGR, depth_lut, downscale_depth, render_preview

SID = "20261202-014512-SIM0001-000012"


# --- area downscale ---------------------------------------------------------------------------------------


def _reference_downscale(d: npt.NDArray[np.float32], h: int, w: int) -> tuple[npt.NDArray[np.float64], ...]:
    """Mean of the finite depths weighted by exact (rational) overlap areas, and the finite fraction of each
    output pixel's area; one output pixel and one source pixel at a time."""
    big_h, big_w = d.shape
    mean = np.full((h, w), np.nan)
    cover = np.zeros((h, w))
    for i in range(h):
        r0, r1 = Fraction(i * big_h, h), Fraction((i + 1) * big_h, h)
        for j in range(w):
            c0, c1 = Fraction(j * big_w, w), Fraction((j + 1) * big_w, w)
            area, acc = Fraction(0), Fraction(0)
            for r in range(big_h):
                oy = min(r1, Fraction(r + 1)) - max(r0, Fraction(r))
                if oy <= 0:
                    continue
                for c in range(big_w):
                    ox = min(c1, Fraction(c + 1)) - max(c0, Fraction(c))
                    if ox > 0 and np.isfinite(d[r, c]):
                        area += oy * ox
                        acc += oy * ox * Fraction(float(d[r, c]))
            cover[i, j] = float(area / ((r1 - r0) * (c1 - c0)))
            if area > 0:
                mean[i, j] = float(acc / area)
    return mean, cover


@pytest.mark.parametrize(("src", "dst"), [((13, 17), (5, 7)), ((10, 10), (3, 4)), ((7, 9), (7, 4)),
                                          ((6, 6), (1, 1)), ((12, 8), (4, 4)), ((9, 11), (9, 11))])  # fmt: skip
@pytest.mark.parametrize("nan_fraction", [0.0, 0.35, 0.7])
def test_downscale_matches_exact_reference(src: tuple[int, int], dst: tuple[int, int], nan_fraction: float) -> None:
    rng = np.random.default_rng(src[0] * 100 + dst[1])
    d = (500 + 100 * rng.random(src)).astype(np.float32)
    d[rng.random(src) < nan_fraction] = np.nan
    got = downscale_depth(d, dst)
    assert got.dtype == np.float32 and got.shape == dst
    mean, cover = _reference_downscale(d, *dst)
    clear = np.abs(cover - MIN_COVERAGE) > 1e-9  # exact ties: see the test below
    expect_nan = cover < MIN_COVERAGE
    np.testing.assert_array_equal(np.isnan(got)[clear], expect_nan[clear])
    ok = clear & ~expect_nan
    np.testing.assert_allclose(got[ok], mean[ok], rtol=1e-6)


def test_downscale_half_covered_keeps_a_depth() -> None:
    """2x2 blocks: 2 of 4 finite is half the area (kept, their mean); 1 of 4 is too little (NaN)."""
    d = np.array([[1, 3, 5, np.nan], [np.nan, np.nan, np.nan, np.nan]], np.float32)
    d = np.vstack([d, np.array([[7, np.nan, 9, 10], [np.nan, 8, 11, 12]], np.float32)])
    got = downscale_depth(d, (2, 2))
    np.testing.assert_array_equal(got[0], [2.0, np.nan])
    np.testing.assert_array_equal(got[1], [7.5, 10.5])


def test_downscale_all_empty_and_identity() -> None:
    assert np.isnan(downscale_depth(np.full((30, 40), np.nan, np.float32), (7, 9))).all()
    d = np.random.default_rng(5).random((30, 40)).astype(np.float32)
    d[3:9, 4:20] = np.nan
    np.testing.assert_array_equal(downscale_depth(d, (30, 40)), d)


@pytest.mark.parametrize("dst", [(511, 639), (949, 1186), (512, 640), (100, 37), (1024, 1000)])
def test_downscale_close_to_opencv_inter_area(dst: tuple[int, int]) -> None:
    import cv2

    yy, xx = np.mgrid[0:1024, 0:1280]
    noise = np.random.default_rng(0).normal(0, 2, (1024, 1280))
    d = (600 + 30 * np.sin(xx / 50) + 20 * np.cos(yy / 70) + noise).astype(np.float32)
    ref = cv2.resize(d, (dst[1], dst[0]), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(downscale_depth(d, dst), ref, atol=1e-3)  # float32 rounding at ~600 mm


@pytest.mark.parametrize(
    ("depth", "shape", "match"),
    [
        (np.zeros((8, 8), np.float64), (4, 4), r"depth = float64 \(8, 8\): must be a 2-D float32 array"),
        (np.zeros((8, 8, 1), np.float32), (4, 4), r"depth = float32 \(8, 8, 1\)"),
        (np.zeros((8, 8), np.float32), (9, 4), r"shape = \(9, 4\): must be \(h, w\) with 1 <= h <= 8"),
        (np.zeros((8, 8), np.float32), (4, 0), r"shape = \(4, 0\)"),
    ],
)
def test_downscale_refuses_bad_input(depth: npt.NDArray[np.float32], shape: tuple[int, int], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        downscale_depth(depth, shape)


# --- font -------------------------------------------------------------------------------------------------


def test_required_characters_have_glyphs() -> None:
    required = "0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz -_.:/+,()%"
    assert set(required) <= set(CHARACTERS)


@pytest.mark.parametrize("scale", [1, 2, 3])
def test_every_character_draws_inside_its_box(scale: int) -> None:
    bitmaps = set()
    for ch in CHARACTERS:
        canvas = np.zeros((40, 40), np.uint8)
        draw_text(canvas, ch, 7, 5, 200, scale)
        w, h = text_size(ch, scale)
        assert (w, h) == (GLYPH_W * scale, LINE_H * scale)
        inside = canvas[5 : 5 + h, 7 : 7 + w]
        assert canvas.sum() == inside.sum(), f"{ch!r} draws outside its box"
        assert set(np.unique(canvas)) <= {0, 200}
        if ch == " ":
            assert not inside.any()
        else:
            assert inside.any(), f"{ch!r} draws nothing"
            if ch != "_":
                assert np.any(inside[: CAP_H * scale]), f"{ch!r} has nothing above the baseline"
        bitmaps.add(inside.tobytes())
    assert len(bitmaps) == len(CHARACTERS)  # no two characters look the same


def test_text_size_and_spacing() -> None:
    assert text_size("", 1) == (0, LINE_H)
    assert text_size(SID, 1) == (6 * len(SID) - 1, LINE_H)
    assert text_size(SID, 2) == (2 * (6 * len(SID) - 1), 2 * LINE_H)
    canvas = np.zeros((20, 200, 3), np.uint8)
    draw_text(canvas, "1.5", 0, 0, (10, 20, 30))
    ink_cols = np.flatnonzero(canvas.any(axis=(0, 2)))
    assert ink_cols.max() < text_size("1.5", 1)[0]
    assert set(map(tuple, canvas[canvas.any(axis=2)])) == {(10, 20, 30)}  # the colour, channel by channel
    # the three glyphs in their own cells, one column apart
    for k, ch in enumerate("1.5"):
        alone = np.zeros((20, 6, 3), np.uint8)
        draw_text(alone, ch, 0, 0, (10, 20, 30))
        np.testing.assert_array_equal(canvas[:, 6 * k : 6 * k + 6], alone)


@pytest.mark.parametrize("ch", ["€", "\t", "~", "é"])
def test_unknown_characters_draw_a_box(ch: str) -> None:
    canvas = np.zeros((12, 8), np.uint8)
    draw_text(canvas, ch, 1, 1, 1)
    box = canvas[1 : 1 + CAP_H, 1 : 1 + GLYPH_W]
    assert box[0].all() and box[-1].all() and box[:, 0].all() and box[:, -1].all()
    assert not box[1:-1, 1:-1].any()
    assert canvas.sum() == box.sum()


@pytest.mark.parametrize("x", [-40, -7, -1, 0, 3, 25, 29, 30, 200])
@pytest.mark.parametrize("y", [-30, -5, 0, 4, 13, 14, 100])
def test_text_is_clipped_at_the_edges(x: int, y: int) -> None:
    """Drawn partly or wholly off the canvas: no error, and what lands on it is exactly that part of the text
    drawn on a larger canvas."""
    big = np.zeros((200, 400, 3), np.uint8)
    draw_text(big, "Ab-9%", 100 + x, 100 + y, (1, 2, 3), 2)
    canvas = np.zeros((15, 30, 3), np.uint8)
    draw_text(canvas, "Ab-9%", x, y, (1, 2, 3), 2)
    np.testing.assert_array_equal(canvas, big[100:115, 100:130])


def test_bad_scale_refused() -> None:
    with pytest.raises(ValueError, match=r"scale = 0: must be an integer >= 1"):
        draw_text(np.zeros((5, 5), np.uint8), "a", 0, 0, 1, 0)
    with pytest.raises(ValueError, match=r"scale = 1.5"):
        text_size("a", 1.5)  # type: ignore[arg-type]


# --- colour map and picture -------------------------------------------------------------------------------


def test_colour_map_far_cold_near_warm() -> None:
    lut = depth_lut()
    assert lut.shape == (256, 3) and lut.dtype == np.uint8 and not lut.flags.writeable
    b, r = lut[:, 0].astype(int), lut[:, 2].astype(int)
    assert r[255] > b[255] + 60 and r[230] > b[230] + 60  # near: red
    assert b[0] > r[0] and b[25] > r[25] + 60  # far: blue
    assert np.abs(np.diff(lut.astype(int), axis=0)).max() <= 16  # smooth: no jumps between neighbours
    assert depth_lut() is lut  # built once
    assert tuple(NO_POINT_BGR) not in set(map(tuple, lut))  # empty pixels stand apart


def _ramp(h: int, w: int) -> npt.NDArray[np.float32]:
    """Depth rising from 500 mm (left) to 700 mm (right), empty in its top quarter."""
    d = np.repeat(np.linspace(500, 700, w, dtype=np.float32)[None, :], h, axis=0)
    d[: h // 4] = np.nan
    return d


@pytest.mark.parametrize("size", [(120, 200), (1024, 1280)])
def test_preview_near_warm_far_cold_empty_grey(size: tuple[int, int]) -> None:
    """Full size (one small tile) and scaled down (two camera tiles)."""
    h, w = size
    depths = [_ramp(h, w)] * (1 if h < 500 else 2)
    img = render_preview(depths, "", 1280)
    th = img.shape[0]
    near, far = img[th // 2, 2].astype(int), img[th // 2, int(0.97 * img.shape[0] * w / h)].astype(int)
    assert near[2] > near[0] + 60 and far[0] > far[2]
    assert tuple(img[th // 8, 30]) == NO_POINT_BGR
    assert tuple(img[th // 8, img.shape[1] - 92 - 30]) == NO_POINT_BGR


@pytest.mark.parametrize("max_width_px", [1280, 800, 333])
def test_two_camera_preview_fits_the_width(max_width_px: int) -> None:
    d = _ramp(1024, 1280)
    img = render_preview([d, d], SID, max_width_px)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert max_width_px - 8 <= img.shape[1] - 4 - 90 <= max_width_px  # tiles and gap; (tile widths: whole px)
    tile_w = (img.shape[1] - 2 * 4 - 90) // 2
    assert abs(img.shape[0] / tile_w - 1024 / 1280) < 0.02  # aspect kept


def test_small_picture_is_not_scaled() -> None:
    img = render_preview([_ramp(100, 300)], "t")
    assert img.shape == (100, 300 + 4 + 90, 3)


def test_title_drawn_white_on_black() -> None:
    d = _ramp(400, 600)
    d[:] = 600.0  # no empty rows: the title sits on the depth colour
    plain = render_preview([d])
    a, b = render_preview([d], SID), render_preview([d], SID.replace("0012", "0013"))
    tw, th = text_size(SID, 2)
    box = (slice(4, 8 + th + 2), slice(4, 8 + tw + 4))
    assert not np.array_equal(a[box], b[box])  # the title changes the pixels in its box
    np.testing.assert_array_equal(a[:, 8 + tw + 4 :], plain[:, 8 + tw + 4 :])  # and nothing beside it
    np.testing.assert_array_equal(a[8 + th + 2 :], plain[8 + th + 2 :])
    colours = set(map(tuple, a[box].reshape(-1, 3)))
    assert colours == {(0, 0, 0), (255, 255, 255)}
    assert (a[box] == 255).all(axis=2).sum() > 8 * len(SID)  # ink, a fair amount per character


def test_scale_bar_ticks_and_labels() -> None:
    d = _ramp(200, 300)
    img = render_preview([d], "")
    h = img.shape[0]
    bar_h = int(0.8 * h)
    y0, x0, bar_w = (h - bar_h) // 2, 300 + 4 + 8, 24
    ramp = img[y0 : y0 + bar_h, x0 + 10]
    lut = depth_lut()
    np.testing.assert_array_equal(ramp[0], lut[255])  # near on top, as in the tiles
    np.testing.assert_array_equal(ramp[-1], lut[0])
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = y0 + int(frac * (bar_h - 1))
        assert (img[y, x0 + bar_w : x0 + bar_w + 5] == 0).all()  # tick
        label = img[y - 3 : y + 4, x0 + bar_w + 7 : x0 + bar_w + 7 + 18]
        assert (label == 0).all(axis=2).sum() > 10  # digits beside it
    assert (img[max(1, y0 - 11) : y0 - 4, x0 : x0 + 23] == 0).all(axis=2).sum() > 10  # "z mm" above the bar
