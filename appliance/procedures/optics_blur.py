"""The optics' blur, measured from fringe contrast at two periods: what the albedo-edge correction assumes.

A sinusoidal fringe of period ``p`` projector px loses contrast to blur: a Gaussian of sigma ``s`` (projector
px) keeps ``exp(-2 pi^2 s^2 / p^2)`` of it. The projector's defocus is in projector px; the camera's lens blur
``b`` (camera px) spreads the fringe over ``b g`` projector px, where ``g`` is the code's slope there
(projector px per camera px). So at the periods 24 and 12, on one pixel,

    ln(m24 / m12) / (2 pi^2 (1/12^2 - 1/24^2)) - 1/12 = s^2 + b^2 g^2,

where ``m`` is each fringe's contrast (its first harmonic over white - black: the albedo, the exposure and the
gain cancel in the ratio) and 1/12 the projector pixel's own width (px^2). Over a scene whose surfaces give
different slopes (a sphere, faces at different angles) the median of the left side in bins of ``g^2`` lies on
a line whose slope is the camera's ``b^2`` and whose intercept is the projector's ``s^2``. A scene of one flat
face has one slope and cannot tell them apart; then only their total along the code is known.

Only the inside of evenly lit surfaces counts: a pixel whose 7 x 7 neighbourhood is not all usable (an edge, a
shadow, a clipped or faint pixel) is left out, and so is one whose code slope changes across it (a depth or
slope edge). On the virtual rig's default scene with the camera blur alone (1.5 px) the binned medians lie
within 1.5 % of ``b^2 g^2``.

``reconstruction.edge_blur_px`` is the camera's ``b``: the albedo-edge correction pulls a dark pixel's code by
``b^2 grad(white) / white``, and its sigma grows with it. ``scan3d tune`` measures it with 8 more probe frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.patterns.sequence import PhaseFrame

PERIODS = (24.0, 12.0)
"""The probe's fringe periods (projector px), coarse first: the finer one keeps a fifth of its contrast at a
total blur of 3 projector px, the pair still tells 0.1 px^2 apart."""
STEPS = 4
"""Phase steps of each period."""
MIN_RANGE_DN = 20.0
"""A pixel is used when its white - black reaches this (DN) ..."""
CLIP_SHARE = 0.95
"""... none of its frames reaches this share of the sensor's full scale ..."""
MIN_CONTRAST = 0.1
"""... its finer fringe keeps at least this share of white - black ..."""
INSIDE_PX = 3
"""... every pixel within this many pixels of it is usable too (the inside of a surface) ..."""
MAX_SLOPE_CHANGE = 0.05
"""... and the code's slope (over the same window) a window's half to either side, and above and below, differs
by at most this share (no depth or slope edge across it)."""
MAX_SLOPE = 3.0
"""Code slopes above this (projector px per camera px) are left out (a period of 12 then spans 4 camera px)."""
SLOPE_BINS = 10
"""Bins of the squared slope (equal counts) whose median the line is fitted to."""
MIN_PIXELS = 2000
"""Fewest usable pixels for an estimate."""
MIN_SLOPE_RATIO = 1.6
"""The squared slopes of the outer bins must differ by at least this factor to tell camera from projector blur."""
_K = 2.0 * math.pi**2 * (1.0 / PERIODS[1] ** 2 - 1.0 / PERIODS[0] ** 2)
_PIXEL_VAR = 1.0 / 12.0


@dataclass(frozen=True)
class BlurEstimate:
    """One camera's blur, measured.

    Attributes
    ----------
    camera : str
        The camera's name.
    pixels : int
        Pixels the estimate used.
    total_px : float
        Median total blur sigma along the code (projector px).
    camera_px : float or None
        The camera's lens blur sigma (camera px); None when the scene's code slopes are too alike to separate it.
    projector_px : float or None
        The projector's defocus sigma (projector px); None likewise.
    slopes : (float, float)
        The code slope of the lowest and highest bins (projector px per camera px).
    """

    camera: str
    pixels: int
    total_px: float
    camera_px: float | None
    projector_px: float | None
    slopes: tuple[float, float]

    def line(self) -> str:
        """What the estimate says, in words."""
        if self.camera_px is None or self.projector_px is None:
            return (f"{self.camera}: optics blur sigma {self.total_px:.2f} projector px along the code in all; the "
                    f"surfaces give code slopes of {self.slopes[0]:.2f}-{self.slopes[1]:.2f} projector px per camera "
                    "px only, too alike to tell the camera's blur from the projector's (probe a part with curved "
                    "or differently tilted faces)")
        return (f"{self.camera}: camera blur sigma {self.camera_px:.2f} camera px, projector blur sigma "
                f"{self.projector_px:.2f} projector px (fringe contrast at periods 24 and 12 over code slopes "
                f"{self.slopes[0]:.2f}-{self.slopes[1]:.2f}, {self.pixels} pixels)")


def in_range(white: npt.NDArray[np.generic], black: npt.NDArray[np.generic],
             full_scale: float) -> npt.NDArray[np.bool_]:
    """Pixels lit well enough (white - black at least :data:`MIN_RANGE_DN`) and not clipped (white under
    :data:`CLIP_SHARE` of ``full_scale``) to measure a fringe's contrast; shape of ``white``."""
    wh = np.asarray(white, np.float32)
    return (wh - np.asarray(black, np.float32) >= MIN_RANGE_DN) & (wh < CLIP_SHARE * full_scale)


def fringe_frames() -> tuple[PhaseFrame, ...]:
    """The probe's frames: :data:`STEPS`-step fringes along x at each of :data:`PERIODS`."""
    return tuple(PhaseFrame("x", p, s, STEPS) for p in PERIODS for s in range(STEPS))


def estimate(camera: str, frames: npt.NDArray[np.generic], white: npt.NDArray[np.generic],
             black: npt.NDArray[np.generic], full_scale: float) -> BlurEstimate | None:
    """Measure a camera's blur from the frames of :func:`fringe_frames` (see the module docstring).

    Parameters
    ----------
    camera : str
        The camera's name (for the report).
    frames : ndarray, shape (8, H, W)
        The fringe frames (DN), in the order of :func:`fringe_frames`.
    white, black : ndarray, shape (H, W)
        The white and black images at the same exposure (DN).
    full_scale : float
        The sensor's largest value (DN).

    Returns
    -------
    BlurEstimate or None
        None when fewer than :data:`MIN_PIXELS` pixels are usable (a dark, clipped or empty scene).
    """
    import cv2

    # each fringe's first harmonic, a frame at a time (no float copy of the stack: a probe runs in the service)
    z1 = np.zeros(frames.shape[1:], np.complex64)
    z2 = np.zeros(frames.shape[1:], np.complex64)
    for i in range(2 * STEPS):
        term = np.complex64(np.exp(-2j * np.pi * (i % STEPS) / STEPS)) * np.asarray(frames[i], np.float32)
        if i < STEPS:
            z1 += term
        else:
            z2 += term
    rng = np.asarray(white, np.float32) - np.asarray(black, np.float32)
    a1, a2 = np.abs(z1), np.abs(z2)
    # 4 steps: |Z| = 2 x the fringe's amplitude = its contrast x (white - black)
    top = np.asarray(frames).max(axis=0)
    good = in_range(white, black, full_scale) & (top < CLIP_SHARE * full_scale)
    good &= a2 >= MIN_CONTRAST * rng
    side = 2 * INSIDE_PX + 1
    good = cv2.erode(good.astype(np.uint8), np.ones((side, side), np.uint8), borderValue=0).astype(bool)
    # the code's slope from the coarse fringe's phase: wrapped differences averaged over the window (noise in the
    # slope would flatten the fitted line), and the same window's slope on either side to find edges
    win = (side, side)
    px = np.zeros_like(z1)
    py = np.zeros_like(z1)
    px[:, 1:] = z1[:, 1:] * np.conj(z1[:, :-1])
    py[1:, :] = z1[1:, :] * np.conj(z1[:-1, :])
    mx = cv2.boxFilter(px.real, -1, win) + 1j * cv2.boxFilter(px.imag, -1, win)
    my = cv2.boxFilter(py.real, -1, win) + 1j * cv2.boxFilter(py.imag, -1, win)
    per = PERIODS[0] / (2.0 * np.pi)
    gx, gy = per * np.angle(mx), per * np.angle(my)
    g = np.hypot(gx, gy)
    h, w = g.shape
    r0, c0 = side, side  # the windows either side stay inside the image
    core = (slice(r0, h - r0), slice(c0, w - c0))
    gc = g[core]
    inner = good[core] & (gc > 0.05) & (gc <= MAX_SLOPE)
    lim = MAX_SLOPE_CHANGE * gc
    for dr, dc in ((0, INSIDE_PX), (INSIDE_PX, 0)):
        a = (slice(r0 - dr, h - r0 - dr), slice(c0 - dc, w - c0 - dc))
        b = (slice(r0 + dr, h - r0 + dr), slice(c0 + dc, w - c0 + dc))
        inner &= (np.abs(gx[a] - gx[b]) <= lim) & (np.abs(gy[a] - gy[b]) <= lim)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.log(a1[core][inner] / a2[core][inner]).astype(np.float64) / _K - _PIXEL_VAR
    g2 = gc[inner].astype(np.float64) ** 2
    ok = np.isfinite(y)
    g2, y = g2[ok], y[ok]
    if g2.size < MIN_PIXELS:
        return None
    parts = np.array_split(np.argsort(g2), SLOPE_BINS)
    xs = np.array([np.median(g2[p]) for p in parts])
    ys = np.array([np.median(y[p]) for p in parts])
    total = math.sqrt(max(float(np.median(y)), 0.0))
    slopes = (math.sqrt(float(xs[0])), math.sqrt(float(xs[-1])))
    if xs[-1] < MIN_SLOPE_RATIO * xs[0]:
        return BlurEstimate(camera, int(g2.size), total, None, None, slopes)
    b2, a = np.polyfit(xs, ys, 1)
    return BlurEstimate(camera, int(g2.size), total, math.sqrt(max(float(b2), 0.0)), math.sqrt(max(float(a), 0.0)),
                        slopes)
