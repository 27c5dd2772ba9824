"""Preview PNG of a scan: depth in colour with a labelled scale bar."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.reconstruct.types import PointCloud

PERCENTILE_SAMPLES = 100_000
"""The colour range (1st to 99th percentile of depth) is taken from about this many evenly spaced points."""
CHUNK_POINTS = 131_072
"""Points (and preview rows, times 1/8) handled at a time: the preview's temporaries stay a few MB."""
NO_POINT_BGR = (40, 40, 40)
"""Colour of pixels without a point."""


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


def render_preview(
    depths: list[npt.NDArray[np.float32]], title: str = "", max_width_px: int = 1280
) -> npt.NDArray[np.uint8]:
    """Colour image (BGR uint8) of one or more depth maps side by side, with a scale bar in mm.

    Parameters
    ----------
    depths : list of ndarray, shape (H, W), float32
        Depth maps (mm), NaN where empty.
    title : str
        Text drawn at the top left.
    max_width_px : int
        The picture is scaled down to at most this width (px).
    """
    import cv2

    lo, hi = _colour_range(depths)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, :]
    gap, margin = 4, 90
    full_w = sum(d.shape[1] for d in depths) + gap * (len(depths) - 1)
    scale = min(1.0, max_width_px / full_w)
    # tiles are coloured straight into the canvas (at full size) or one at a time, then scaled into it
    sizes = [(d.shape[1], d.shape[0]) if scale == 1.0 else
             (max(1, round(d.shape[1] * scale)), max(1, round(d.shape[0] * scale))) for d in depths]  # fmt: skip
    h = max(sz[1] for sz in sizes)
    w = sum(sz[0] for sz in sizes) + gap * (len(depths) - 1)
    canvas = np.full((h, w + gap + margin, 3), 255, np.uint8)
    canvas[:, : w + gap] = 0
    x = 0
    for d, (sw, sh) in zip(depths, sizes, strict=True):
        if scale == 1.0:
            _colour_into(d, lo, hi, lut, canvas[:sh, x : x + sw])
        else:
            tile = np.empty((*d.shape, 3), np.uint8)
            _colour_into(d, lo, hi, lut, tile)
            canvas[:sh, x : x + sw] = cv2.resize(tile, (sw, sh), interpolation=cv2.INTER_AREA)
            del tile
        x += sw + gap
    bar_h, bar_w = int(h * 0.8), 24
    ramp = np.linspace(255, 0, bar_h).astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)  # same mapping as the tiles: near = warm
    y0 = (h - bar_h) // 2
    x0 = w + gap + 8
    canvas[y0 : y0 + bar_h, x0 : x0 + bar_w] = bar
    font = cv2.FONT_HERSHEY_SIMPLEX
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = y0 + int(frac * (bar_h - 1))
        val = lo + frac * (hi - lo)
        cv2.line(canvas, (x0 + bar_w, y), (x0 + bar_w + 4, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"{val:.0f}", (x0 + bar_w + 6, y + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, "z mm", (x0, max(12, y0 - 6)), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    if title:
        (tw, th), base = cv2.getTextSize(title, font, 0.55, 1)
        cv2.rectangle(canvas, (4, 20 - th - 4), (12 + tw, 20 + base + 2), (0, 0, 0), -1)  # legible on any colour
        cv2.putText(canvas, title, (8, 20), font, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


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
