"""numba kernels of the exposure fusion (private; see :mod:`appliance.reconstruct.hdr`)."""

from __future__ import annotations

from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def choose_pass(mask, reason, r_sat, r_ok, choice, out_reason):  # type: ignore[no-untyped-def]
    """Per pixel the brightest pass (highest index) that did not clip it: its result, decoded or not (a darker
    pass has less signal, so where the brightest unclipped one found no reliable code, no darker one is trusted);
    the darkest pass ("saturated") where every pass clipped it."""
    n, h, w = mask.shape
    for y in prange(h):
        for x in range(w):
            best = 0
            for k in range(n - 1, -1, -1):
                if reason[k, y, x] != r_sat:
                    best = k
                    break
            choice[y, x] = best
            out_reason[y, x] = r_ok if mask[best, y, x] else reason[best, y, x]


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def gather_pass(choice, mask, u, v, q, lev, ou, ov, omask, oq, olev):  # type: ignore[no-untyped-def]
    """Copy each pixel's maps from the pass ``choice`` names."""
    _, h, w = mask.shape
    for y in prange(h):
        for x in range(w):
            k = choice[y, x]
            ou[y, x] = u[k, y, x]
            ov[y, x] = v[k, y, x]
            omask[y, x] = mask[k, y, x]
            oq[y, x] = q[k, y, x]
            olev[0, y, x] = lev[k, 0, y, x]
            olev[1, y, x] = lev[k, 1, y, x]
