"""Preview PNG of a scan: depth in colour with a labelled scale bar, and why pixels have no point.

Where a camera pixel has no point and its reason map (:class:`appliance.reconstruct.types.Reason`) says why,
the tile shows diagonal stripes in the reason's colour over the no-point grey (stripes, so a reason is never
read as a depth), and a legend under the tiles gives each reason's colour and share of the image.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.output.font import CAP_H, LINE_H, draw_text, text_size
from appliance.reconstruct.types import PointCloud, Reason

PERCENTILE_SAMPLES = 100_000
"""The colour range (1st to 99th percentile of depth) is taken from about this many evenly spaced points."""
CHUNK_POINTS = 131_072
"""Points (and preview rows, times 1/8) handled at a time: the preview's temporaries stay a few MB."""
NO_POINT_BGR = (40, 40, 40)
"""Colour of pixels without a point."""
MIN_COVERAGE = 0.5
"""A scaled-down pixel holds a depth when at least this fraction of the area it covers has one."""

REASON_STYLE: dict[int, tuple[str, tuple[int, int, int]]] = {
    Reason.SHADOW: ("shadow", NO_POINT_BGR),
    Reason.TOO_DARK: ("too dark", (255, 90, 140)),
    Reason.SATURATED: ("saturated", (255, 255, 255)),
    Reason.WEAK_CODE: ("weak/inconsistent code", (255, 0, 255)),
    Reason.NOT_MATCHED: ("not matched", (255, 255, 0)),
    Reason.OUT_OF_RANGE: ("out of range", (0, 255, 255)),
    Reason.FILTERED: ("filtered", (0, 140, 255)),
    Reason.EPIPOLAR: ("off epipolar line", (0, 0, 255)),
    Reason.MIXED: ("next to clipped", (200, 200, 200)),
    Reason.INTERREFLECTION: ("two patterns", (0, 200, 0)),
    Reason.HIDDEN: ("hidden from projector", (255, 0, 0)),
    Reason.EDGE: ("shadow/silhouette edge", (30, 105, 160)),
}
"""Per reason a pixel has no point: its legend label and stripe colour (BGR). Shadow is the plain no-point grey
(nothing to fix); a reason missing here is drawn in :data:`OTHER_REASON_BGR`."""
OTHER_REASON_BGR = (128, 128, 128)
"""Stripe colour of a reason :data:`REASON_STYLE` does not name."""
STRIPE_PX = 3
"""Width of the reason stripes (px of the preview)."""

_COLOUR_ANCHORS = (
    (0.00, (30, 15, 90)), (0.12, (45, 70, 210)), (0.30, (20, 195, 225)), (0.45, (60, 215, 75)),
    (0.60, (225, 225, 40)), (0.74, (250, 150, 25)), (0.87, (215, 45, 20)), (1.00, (125, 10, 10)),
)  # fmt: skip
"""Colour map anchors: (position in [0, 1], RGB), far (dark blue) to near (dark red), linear in between."""


def depth_image(cloud: PointCloud, camera: int, shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    """Organised depth (world z, mm) of the points of one camera; NaN where no point. Shape ``shape`` (H, W).

    Filled :data:`CHUNK_POINTS` points at a time: indexing with the cloud's whole int32 row and column arrays
    would first convert both to int64 (16 B per point, 20 MB for 1.25 M points).
    """
    img = np.full(shape, np.nan, np.float32)
    flat = img.ravel()
    width = shape[1]
    for start in range(0, len(cloud), CHUNK_POINTS):
        stop = min(start + CHUNK_POINTS, len(cloud))
        cam = cloud.camera[start:stop]
        sel = slice(None) if not np.any(cam != camera) else cam == camera
        idx = cloud.row[start:stop][sel].astype(np.intp)
        idx *= width
        idx += cloud.col[start:stop][sel]
        flat[idx] = cloud.xyz[start:stop, 2][sel]
    return img


@functools.cache
def depth_lut() -> npt.NDArray[np.uint8]:
    """The preview's colour map: 256 BGR colours, index 0 far (dark blue) to 255 near (dark red).

    Returns
    -------
    ndarray, shape (256, 3), uint8
        Read-only; interpolated linearly between the anchors of ``_COLOUR_ANCHORS``.
    """
    pos = np.array([p for p, _ in _COLOUR_ANCHORS])
    rgb = np.array([c for _, c in _COLOUR_ANCHORS], np.float64)
    t = np.arange(256) / 255.0
    lut = np.rint(np.stack([np.interp(t, pos, rgb[:, ch]) for ch in (2, 1, 0)], axis=1)).astype(np.uint8)
    lut.flags.writeable = False
    return lut


def downscale_depth(depth: npt.NDArray[np.float32], shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    """Scale a depth map down by area averaging, ignoring empty pixels.

    Output pixel (i, j) covers the source rectangle ``[i * H / h, (i + 1) * H / h) x [j * W / w, (j + 1) * W / w)``;
    each source pixel counts with the exact area it shares with it. The result is the weighted mean of the
    finite depths there, or NaN when they cover less than :data:`MIN_COVERAGE` of the rectangle. Worked a block
    of rows at a time (float64 sums for the block only).

    Parameters
    ----------
    depth : ndarray, shape (H, W), float32
        Depth (mm), NaN where empty.
    shape : (int, int)
        ``(h, w)`` of the result (px), ``1 <= h <= H``, ``1 <= w <= W``.

    Returns
    -------
    ndarray, shape (h, w), float32
        Depth (mm), NaN where empty.
    """
    if not isinstance(depth, np.ndarray) or depth.dtype != np.float32 or depth.ndim != 2:
        got = f"{depth.dtype} {depth.shape}" if isinstance(depth, np.ndarray) else type(depth).__name__
        raise ValueError(f"depth = {got}: must be a 2-D float32 array")
    big_h, big_w = depth.shape
    h, w = shape
    if not (1 <= h <= big_h and 1 <= w <= big_w):
        raise ValueError(f"shape = {shape}: must be (h, w) with 1 <= h <= {big_h} and 1 <= w <= {big_w}")
    col_idx, col_wt = _area_taps(big_w, w)
    row_idx, row_wt = _area_taps(big_h, h)
    min_area = MIN_COVERAGE * (big_h / h) * (big_w / w)
    out = np.empty((h, w), np.float32)
    step = max(1, CHUNK_POINTS * h // (big_h * big_w))  # output rows per block (about CHUNK_POINTS source px)
    for o0 in range(0, h, step):
        o1 = min(o0 + step, h)
        n = o1 - o0
        s0, s1 = int(row_idx[:, o0:o1].min()), int(row_idx[:, o0:o1].max()) + 1
        src = depth[s0:s1]
        finite = np.isfinite(src)
        vals = np.where(finite, src, np.float32(0))
        # across the rows (whole rows: cheap copies), then along them: sums of depth and of finite area
        col_sum, col_area, tmp = np.zeros((n, big_w)), np.zeros((n, big_w)), np.empty((n, big_w))
        for idx, wt in zip(row_idx[:, o0:o1] - s0, row_wt[:, o0:o1, None], strict=True):
            col_sum += np.multiply(vals[idx], wt, out=tmp)
            col_area += np.multiply(finite[idx], wt, out=tmp)
        total, area, tmp = np.zeros((n, w)), np.zeros((n, w)), np.empty((n, w))
        for idx, wt in zip(col_idx, col_wt, strict=True):
            total += np.multiply(np.take(col_sum, idx, axis=1), wt, out=tmp)
            area += np.multiply(np.take(col_area, idx, axis=1), wt, out=tmp)
        empty = area < min_area
        area[empty] = 1.0
        total /= area
        total[empty] = np.nan
        out[o0:o1] = total
    return out


def render_preview(
    depths: list[npt.NDArray[np.float32]],
    title: str = "",
    max_width_px: int = 1280,
    reasons: list[npt.NDArray[np.uint8] | None] | None = None,
) -> npt.NDArray[np.uint8]:
    """Colour image (BGR uint8) of one or more depth maps side by side, with a scale bar in mm, and where
    ``reasons`` are given, why pixels have no point.

    Parameters
    ----------
    depths : list of ndarray, shape (H, W), float32
        Depth maps (mm), NaN where empty.
    title : str
        Text drawn at the top left, white on black (:mod:`appliance.output.font` at twice its size).
    max_width_px : int
        The tiles are scaled down (:func:`downscale_depth`) so that they and the 4-px gaps between them are
        at most this wide (px), at least 1 px a tile; the scale bar adds 94 px beside them. One camera up to
        this width is drawn at full size (no resampling).
    reasons : list of (ndarray, shape (H, W), uint8, or None), optional
        Per depth map, the camera's reason map (:class:`appliance.reconstruct.types.Reason`, 0 = decoded),
        or None. A pixel without a depth whose reason is not 0 is striped in the reason's colour
        (:data:`REASON_STYLE`, sampled at the tile's nearest source pixel), and a legend under the tiles gives
        each reason present with its share of the images' pixels (%).

    Returns
    -------
    ndarray, shape (H', W', 3), uint8
        The picture: tiles (near = warm, :data:`NO_POINT_BGR` where empty) on black, 4 px apart, then the
        scale bar on white; the reasons' legend below when there is one.
    """
    if reasons is not None and len(reasons) != len(depths):
        raise ValueError(f"reasons: {len(reasons)} maps for {len(depths)} depth maps; give one (or None) each")
    lo, hi = _colour_range(depths)
    lut = depth_lut()
    gap, margin = 4, 90
    room = max_width_px - gap * (len(depths) - 1)  # for the tiles: less the gaps between them
    scale = min(1.0, max(1, room) / sum(d.shape[1] for d in depths))
    sizes = [(d.shape[1], d.shape[0]) if scale == 1.0 else
             (max(1, int(d.shape[1] * scale)), max(1, round(d.shape[0] * scale))) for d in depths]  # fmt: skip
    h = max(sz[1] for sz in sizes)
    w = sum(sz[0] for sz in sizes) + gap * (len(depths) - 1)
    canvas = np.full((h, w + gap + margin, 3), 255, np.uint8)
    canvas[:, : w + gap] = 0
    x = 0
    for i, (d, (sw, sh)) in enumerate(zip(depths, sizes, strict=True)):
        small = d if (sh, sw) == d.shape else downscale_depth(d, (sh, sw))
        _colour_into(small, lo, hi, lut, canvas[:sh, x : x + sw])
        reason = None if reasons is None else reasons[i]
        if reason is not None:
            _stripe_reasons(small, reason, canvas[:sh, x : x + sw])
        del small
        x += sw + gap
    black, white = (0, 0, 0), (255, 255, 255)
    bar_h, bar_w = int(h * 0.8), 24
    y0 = (h - bar_h) // 2
    x0 = w + gap + 8
    ramp = np.linspace(255, 0, bar_h).astype(np.uint8)  # same mapping as the tiles: near (top) = warm
    canvas[y0 : y0 + bar_h, x0 : x0 + bar_w] = lut[ramp][:, None, :]
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = y0 + int(frac * (bar_h - 1))
        if 0 <= y < h:
            canvas[y, x0 + bar_w : x0 + bar_w + 5] = black
        draw_text(canvas, f"{lo + frac * (hi - lo):.0f}", x0 + bar_w + 7, y - CAP_H // 2, black)
    draw_text(canvas, "z mm", x0, max(1, y0 - 4 - CAP_H), black)
    if title:
        tw, th = text_size(title, 2)
        canvas[4 : 8 + th + 2, 4 : 8 + tw + 4] = black  # legible on any colour
        draw_text(canvas, title, 8, 8, white, 2)
    if reasons is not None:
        canvas = _with_legend(canvas, [r for r in reasons if r is not None])
    return canvas


def reason_colour(reason: int) -> tuple[int, int, int]:
    """The stripe colour (BGR) of a :class:`appliance.reconstruct.types.Reason` value in the preview."""
    style = REASON_STYLE.get(reason)
    return OTHER_REASON_BGR if style is None else style[1]


@functools.cache
def _reason_lut() -> npt.NDArray[np.uint8]:
    """(256, 3) BGR stripe colour of every reason value (:func:`reason_colour`), read-only."""
    lut = np.array([reason_colour(v) for v in range(256)], np.uint8)
    lut.flags.writeable = False
    return lut


def _stripe_reasons(small: npt.NDArray[np.float32], reason: npt.NDArray[np.uint8], out: npt.NDArray[Any]) -> None:
    """Stripe the tile ``out`` (h, w, 3) where ``small`` (h, w) has no depth, by the reason map (H, W) sampled at
    each tile pixel's nearest source pixel: the reason's colour on every other :data:`STRIPE_PX`-wide diagonal."""
    h, w = small.shape
    big_h, big_w = reason.shape
    rows = ((np.arange(h) + 0.5) * (big_h / h)).astype(np.intp)
    cols = ((np.arange(w) + 0.5) * (big_w / w)).astype(np.intp)
    colour = _reason_lut()
    step = max(1, CHUNK_POINTS // 8 // max(1, w))  # a block of rows at a time: no full-size temporaries
    diag = np.arange(w, dtype=np.int32)
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        stripe = ((np.arange(r0, r1, dtype=np.int32)[:, None] + diag) // STRIPE_PX) % 2 == 0
        sampled = reason[rows[r0:r1]][:, cols]
        paint = stripe & ~np.isfinite(small[r0:r1]) & (sampled != Reason.DECODED)
        out[r0:r1][paint] = colour[sampled[paint]]


def _with_legend(canvas: npt.NDArray[np.uint8], reasons: list[npt.NDArray[np.uint8]]) -> npt.NDArray[np.uint8]:
    """``canvas`` with a legend strip below: a swatch, the label and the share (% of all pixels of ``reasons``)
    of each reason present, in :class:`Reason` order, wrapped to the canvas's width (widened for one entry)."""
    total = sum(r.size for r in reasons)
    counts = np.zeros(256, np.int64)
    for r in reasons:
        counts += np.bincount(r.ravel(), minlength=256)[:256]
    entries = [(f"{REASON_STYLE[v][0] if v in REASON_STYLE else f'reason {v}'} {100.0 * counts[v] / total:.1f} %",
                reason_colour(v)) for v in range(1, 256) if counts[v]]  # fmt: skip
    if not entries:
        return canvas
    swatch, pad = 10, 12
    widths = [swatch + 4 + text_size(label)[0] for label, _ in entries]
    width = max(canvas.shape[1], max(widths) + 2 * pad)
    lines: list[list[int]] = [[]]
    x = pad
    for i, wd in enumerate(widths):
        if lines[-1] and x + wd > width - pad:
            lines.append([])
            x = pad
        lines[-1].append(i)
        x += wd + pad
    row_h = LINE_H + 6
    out = np.full((canvas.shape[0] + 4 + row_h * len(lines), width, 3), 255, np.uint8)
    out[: canvas.shape[0], : canvas.shape[1]] = canvas
    for n, line in enumerate(lines):
        y = canvas.shape[0] + 4 + n * row_h + 3
        x = pad
        for i in line:
            label, colour = entries[i]
            out[y : y + CAP_H + 1, x : x + swatch] = (0, 0, 0)
            out[y + 1 : y + CAP_H, x + 1 : x + swatch - 1] = colour
            draw_text(out, label, x + swatch + 4, y, (0, 0, 0))
            x += widths[i] + pad
    return out


def _area_taps(n_in: int, n_out: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.float64]]:
    """Source indices and overlaps (px) of each output pixel of an area scaling ``n_in`` -> ``n_out``, both
    (K, n_out): output pixel j covers ``[j * n_in / n_out, (j + 1) * n_in / n_out)``; unused taps weigh 0."""
    j = np.arange(n_out + 1)
    edge = j * n_in / n_out  # exact at whole pixels (integer product, one division)
    a, b = edge[:-1], edge[1:]
    first = np.floor(a).astype(np.intp)
    last = np.minimum(np.ceil(b).astype(np.intp), n_in) - 1
    idx = first + np.arange(int((last - first).max()) + 1)[:, None]
    weight = np.clip(np.minimum(b, idx + 1) - np.maximum(a, idx), 0.0, None)
    return np.minimum(idx, n_in - 1), weight


def _colour_into(
    d: npt.NDArray[np.float32], lo: float, hi: float, lut: npt.NDArray[Any], out: npt.NDArray[Any]
) -> None:
    """Colour the depth map ``d`` (H, W, mm) into ``out`` (H, W, 3) BGR through ``lut`` (256, 3), near = warm,
    a block of rows at a time: index ``255 - 255 * clip((z - lo) / (hi - lo), 0, 1)`` (float32, truncated);
    :data:`NO_POINT_BGR` where NaN."""
    rows = max(1, CHUNK_POINTS // 8 // max(1, d.shape[1]) * 8)
    for r0 in range(0, d.shape[0], rows):
        block = d[r0 : r0 + rows]
        norm = np.nan_to_num(block, nan=lo)
        norm -= np.float32(lo)
        norm /= np.float32(hi - lo)
        np.clip(norm, 0, 1, out=norm)
        norm *= np.float32(255)
        np.subtract(np.float32(255), norm, out=norm)
        tile = out[r0 : r0 + block.shape[0]]
        tile[...] = lut[norm.astype(np.uint8)]
        tile[~np.isfinite(block)] = NO_POINT_BGR


def _colour_range(depths: list[npt.NDArray[np.float32]]) -> tuple[float, float]:
    """1st and 99th percentile (mm) of about :data:`PERCENTILE_SAMPLES` evenly spaced finite depths: every
    ``n // PERCENTILE_SAMPLES``-th of the ``n`` finite values in raster order, gathered a block of rows at a time
    (no copy of all finite values); (0, 1) when there is none, at least 1e-3 apart."""
    counts = [int(np.count_nonzero(np.isfinite(d))) for d in depths]
    n = sum(counts)
    if n == 0:
        return 0.0, 1.0
    step = max(1, n // PERCENTILE_SAMPLES)
    parts: list[npt.NDArray[np.float32]] = []
    skip = 0  # finite values still to pass before the next sample
    for d in depths:
        rows = max(1, CHUNK_POINTS // max(1, d.shape[1]))
        for r0 in range(0, d.shape[0], rows):
            block = d[r0 : r0 + rows]
            vals = block[np.isfinite(block)]
            if skip < vals.size:
                parts.append(vals[skip::step])
                skip = (skip - vals.size) % step
            else:
                skip -= vals.size
    lo, hi = (float(v) for v in np.percentile(np.concatenate(parts), [1, 99]))
    return lo, (lo + 1.0 if hi - lo < 1e-3 else hi)
