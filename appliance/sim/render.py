"""Photometry of the virtual rig: projector light at exact projector coordinates, camera blur, noise, ADC.

The projector image is never rasterised. For a camera pixel that sees projector coordinates ``(u, v)``
(pixel centres at integers) the light of a frame is evaluated analytically:

- Gray bit: the bit of ``floor((u + 0.5) / stripe)``'s Gray code (exactly the projector pixels of
  :func:`appliance.patterns.render.frame_profile`), its edges blurred by the projector defocus, a Gaussian
  of sigma ``projector_blur_px``: a sum of ``Φ`` terms over the nearby edges (Φ tabulated to 3e-7). An XOR
  code frame (``xor_with``): the two blurred bits ``a``, ``b`` combined as ``a + b - 2ab``.
- Phase step: ``(1 + m cos(2π u / P + offset + 2π step / steps)) / 2`` with
  ``m = sinc(1 / P) exp(-2π² σ² / P²)``: the fundamental of the pixelated, blurred sinusoid. The pixel
  aliases it leaves out (frequencies ``1 ± 1/P``) are 1.3e-4 of the modulation for ``P = 16``,
  ``σ = 0.6`` (a phase ripple of 3e-4 projector px), 3.5e-3 for ``P = 8``, ``σ = 0.5``.
- White / black: 1 / 0. Every frame is multiplied by the blurred edge of the projector's image.

With ``gamma_corrected`` false the light is raised to ``projector_gamma`` after the blur (an
approximation of blurring the gamma-distorted pixels). The camera sees
``DN = ambient_dn * albedo + projector_gain_dn * albedo * cos(incidence) * light`` (Lambertian),
blurred by the camera defocus (Gaussian, ``camera_blur_px``), plus read and shot noise (Gaussian
with variance ``read_noise_dn² + DN / electrons_per_dn``, the normal limit of Poisson counts), then
rounded and clipped to the ADC range. Photometric quantities are on the 8-bit scale; a 12- or 16-bit
camera multiplies them by ``2**(bit_depth - 8)``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.config.schema import ImagingConfig
from appliance.errors import PatternError
from appliance.patterns.sequence import BlackFrame, Frame, GrayFrame, PhaseFrame, WhiteFrame
from appliance.sim import _sim_kernels as _k

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
ImageArray = npt.NDArray[np.unsignedinteger[Any]]
"""A camera image: uint8 (8-bit camera) or uint16 (12/16-bit)."""

_WHITE, _BLACK, _GRAY, _PHASE = 0, 1, 2, 3

Layer = tuple[F64, F32]
"""A second light path to the camera pixels (e.g. by a mirror): projector coordinates (H, W, 2) px and the
DN of full projector light along it (H, W) (8-bit scale, 0 where the path does not exist)."""


@dataclass(frozen=True)
class FrameLight:
    """Parameters of a frame's projected light for the shading kernel (see the module docstring)."""

    kind: int
    axis: str = "x"
    stripe: float = 1.0
    bit: int = 0
    inverted: bool = False
    xor_with: int = -1
    freq: float = 0.0
    phase0: float = 0.0
    modulation: float = 1.0


def frame_light(frame: Frame, projector_blur_px: float) -> FrameLight:
    """Analytic light parameters of ``frame`` for a projector blur of sigma ``projector_blur_px`` (px)."""
    if isinstance(frame, WhiteFrame):
        return FrameLight(_WHITE)
    if isinstance(frame, BlackFrame):
        return FrameLight(_BLACK)
    if isinstance(frame, GrayFrame):
        xor = -1 if frame.xor_with is None else frame.xor_with
        return FrameLight(_GRAY, frame.axis, float(frame.stripe), frame.bit, frame.inverted, xor)
    if isinstance(frame, PhaseFrame):
        f = 1.0 / frame.period
        sinc = math.sin(math.pi * f) / (math.pi * f)
        mod = sinc * math.exp(-2.0 * math.pi**2 * projector_blur_px**2 * f * f)
        return FrameLight(_PHASE, frame.axis, freq=2.0 * math.pi * f,
                          phase0=frame.offset + 2.0 * math.pi * frame.step / frame.steps, modulation=mod)
    raise PatternError(
        f"virtual rig: frame kind {frame.pattern!r} is not known; cannot render it "
        "(use gray, phase, white, black)"
    )


def projected_light(frame: Frame, u: F64, v: F64, width: int, height: int, projector_blur_px: float = 0.0,
                    gamma: float = 1.0) -> F64:
    """Relative projector light of ``frame`` at exact projector coordinates.

    Parameters
    ----------
    frame : Frame
        Gray, phase, white or black frame.
    u, v : ndarray, shape (N,)
        Projector coordinates (px; pixel centres at integers).
    width, height : int
        Projector size (px); light falls off at its (blurred) edges.
    projector_blur_px : float
        Projector defocus, Gaussian sigma (projector px).
    gamma : float
        Exponent applied to the light (1 for a gamma-corrected pattern).

    Returns
    -------
    ndarray, shape (N,), float64 in [0, 1]
    """
    uu = np.ascontiguousarray(np.asarray(u, dtype=np.float64).ravel())
    vv = np.ascontiguousarray(np.asarray(v, dtype=np.float64).ravel())
    if uu.shape != vv.shape:
        raise ValueError(f"u has {uu.size} values and v {vv.size}: must be equal")
    win = np.empty(uu.size)
    with _k.KERNEL_LOCK:
        _k.projector_window(uu, vv, width, height, projector_blur_px, win)
    coord = np.nan_to_num(uu if frame_light(frame, 0.0).axis == "x" else vv, nan=-1e6)
    out = np.empty(uu.size)
    _shade(frame, coord, win, np.zeros(uu.size), projector_blur_px, gamma, out)
    return out


def _shade(frame: Frame, coord: F64 | F32, gain: F64 | F32, ambient: F64 | F32, sigma: float, gamma: float,
           out: F64 | F32) -> None:
    """Noise-free DN ``ambient + gain * light ** gamma`` of ``frame`` at projector coordinates ``coord``."""
    with _k.KERNEL_LOCK:
        _shade_locked(frame, coord, gain, ambient, sigma, gamma, out)


def _shade_locked(frame: Frame, coord: F64 | F32, gain: F64 | F32, ambient: F64 | F32, sigma: float,
                  gamma: float, out: F64 | F32) -> None:
    fl = frame_light(frame, sigma)
    if fl.kind in (_WHITE, _BLACK):
        _k.shade_const(1.0 if fl.kind == _WHITE else 0.0, gain, ambient, gamma, out)
    elif fl.kind == _GRAY and fl.xor_with >= 0:
        _k.shade_gray_xor(coord, gain, ambient, fl.stripe, fl.bit, fl.xor_with, fl.inverted, sigma, gamma, out)
    elif fl.kind == _GRAY:
        _k.shade_gray(coord, gain, ambient, fl.stripe, fl.bit, fl.inverted, sigma, gamma, out)
    else:
        mc = fl.modulation * math.cos(fl.phase0)
        ms = fl.modulation * math.sin(fl.phase0)
        _k.shade_phase(coord, fl.freq / (2.0 * math.pi), _k.TRIG, gain, ambient, mc, ms, gamma, out)


class FrameRenderer:
    """Renders frames for one camera from its precomputed per-pixel geometry; owns its buffers.

    Parameters
    ----------
    proj_uv : ndarray, shape (H, W, 2)
        Projector coordinates seen by each camera pixel (px; anything where ``gain`` is 0).
    gain : ndarray, shape (H, W)
        DN of full projector light at each pixel (8-bit scale; 0 where unlit).
    ambient : ndarray, shape (H, W)
        DN of the ambient light at each pixel (8-bit scale).
    imaging : ImagingConfig
        Blur, gamma, noise and ADC settings.
    axes : frozenset of str, optional
        Projector axes to keep coordinates of (default both).
    layers : sequence of Layer, optional
        Further light paths (one-bounce mirror light), each with its own projector coordinates and gain;
        their light adds to the direct light before blur, noise and clipping.
    margin : int, optional
        Pixels beyond the image on each side that the arrays cover (see :func:`blur_margin`): the camera's blur
        reads the scene there, as a lens does, and the image is the inner (H - 2 margin, W - 2 margin) part.

    Notes
    -----
    Phase frames evaluate ``cos`` and ``sin`` of ``2π u / P`` from a shared 65 536-step table by linear
    interpolation (1.2e-9), not from per-pixel tables. Thread-safe: one lock serialises renders of this
    camera.
    """

    def __init__(self, proj_uv: F64, gain: F64 | F32, ambient: F64 | F32, imaging: ImagingConfig,
                 axes: frozenset[str] | None = None, layers: Sequence[Layer] = (), margin: int = 0) -> None:
        h, w = gain.shape
        self.margin = int(margin)
        self.height, self.width = h - 2 * self.margin, w - 2 * self.margin
        self._inner: F32 = (np.empty((self.height, self.width), np.float32) if self.margin
                            else np.empty((0, 0), np.float32))  # fmt: skip
        self.imaging = imaging
        self.axes = frozenset(("x", "y")) if axes is None else frozenset(axes)
        """The projector axes this renderer can render coded frames of."""
        # float32 coordinates (1e-4 px apart at 1280 px, far below the projector blur; half the memory of
        # float64: 5 MB an axis of a 1280x1024 camera), one axis at a time (no float64 copy of both), only
        # of the axes asked for
        self._coord = {axis: np.nan_to_num(np.asarray(proj_uv[..., k], dtype=np.float32), nan=-1e6).ravel()
                       for k, axis in enumerate(("x", "y")) if axis in self.axes}  # fmt: skip
        self._no_coord = np.zeros(0, np.float32)  # white and black frames read no coordinate
        self._gain = np.ascontiguousarray(gain, dtype=np.float32).ravel()
        self._ambient = np.ascontiguousarray(ambient, dtype=np.float32).ravel()
        self._clean = np.empty((h, w), dtype=np.float32)
        self._layers = [({axis: np.nan_to_num(np.asarray(luv[..., k], dtype=np.float32), nan=-1e6).ravel()
                          for k, axis in enumerate(("x", "y")) if axis in self.axes},
                         np.ascontiguousarray(lgain, dtype=np.float32).ravel())
                        for luv, lgain in layers]  # fmt: skip
        if self._layers:  # scratch of the layers' light, and their (zero) ambient
            self._layer_buf = np.empty(h * w, dtype=np.float32)
            self._zero = np.zeros(h * w, dtype=np.float32)
        self._lock = threading.Lock()
        self.dtype: type[np.uint8] | type[np.uint16] = np.uint8 if imaging.bit_depth == 8 else np.uint16
        self._scale = float(2 ** (imaging.bit_depth - 8))
        self._full = float(2**imaging.bit_depth - 1)
        self._gamma = 1.0 if imaging.gamma_corrected else float(imaging.projector_gamma)
        blur = imaging.camera_blur_px
        self._blur_passes: int
        self._blur_w: npt.NDArray[np.float32]
        self._blur_passes, self._blur_w = _k.gaussian_passes(blur) if blur > 0 else (0, np.ones(1, np.float32))
        self._blur_scratch: F32 = _k.blur_scratch(h, w) if blur > 0 else np.empty((1, 1), np.float32)

    def _blur(self, img: F32) -> None:
        """The camera defocus, in place (a Gaussian of sigma ``camera_blur_px``; borders replicated, so the margin
        beyond the image, when there is one, takes what replication would get wrong)."""
        for _ in range(self._blur_passes):
            with _k.KERNEL_LOCK:
                _k.gaussian_blur_inplace(img, self._blur_w, self._blur_scratch)

    def _clean_into(self, frame: Frame) -> F32:
        fl = frame_light(frame, self.imaging.projector_blur_px)
        if fl.kind in (_WHITE, _BLACK):
            coord = self._no_coord
        elif fl.axis in self._coord:
            coord = self._coord[fl.axis]
        else:
            raise PatternError(f"virtual rig: this renderer keeps axes {sorted(self.axes)}; a frame of axis "
                               f"{fl.axis!r} needs one built with it (VirtualRig.coded_axes)")
        _shade(frame, coord, self._gain, self._ambient, self.imaging.projector_blur_px,
               self._gamma, self._clean.ravel())
        for lcoord, lgain in self._layers:
            c = coord if fl.kind in (_WHITE, _BLACK) else lcoord[fl.axis]
            _shade(frame, c, lgain, self._zero, self.imaging.projector_blur_px, self._gamma, self._layer_buf)
            self._clean.ravel()[:] += self._layer_buf
        return self._clean

    def clean(self, frame: Frame, blur: bool = False) -> F32:
        """Noise-free image of ``frame`` (DN, 8-bit scale), shape (H, W), float32 (a new array).

        ``blur`` applies the camera defocus.
        """
        with self._lock:
            img = self._clean_into(frame).copy()
            if blur:
                self._blur(img)
        m = self.margin
        return np.ascontiguousarray(img[m:m + self.height, m:m + self.width]) if m else img

    def render(self, frame: Frame, out: ImageArray, rng: np.random.Generator, exposure: float = 1.0,
               intensity: float = 1.0) -> ImageArray:
        """Render ``frame`` into ``out`` (shape (H, W), uint8 or uint16 by bit depth) and return it.

        ``exposure`` scales all light (relative to ``imaging.reference_exposure_us``), ``intensity`` the
        projector's light only; both before noise and clipping.
        """
        if out.shape != (self.height, self.width) or out.dtype != self.dtype or not out.flags.c_contiguous:
            raise ValueError(
                f"out: shape {out.shape} dtype {out.dtype}: must be C-contiguous "
                f"({self.height}, {self.width}) {np.dtype(self.dtype).name}"
            )
        im = self.imaging
        key = np.uint64(rng.integers(0, 2**63, dtype=np.int64))
        with self._lock:
            src = self._clean_into(frame)
            if intensity != 1.0 or exposure != 1.0:  # in place: (ambient + intensity * light) * exposure
                flat = src.ravel()
                if intensity != 1.0:
                    flat -= self._ambient
                    flat *= np.float32(intensity)
                    flat += self._ambient
                flat *= np.float32(exposure)
            self._blur(src)  # in place, through per-thread scratch rows (no second image per camera)
            if self.margin:  # the image inside the margin
                m = self.margin
                np.copyto(self._inner, src[m:m + self.height, m:m + self.width])
                src = self._inner
            shot = 1.0 / im.electrons_per_dn if im.shot_noise else 0.0
            with _k.KERNEL_LOCK:
                _k.add_noise_quantise(src.ravel(), key, im.read_noise_dn**2, shot, self._scale, self._full,
                                      out.ravel())
        return out


def blur_margin(imaging: ImagingConfig) -> int:
    """Pixels beyond each side of the image a camera's blur reads (0 without blur): its passes times their
    radius (see ``_sim_kernels.gaussian_passes``)."""
    blur = imaging.camera_blur_px
    if blur <= 0:
        return 0
    passes, _ = _k.gaussian_passes(blur)
    return int(passes * _k.BLUR_RADIUS)

