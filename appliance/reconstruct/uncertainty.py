"""Noise of a decoded projector code, from the sequence, the pixel's modulation and the camera noise.

Model
-----
A phase set of ``N`` steps measures ``I_n = A + B cos(phi + theta_n)`` with camera noise of standard
deviation ``sigma_I`` per frame. The decoder's sums ``S = sum I_n sin theta_n``, ``C = sum I_n cos theta_n``
carry noise of variance ``N sigma_I^2 / 2`` each, uncorrelated, around a signal of length ``N B / 2``; the
part across the signal is the phase error, so ``sigma_phi = sqrt(2 / N) sigma_I / B``. The decoder's quality
is the peak-to-peak modulation ``q = 2 B`` (DN), and the code is ``u = P phi / (2 pi)``, so

    sigma_u = P sqrt(2 / N) sigma_I / (pi q)        (projector px)

with ``P`` and ``N`` of the finest phase set (it gives the result; coarser sets only unwrap it). The camera
noise is read noise plus shot noise plus rounding: ``sigma_I^2 = read^2 + A / (e- per DN) + 1 / 12``, with the
mean level ``A = white - q / 2`` (ambient included) when the white image is known, else ``A = q / 2``.
For N >= 4 the shot noise of the varying ``I_n`` averages to that of ``A`` exactly (the cross terms sum to
zero over the steps). A Gray-only code is a stripe centre: its error is uniform over the stripe, ``s / sqrt 12``.

Light that came another way
---------------------------
Light that reaches a pixel by another path (diffuse interreflection from a nearby face, subsurface
scattering) adds to its range ``white - black`` but, averaged over many projector pixels, little to the
pattern's contrast. So the pixel's *fringe share* ``f = q / (white - black)`` (``DecodedMaps.fringe``) drops
below what the optics give a clean pixel, ``m`` (taken as the scan's median share). Its light is then a share
``rho = 1 - f / m`` indirect. That light need not be averaged out: near a concave corner it comes from nearby
surface whose code is close to but not the pixel's, and it shifts the phase by up to ``rho / (1 - rho)``
(its phasor against the direct one). The code's 1-sigma then gains, in quadrature,

    sigma_b = P / (2 pi) * e / (1 - e),   e = max(0, 1 - f / m - tolerance)       (projector px)

with ``P`` the finest period and :data:`FRINGE_TOLERANCE` the spread of ``f`` over a clean scene (blur,
texture, noise). Camera-camera matching does not need it: a Lambertian surface sends the same light, so the
same code, to both cameras. Measured on the virtual rig's matte concave corner (one-bounce interreflection,
64 samples): points beyond 5 sigma 0.155 % -> 0.02 %; the default scene's sigma is unchanged.

Triangulation turns ``sigma_u`` into a 1-sigma distance along the camera ray (mm) by the derivative of
the depth with respect to the code (see :mod:`appliance.reconstruct.triangulate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.patterns.sequence import GrayFrame, PhaseFrame, Sequence

ROUNDING_VAR_DN2 = 1.0 / 12.0
"""Variance of rounding to integer DN."""

FRINGE_TOLERANCE = 0.10
"""Share of the scan's median fringe share a pixel may lack before its light counts as partly indirect
(the spread of the share over a clean scene: blur that varies with the local fringe frequency, texture,
noise; on the virtual rig's default scene 90 % of the pixels lie within it)."""

FRINGE_MAX_INDIRECT = 0.9
"""Largest indirect share ``e`` the bias term takes (its phase bound ``e / (1 - e)`` is then 9 rad)."""

FRINGE_MIN_PIXELS = 1000
"""Fewest decoded pixels whose median fringe share is trusted as the scan's clean level."""


@dataclass(frozen=True)
class CodeNoise:
    """How the noise of the decoded code follows from a pixel's modulation.

    Attributes
    ----------
    phase_px : float
        ``P sqrt(2 / N) / pi`` of the finest phase set (projector px): ``sigma_u = phase_px sigma_I / q``;
        0 for a Gray-only code.
    stripe_px : float
        Gray stripe width of a Gray-only code (projector px): ``sigma_u = stripe_px / sqrt(12)``; 0 with phase.
    period_px : float
        Period of the finest phase set (projector px), for the bias of indirect light
        (:func:`fringe_variance_table`); 0: none (a Gray-only code).
    read_noise_dn : float
        Camera read noise, 1 sigma (DN of the decoded data).
    electrons_per_dn : float
        Camera conversion gain for shot noise (e- per DN of the data); ``inf``: no shot noise.
    """

    phase_px: float
    stripe_px: float = 0.0
    read_noise_dn: float = 2.0
    electrons_per_dn: float = 25.0
    period_px: float = 0.0

    def __post_init__(self) -> None:
        if not (self.phase_px >= 0 and self.stripe_px >= 0 and (self.phase_px > 0 or self.stripe_px > 0)):
            raise ValueError(
                f"code noise: phase_px = {self.phase_px}, stripe_px = {self.stripe_px}: one must be > 0"
            )
        if not (self.read_noise_dn >= 0 and self.electrons_per_dn > 0):
            raise ValueError(
                f"code noise: read_noise_dn = {self.read_noise_dn} must be >= 0 and electrons_per_dn = "
                f"{self.electrons_per_dn} > 0"
            )

    def params(self) -> npt.NDArray[np.float64]:
        """(phase_px, stripe var px^2, read var + rounding DN^2, 1 / e- per DN) for the kernels."""
        inv_e = 0.0 if math.isinf(self.electrons_per_dn) else 1.0 / self.electrons_per_dn
        return np.array(
            [self.phase_px, self.stripe_px**2 / 12.0, self.read_noise_dn**2 + ROUNDING_VAR_DN2, inv_e],
            np.float64,
        )

    def sigma_px(
        self, quality: npt.ArrayLike, mean_dn: npt.ArrayLike | None = None
    ) -> npt.NDArray[np.float64]:
        """1-sigma code error (projector px) of pixels of modulation ``quality`` (DN, peak to peak).

        ``mean_dn`` is the pixel's mean level (DN) under the phase frames; ``quality / 2`` when None.
        Same formula as the triangulation kernels (for checks and notebooks).
        """
        q = np.asarray(quality, np.float64)
        a = 0.5 * q if mean_dn is None else np.asarray(mean_dn, np.float64)
        p = self.params()
        var_i = p[2] + np.maximum(a, 0.0) * p[3]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = p[0] * np.sqrt(var_i) / q
        out: npt.NDArray[np.float64] = np.sqrt(s * s + p[1])
        return out


def code_noise_for_sequence(
    sequence: Sequence, axis: str = "x", read_noise_dn: float = 2.0, electrons_per_dn: float = 25.0
) -> CodeNoise:
    """The :class:`CodeNoise` of the code a sequence gives on one axis.

    Parameters
    ----------
    sequence : Sequence
        The projected frames.
    axis : {'x', 'y'}
        The coded axis (with both coded, the finer of the two is what the kernels assume for both).
    read_noise_dn, electrons_per_dn : float
        Camera noise in the DN of the decoded data (see :class:`CodeNoise`).

    Returns
    -------
    CodeNoise
        From the finest phase set of the axis, else from its finest Gray stripe.

    Raises
    ------
    ValueError
        When the sequence codes nothing on ``axis``.
    """
    phases = [f for f in sequence.frames if isinstance(f, PhaseFrame) and f.axis == axis]
    if phases:
        finest = min(phases, key=lambda f: f.period)
        gain = float(finest.period) * math.sqrt(2.0 / finest.steps) / math.pi
        return CodeNoise(gain, 0.0, read_noise_dn, electrons_per_dn, float(finest.period))
    grays = [f for f in sequence.frames if isinstance(f, GrayFrame) and f.axis == axis]
    if not grays:
        raise ValueError(f"sequence {sequence.describe()}: codes nothing on axis {axis!r}")
    return CodeNoise(0.0, float(min(f.stripe for f in grays)), read_noise_dn, electrons_per_dn)


def fringe_variance_table(
    histogram: npt.NDArray[np.int64], period_px: float, tolerance: float = FRINGE_TOLERANCE
) -> tuple[npt.NDArray[np.float64], float] | None:
    """Bias variance of the code (projector px^2) for each fringe share 0..255 %, from the scan's histogram.

    Parameters
    ----------
    histogram : ndarray, shape (256,), int64
        Counts of ``DecodedMaps.fringe`` over the camera (bin 0, undecoded pixels, is not counted).
    period_px : float
        Period of the finest phase set (projector px); <= 0: no table.
    tolerance : float, optional
        Share of the median a pixel may lack before any of its light counts as indirect.

    Returns
    -------
    (table, median) or None
        ``table`` (256,) float64: ``(P / (2 pi) * e / (1 - e))^2`` with ``e = clip(1 - f / m - tolerance, 0,``
        :data:`FRINGE_MAX_INDIRECT` ``)``, ``f`` the bin's share and ``m`` the median share (both 0..1, see the
        module's notes); ``median`` is ``m``. None without a phase code or with fewer than
        :data:`FRINGE_MIN_PIXELS` decoded pixels.
    """
    hist = np.asarray(histogram, np.int64)
    if hist.shape != (256,):
        raise ValueError(f"fringe histogram: shape {hist.shape}: must be (256,)")
    counts = hist[1:]
    total = int(counts.sum())
    if not period_px > 0 or total < FRINGE_MIN_PIXELS:
        return None
    median = (int(np.searchsorted(np.cumsum(counts), (total + 1) // 2)) + 1) / 100.0
    share = np.arange(256, dtype=np.float64) / 100.0
    e = np.clip(1.0 - share / median - tolerance, 0.0, FRINGE_MAX_INDIRECT)
    table: npt.NDArray[np.float64] = (period_px / (2.0 * math.pi) * e / (1.0 - e)) ** 2
    return table, median
