"""Photometry of the virtual rig: projector light at exact projector coordinates, camera blur, noise, ADC.

The projector image is never rasterised. For a camera pixel that sees projector coordinates ``(u, v)``
(pixel centres at integers) the light of a frame is evaluated analytically:

- Gray bit: the bit of ``floor((u + 0.5) / stripe)``'s Gray code (exactly the projector pixels of
  :func:`appliance.patterns.render.frame_profile`), its edges blurred by the projector defocus, a Gaussian
  of sigma ``projector_blur_px``: a sum of ``Φ`` (erf) terms over the nearby edges, exact.
- Phase step: ``(1 + m cos(2π u / P + offset + 2π step / steps)) / 2`` with
  ``m = sinc(1 / P) exp(-2π² σ² / P²)``: the fundamental of the pixelated, blurred sinusoid (the pixel
  aliases it neglects are below 2e-4 of the modulation for ``P >= 8`` and ``σ >= 0.5``).
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
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from appliance.config.schema import ImagingConfig
from appliance.errors import PatternError
from appliance.patterns.sequence import BlackFrame, Frame, GrayFrame, PhaseFrame, WhiteFrame
from appliance.sim import _sim_kernels as _k

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
ImageArray = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]

_WHITE, _BLACK, _GRAY, _PHASE = 0, 1, 2, 3


@dataclass(frozen=True)
class FrameLight:
    """Parameters of a frame's projected light for the shading kernel (see the module docstring)."""

    kind: int
    axis: str = "x"
    stripe: float = 1.0
    bit: int = 0
    inverted: bool = False
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
        return FrameLight(_GRAY, frame.axis, float(frame.stripe), frame.bit, frame.inverted)
    if isinstance(frame, PhaseFrame):
        f = 1.0 / frame.period
        sinc = math.sin(math.pi * f) / (math.pi * f)
        mod = sinc * math.exp(-2.0 * math.pi**2 * projector_blur_px**2 * f * f)
        return FrameLight(_PHASE, frame.axis, freq=2.0 * math.pi * f,
                          phase0=frame.offset + 2.0 * math.pi * frame.step / frame.steps, modulation=mod)
    raise PatternError(
        f"virtual rig: frame kind {frame.pattern!r} is not known; cannot render it (use gray, phase, white, black)"
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
    fl = frame_light(frame, projector_blur_px)
    ok = np.isfinite(uu) & np.isfinite(vv)
    win = np.empty(uu.size)
    _k.projector_window(uu, vv, width, height, projector_blur_px, win)
    coord = np.where(ok, uu if fl.axis == "x" else vv, 0.0)
    out = np.empty(uu.size)
    _shade(fl, coord, win, np.zeros(uu.size), projector_blur_px, gamma, out)
    return out


def _shade(fl: FrameLight, coord: F64, gain: F64 | F32, ambient: F64 | F32, sigma: float, gamma: float,
           out: F64 | F32) -> None:
    _k.shade_frame(fl.kind, coord, gain, ambient, fl.stripe, fl.bit, fl.inverted, fl.freq, fl.phase0,
                   fl.modulation, sigma, gamma, out)


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

    Notes
    -----
    Thread-safe: one lock serialises renders of this camera (the buffers are shared).
    """

    def __init__(self, proj_uv: F64, gain: F64, ambient: F64, imaging: ImagingConfig) -> None:
        h, w = gain.shape
        self.height, self.width = h, w
        self.imaging = imaging
        uv = np.nan_to_num(np.asarray(proj_uv, dtype=np.float64), nan=-1e6)
        self._u = np.ascontiguousarray(uv[..., 0].ravel())
        self._v = np.ascontiguousarray(uv[..., 1].ravel())
        self._gain = np.ascontiguousarray(gain, dtype=np.float32).ravel()
        self._ambient = np.ascontiguousarray(ambient, dtype=np.float32).ravel()
        self._clean = np.empty((h, w), dtype=np.float32)
        self._blurred = np.empty((h, w), dtype=np.float32)
        self._normal = np.empty((h, w), dtype=np.float32)
        self._lock = threading.Lock()
        self.dtype: type[np.uint8] | type[np.uint16] = np.uint8 if imaging.bit_depth == 8 else np.uint16
        self._scale = float(2 ** (imaging.bit_depth - 8))
        self._full = float(2**imaging.bit_depth - 1)
        self._gamma = 1.0 if imaging.gamma_corrected else float(imaging.projector_gamma)

    def clean(self, frame: Frame) -> F32:
        """Noise-free, unblurred image of ``frame`` (DN, 8-bit scale), shape (H, W); a shared buffer."""
        fl = frame_light(frame, self.imaging.projector_blur_px)
        coord = self._u if fl.axis == "x" else self._v
        _shade(fl, coord, self._gain, self._ambient, self.imaging.projector_blur_px, self._gamma,
               self._clean.ravel())
        return self._clean

    def render(self, frame: Frame, out: ImageArray, rng: np.random.Generator) -> ImageArray:
        """Render ``frame`` into ``out`` (shape (H, W), uint8 or uint16 by bit depth) and return it."""
        if out.shape != (self.height, self.width) or out.dtype != self.dtype or not out.flags.c_contiguous:
            raise ValueError(
                f"out: shape {out.shape} dtype {out.dtype}: must be C-contiguous ({self.height}, {self.width}) "
                f"{np.dtype(self.dtype).name}"
            )
        im = self.imaging
        with self._lock:
            clean = self.clean(frame)
            if im.camera_blur_px > 0:
                cv2.GaussianBlur(clean, (0, 0), im.camera_blur_px, dst=self._blurred,
                                 sigmaY=im.camera_blur_px, borderType=cv2.BORDER_REPLICATE)
                src = self._blurred
            else:
                src = clean
            read_var = im.read_noise_dn**2
            shot = 1.0 / im.electrons_per_dn if im.shot_noise else 0.0
            if read_var > 0 or shot > 0:
                rng.standard_normal(dtype=np.float32, out=self._normal)
            else:
                self._normal.fill(0.0)
            _k.add_noise_quantise(src.ravel(), self._normal.ravel(), read_var, shot, self._scale, self._full,
                                  out.ravel())
        return out
