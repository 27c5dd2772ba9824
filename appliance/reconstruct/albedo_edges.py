"""The code shift at albedo edges: a dark pixel beside a bright one reads its neighbour's code too.

The camera's lens blurs each pixel's light with its neighbours'. Where the surface's albedo is even, that
averages the pattern's phase around the pixel and shifts nothing. Beside a bright patch, a dark pixel's light
comes largely from the bright side: its phasor is the blur-weighted sum ``sum_j w_j a_j exp(i phi_j)``, and its
code is pulled towards the bright neighbours' codes. For a Gaussian blur of sigma ``b`` (camera px) and a code
that is locally linear, the pull is the light-weighted centroid of the blur, ``d = b^2 grad(R) / R``, where
``R`` is the pixel's white-light level *as the camera sees it* (after the blur): the first moment of the blur
kernel times the albedo is ``b^2`` times the gradient of the blurred image. The code is off by ``d . grad(u)``
(projector px), to first order in ``b |grad(phi)|``.

The correction subtracts that shift from each decoded code and adds ``(0.5 + |d|)`` times it, as a 1-sigma
term, to the code's variance: the blur is a configured estimate (``reconstruction.edge_blur_px``), the
first-order formula under-reads the strongest edges (most of the pixel's light from aside), and the level's own
noise enters the gradient.

On the dark-and-shiny render (albedo 0.03 patches beside 0.95 ones, camera blur 0.5 px, tune's three
exposures), with the fusion then free to take a pixel beside a clipped one: 93.4 -> 98.1 % complete, RMS
0.213 -> 0.162 mm, points beyond 5 sigma 0.102 -> 0 %.

With several exposures ``R`` must be in one scale across pixels that came from different passes:
:func:`appliance.reconstruct.hdr.radiance` gives it (each pixel's brightest unclipped white, divided by its
pass's light), and the HDR fusion may then take a pixel from a pass where a neighbour clipped: that
neighbour's level is known from a darker pass.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from appliance.reconstruct import _edge_kernels as K
from appliance.reconstruct.types import DecodedMaps

EDGE_SIGMA_SHARE = 0.5
"""The 1-sigma uncertainty of the correction, as a share of it, where the centroid shift is small; the share
grows by the shift (camera px): ``0.5 + |d|`` (the formula is first order in the light from aside)."""

MIN_SHIFT_PX = 0.02
"""The shortest centroid shift corrected (camera px): under it the code moves by less than 0.04 projector px
at the usual 1-2 projector px per camera pixel, a fifth of the code noise of a well-lit pixel; it spares the
even surfaces (most pixels) the work and the sigma pass."""

MAX_SHIFT_PX = 1.0
"""The longest centroid shift the correction applies (camera px): the first-order formula's limit (a blur of
0.5 px puts 2 % of its weight a pixel away from its centre, 0.03 % two pixels away)."""

REPORT_SHIFT_PX = 0.05
"""A code moved by more than this (projector px) counts as corrected (:attr:`AlbedoEdges.moved`)."""

F32 = npt.NDArray[np.float32]


class AlbedoEdges:
    """One camera's albedo-edge correction, applied to its decoded codes in place for one reconstruction.

    The corrections are few (the pixels beside an edge), so they are kept sparsely: per row the entries
    ``offsets[r] .. offsets[r + 1] - 1`` of ``cols`` (ascending columns), ``variance`` (projector px^2). The
    buffers grow as needed and are kept for the next scan.

    Parameters
    ----------
    height : int
        Rows of the camera image.
    """

    def __init__(self, height: int) -> None:
        self.offsets = np.zeros(int(height) + 1, np.int64)
        self._rows = np.zeros(int(height), np.int64)
        self.moved_rows = np.zeros(int(height), np.int64)
        self._alloc(0)
        self._applied: list[tuple[F32, F32]] = []

    def _alloc(self, n: int) -> None:
        self.cols = np.zeros(n, np.int64)
        self.variance = np.zeros(n, np.float32)
        self._du = np.zeros(n, np.float32)
        self._dv = np.zeros(n, np.float32)
        self._old_u = np.zeros(n, np.float32)
        self._old_v = np.zeros(n, np.float32)

    @property
    def moved(self) -> int:
        """Pixels whose code the last :meth:`apply` moved by more than :data:`REPORT_SHIFT_PX`."""
        return int(self.moved_rows.sum())

    def apply(self, maps: DecodedMaps, level: npt.NDArray[np.generic], blur_px: float, axes: str) -> None:
        """Correct the codes of ``maps`` in place (undo with :meth:`restore`).

        Parameters
        ----------
        maps : DecodedMaps
            One camera's decoded maps; the coded axes' ``u`` / ``v`` change (where they are writable; read-only
            codes stay as they are, their variance still counts).
        level : ndarray, shape (H, W)
            White-light level per pixel in one scale (DN, or DN per unit of light for several exposures); any
            real dtype.
        blur_px : float
            The camera's blur (Gaussian sigma, camera px); 0 changes nothing.
        axes : str
            The coded axes: ``'x'`` (``u``), ``'y'`` (``v``) or ``'xy'``.
        """
        self.restore()
        shape = maps.shape
        if level.shape != shape or shape[0] + 1 != self.offsets.shape[0]:
            raise ValueError(f"albedo edges: level image {level.shape}, maps {shape}: must be "
                             f"({self.offsets.shape[0] - 1}, W) both")  # fmt: skip
        s2 = float(blur_px) ** 2
        lim2 = (MIN_SHIFT_PX / s2) ** 2 if s2 > 0.0 else math.inf
        K.edge_count(maps.mask, level, lim2, self._rows)
        self.offsets[0] = 0
        np.cumsum(self._rows, out=self.offsets[1:])
        n = int(self.offsets[-1])
        if n > self.cols.shape[0]:
            self._alloc(n + n // 4)
        has_u, has_v = "x" in axes, "y" in axes
        K.edge_shift(maps.u, maps.v, maps.mask, level, s2, lim2, MAX_SHIFT_PX, EDGE_SIGMA_SHARE, REPORT_SHIFT_PX**2,
                     has_u, has_v, self.offsets, self.cols, self._du, self._dv, self.variance,
                     self.moved_rows)  # fmt: skip
        for code, delta, old, coded in ((maps.u, self._du, self._old_u, has_u), (maps.v, self._dv, self._old_v, has_v)):
            if coded and n and code.flags.writeable:  # read-only codes keep their values, and the variance
                K.shift_codes(code, self.offsets, self.cols, delta, old)
                self._applied.append((code, old))

    def restore(self) -> None:
        """Put back the codes the last :meth:`apply` changed (nothing when there are none)."""
        while self._applied:
            code, old = self._applied.pop()
            K.put_codes(code, self.offsets, self.cols, old)


