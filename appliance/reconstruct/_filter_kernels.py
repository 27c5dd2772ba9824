"""numba kernels of the cloud filters and the organised -> cloud step (private; see ``filters.py``)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.reconstruct._geom_kernels import NAN32 as _NAN


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def near_neighbours(xyz, r, c, lim2):  # type: ignore[no-untyped-def]
    """How many of the 8 neighbours of the (valid) point (r, c) are valid and within sqrt(lim2) of it; those
    beyond the image's border count as such (the filter judges the neighbours that exist)."""
    h, w = xyz.shape[0], xyz.shape[1]
    x = xyz[r, c, 0]
    y = xyz[r, c, 1]
    z = xyz[r, c, 2]
    n = 0
    for dr in range(-1, 2):
        rr = r + dr
        if rr < 0 or rr >= h:
            n += 3
            continue
        for dc in range(-1, 2):
            cc = c + dc
            if cc < 0 or cc >= w:
                n += 1
                continue
            if dr == 0 and dc == 0:
                continue
            ex = xyz[rr, cc, 0] - x
            ey = xyz[rr, cc, 1] - y
            ez = xyz[rr, cc, 2] - z
            if ex * ex + ey * ey + ez * ez < lim2:  # NaN neighbours compare false
                n += 1
    return n


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def isolated_keep(xyz, min_nb, max_jump, keep):  # type: ignore[no-untyped-def]
    """keep[r, c] = valid point with >= ``min_nb`` of its 8 neighbours valid and nearer than ``max_jump``."""
    h, w = xyz.shape[0], xyz.shape[1]
    j2 = max_jump * max_jump
    for r in prange(h):
        for c in range(w):
            keep[r, c] = xyz[r, c, 2] == xyz[r, c, 2] and near_neighbours(xyz, r, c, j2) >= min_nb
    return keep


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def apply_keep(xyz, keep):  # type: ignore[no-untyped-def]
    """NaN the valid points where ``keep`` is False; returns how many."""
    h, w = xyz.shape[0], xyz.shape[1]
    removed = np.zeros(h, np.int64)
    for r in prange(h):
        n = 0
        for c in range(w):
            if not keep[r, c] and xyz[r, c, 2] == xyz[r, c, 2]:
                xyz[r, c, 0] = _NAN
                xyz[r, c, 1] = _NAN
                xyz[r, c, 2] = _NAN
                n += 1
        removed[r] = n
    return removed.sum()

@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def row_counts(xyz):  # type: ignore[no-untyped-def]
    """Number of valid points in every row."""
    h, w = xyz.shape[0], xyz.shape[1]
    counts = np.zeros(h + 1, np.int64)
    for r in prange(h):
        n = 0
        for c in range(w):
            if xyz[r, c, 2] == xyz[r, c, 2]:
                n += 1
        counts[r + 1] = n
    return counts


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def compact(xyz, quality, intensity, nrm, sig, starts, o_xyz, o_row, o_col, o_q, o_i, o_n, o_s):  # type: ignore[no-untyped-def]
    """Copy the valid points of the organised arrays into the cloud arrays (rows start at ``starts``)."""
    h, w = xyz.shape[0], xyz.shape[1]
    has_n = nrm.shape[0] == h
    has_s = sig.shape[0] == h
    for r in prange(h):
        k = starts[r]
        for c in range(w):
            if xyz[r, c, 2] != xyz[r, c, 2]:
                continue
            o_xyz[k, 0] = xyz[r, c, 0]
            o_xyz[k, 1] = xyz[r, c, 1]
            o_xyz[k, 2] = xyz[r, c, 2]
            o_row[k] = r
            o_col[k] = c
            o_q[k] = quality[r, c]
            o_i[k] = intensity[r, c]
            if has_n:
                o_n[k, 0] = nrm[r, c, 0]
                o_n[k, 1] = nrm[r, c, 1]
                o_n[k, 2] = nrm[r, c, 2]
            if has_s:
                o_s[k] = sig[r, c]
            k += 1

# Neighbour counting visits each pair of neighbouring pixels once (4 pairs per pixel: right, and the three
# below) and credits both ends; every loop runs over whole rows with non-negative indices, so it vectorises.
# Rows of points are padded (5, W + 2): x, y, z, sigma, jump limit (mm); a pair is near when closer than the
# mean of its two limits.


@njit(nogil=True, cache=True, error_model="numpy")
def _near(px, py, pz, pj, qx, qy, qz, qj, e):  # type: ignore[no-untyped-def]
    """e[c] = 1 where points p[c] and q[c] are nearer than (pj[c] + qj[c]) / 2, else 0 (NaN compares false)."""
    for c in range(e.shape[0]):
        ex = qx[c] - px[c]
        ey = qy[c] - py[c]
        ez = qz[c] - pz[c]
        j = np.float32(0.5) * (pj[c] + qj[c])
        e[c] = np.int32(ex * ex + ey * ey + ez * ez < j * j)


@njit(nogil=True, cache=True, error_model="numpy")
def _add2(n, a, b):  # type: ignore[no-untyped-def]
    for c in range(n.shape[0]):
        n[c] += a[c] + b[c]


@njit(nogil=True, cache=True, error_model="numpy")
def _add1(n, a):  # type: ignore[no-untyped-def]
    for c in range(n.shape[0]):
        n[c] += a[c]


@njit(nogil=True, cache=True, error_model="numpy")
def pairs_in_row(p, e, n):  # type: ignore[no-untyped-def]
    """Credit both pixels of every near horizontal pair of padded row p (5, W + 2) to n (W + 2,)."""
    w = p.shape[1] - 2
    # e[k]: padded columns k and k + 1 (the pads are NaN: pairs with them never count)
    _near(p[0, 0 : w + 1], p[1, 0 : w + 1], p[2, 0 : w + 1], p[4, 0 : w + 1], p[0, 1 : w + 2], p[1, 1 : w + 2],
          p[2, 1 : w + 2], p[4, 1 : w + 2], e[: w + 1])  # fmt: skip
    _add2(n[1 : w + 1], e[0:w], e[1 : w + 1])


@njit(nogil=True, cache=True, error_model="numpy")
def pairs_between_rows(p, q, e, np_, nq):  # type: ignore[no-untyped-def]
    """Credit every near pair (p column c, q column c + off), off = -1, 0, 1, to np_ and nq (padded)."""
    w = p.shape[1] - 2
    for off in range(-1, 2):
        a = 1 + off
        _near(p[0, 1 : w + 1], p[1, 1 : w + 1], p[2, 1 : w + 1], p[4, 1 : w + 1], q[0, a : a + w],
              q[1, a : a + w], q[2, a : a + w], q[4, a : a + w], e[:w])  # fmt: skip
        _add1(np_[1 : w + 1], e[:w])
        _add1(nq[a : a + w], e[:w])


@njit(nogil=True, cache=True, error_model="numpy")
def pairs_in_span(p, e, n, lo, hi):  # type: ignore[no-untyped-def]
    """:func:`pairs_in_row` where row p holds points only in padded columns lo .. hi - 1 (NaN elsewhere)."""
    if hi <= lo:
        return
    m = hi - lo + 1  # pairs (k, k + 1), k = lo - 1 .. hi - 1
    _near(p[0, lo - 1 : hi], p[1, lo - 1 : hi], p[2, lo - 1 : hi], p[4, lo - 1 : hi], p[0, lo : hi + 1],
          p[1, lo : hi + 1], p[2, lo : hi + 1], p[4, lo : hi + 1], e[:m])  # fmt: skip
    _add2(n[lo:hi], e[0 : m - 1], e[1:m])


@njit(nogil=True, cache=True, error_model="numpy")
def pairs_between_spans(p, q, e, np_, nq, lo_p, hi_p, lo_q, hi_q):  # type: ignore[no-untyped-def]
    """:func:`pairs_between_rows` where p and q hold points only in padded columns [lo, hi) each."""
    for off in range(-1, 2):
        lo = max(lo_p, lo_q - off)
        hi = min(hi_p, hi_q - off)
        if hi <= lo:
            continue
        k = hi - lo
        _near(p[0, lo:hi], p[1, lo:hi], p[2, lo:hi], p[4, lo:hi], q[0, lo + off : hi + off],
              q[1, lo + off : hi + off], q[2, lo + off : hi + off], q[4, lo + off : hi + off], e[:k])  # fmt: skip
        _add1(np_[lo:hi], e[:k])
        _add1(nq[lo + off : hi + off], e[:k])


@njit(nogil=True, cache=True, error_model="numpy")
def keep_row(pz, ps, n, min_nb, max_sigma, out, out_s):  # type: ignore[no-untyped-def]
    """out, out_s = the depths and sigmas of row pz with >= min_nb near neighbours and sigma <= max_sigma.

    Returns how many had the neighbours and how many were kept (a NaN sigma passes).
    """
    with_nb = np.int64(0)
    kept = np.int64(0)
    for c in range(out.shape[0]):
        z = pz[c]
        b = (z == z) & (n[c] >= min_nb)
        k = b & ~(ps[c] > max_sigma)
        out[c] = z if k else np.float32(np.nan)
        out_s[c] = ps[c] if k else np.float32(np.nan)
        with_nb += np.int64(b)
        kept += np.int64(k)
    return with_nb, kept
