"""Preview PNG of a scan: depth in colour with a labelled scale bar."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from appliance.reconstruct.types import PointCloud

PERCENTILE_SAMPLES = 100_000
"""The colour range (1st to 99th percentile of depth) is taken from about this many evenly spaced points."""


def depth_image(cloud: PointCloud, camera: int, shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    """Organised depth (world z, mm) of the points of one camera; NaN where no point. Shape ``shape`` (H, W)."""
    img = np.full(shape, np.nan, np.float32)
    if len(cloud) and cloud.camera[0] == camera and not np.any(cloud.camera != camera):
        img[cloud.row, cloud.col] = cloud.xyz[:, 2]  # one camera (the common case): no selection copies
    else:
        sel = cloud.camera == camera
        img[cloud.row[sel], cloud.col[sel]] = cloud.xyz[sel, 2]
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

    finite = np.concatenate([d[np.isfinite(d)] for d in depths]) if depths else np.zeros(0, np.float32)
    if finite.size:
        sample = finite[:: max(1, finite.size // PERCENTILE_SAMPLES)]  # a colour range needs no exact percentile
        lo, hi = (float(v) for v in np.percentile(sample, [1, 99]))
    else:
        lo, hi = 0.0, 1.0
    if hi - lo < 1e-3:
        hi = lo + 1.0
    tiles = []
    for d in depths:
        norm = np.clip((np.nan_to_num(d, nan=lo) - lo) / (hi - lo), 0, 1)
        col = cv2.applyColorMap((255 - norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        col[~np.isfinite(d)] = (40, 40, 40)
        tiles.append(col)
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 4), (0, 0))) for t in tiles]
    img = np.concatenate(tiles, axis=1)
    scale = min(1.0, max_width_px / img.shape[1])
    if scale < 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    # scale bar: a column of the colour map, labelled with its depth range
    bar_h, bar_w, margin = int(img.shape[0] * 0.8), 24, 90
    canvas = np.full((img.shape[0], img.shape[1] + margin, 3), 255, np.uint8)
    canvas[:, : img.shape[1]] = img
    ramp = np.linspace(255, 0, bar_h).astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)  # same mapping as the tiles: near = warm
    y0 = (img.shape[0] - bar_h) // 2
    x0 = img.shape[1] + 8
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
