"""numba kernels of the exposure fusion (private; see :mod:`appliance.reconstruct.hdr`)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def clipped_near(reason, r_sat, radius, scratch, near):  # type: ignore[no-untyped-def]
    """``near[k]`` = 1 where pass ``k`` clipped a pixel within ``radius`` px (a square) of this one, else 0;
    ``scratch`` (n, H, W) uint8 holds the row pass of the separable running maximum."""
    n, h, w = reason.shape
    for ky in prange(n * h):
        k, y = ky // h, ky % h
        for x in range(w):
            hit = 0
            for xx in range(max(x - radius, 0), min(x + radius + 1, w)):
                if reason[k, y, xx] == r_sat:
                    hit = 1
                    break
            scratch[k, y, x] = hit
    for ky in prange(n * h):
        k, y = ky // h, ky % h
        for x in range(w):
            near[k, y, x] = 0
        for yy in range(max(y - radius, 0), min(y + radius + 1, h)):
            for x in range(w):
                near[k, y, x] |= scratch[k, yy, x]


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def choose_pass(mask, reason, r_sat, r_ok, r_mixed, clean_rule, near, choice, out_reason):  # type: ignore[no-untyped-def]
    """Per pixel the brightest pass (highest index) in which neither the pixel nor any of its 8 neighbours
    clipped: its result, decoded or not (a darker pass has less signal, so no darker one is trusted over its
    verdict). A pixel that decoded only in passes where a neighbour clipped is ``r_mixed`` (the clipped
    neighbour's light, of unknown level, reaches it through the lens blur: its code is the neighbour's as much
    as its own); the darkest pass ("saturated") where every pass clipped the pixel itself. Without
    ``clean_rule`` the neighbours are not looked at: the brightest pass that did not clip the pixel itself.
    ``near`` (n, H, W) uint8 of :func:`clipped_near`, for optics that blur farther than a pixel, replaces the 8
    neighbours by a wider square; an empty one (0, 0, 0): the 8 neighbours."""
    n, h, w = mask.shape
    wide = near.shape[0] == n
    for y in prange(h):
        for x in range(w):
            best = -1
            own = -1  # the brightest pass that did not clip the pixel itself
            for k in range(n - 1, -1, -1):
                if reason[k, y, x] == r_sat:
                    continue
                if own < 0:
                    own = k
                clean = True
                if not clean_rule:
                    best = k
                    break
                if wide:
                    clean = near[k, y, x] == 0
                else:
                    for yy in range(max(y - 1, 0), min(y + 2, h)):
                        for xx in range(max(x - 1, 0), min(x + 2, w)):
                            if reason[k, yy, xx] == r_sat:
                                clean = False
                if clean:
                    best = k
                    break
            if own < 0:
                choice[y, x] = 0
                out_reason[y, x] = reason[0, y, x]
                continue
            decoded_unclean = False
            for k in range(own, best, -1):  # passes brighter than the clean one, where a neighbour clipped
                if mask[k, y, x]:
                    decoded_unclean = True
            if best < 0:
                choice[y, x] = own
                out_reason[y, x] = r_mixed if mask[own, y, x] else reason[own, y, x]
            else:
                choice[y, x] = best
                if mask[best, y, x]:
                    out_reason[y, x] = r_ok
                else:
                    out_reason[y, x] = r_mixed if decoded_unclean else reason[best, y, x]


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def gather_pass(choice, reason, r_ok, mask, u, v, q, lev, ou, ov, omask, oq, olev):  # type: ignore[no-untyped-def]
    """Copy each pixel's maps from the pass ``choice`` names; undecoded (NaN, 0) where the fused ``reason`` is
    not ``r_ok``."""
    _, h, w = mask.shape
    nan = np.float32(np.nan)
    for y in prange(h):
        for x in range(w):
            k = choice[y, x]
            if reason[y, x] != r_ok:
                ou[y, x] = nan
                ov[y, x] = nan
                omask[y, x] = False
                oq[y, x] = 0.0
                olev[0, y, x] = 0
                olev[1, y, x] = 0
                continue
            ou[y, x] = u[k, y, x]
            ov[y, x] = v[k, y, x]
            omask[y, x] = mask[k, y, x]
            oq[y, x] = q[k, y, x]
            olev[0, y, x] = lev[k, 0, y, x]
            olev[1, y, x] = lev[k, 1, y, x]
