"""numba kernels of the structured-light decoder (private; see :mod:`appliance.reconstruct.decode`).

Bit-exact streaming: everything a frame contributes before the final per-pixel step is exact
(integers, and phase sums of products with coefficients quantised to 2**-20, which float64 adds
exactly in any order). Batch and streaming then run the same :func:`_finish_row`, so both give
the same bits whatever order frames arrive in.

Plan tables (built by ``decode.plan_decode``):

- ``gray_tab`` int64 (G, 4): axis (0 = x, 1 = y), bit, positive frame, negative frame (-1: absent).
  The positive frame is lit where the bit is 1; a bit with one frame is compared to (white + black) / 2.
- ``axis_tab`` int64 (2, 6): coded, has Gray, stripe (px), stripe count, tolerate one weak bit, size (px).
- ``ph_tab`` int64 (S, 4): axis, steps, source (-2 axis centre, -1 Gray, 1 previous set), first row
  in ``ph_idx`` / ``ph_sin`` / ``ph_cos``; sets ordered coarse to fine within an axis.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

BIG = np.int32(2**30)  # "no contrast seen yet"
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi

# Odd minimax-like polynomial for atan on [0, 1] (fitted here; max error 6e-9 rad).
_A0 = 0.9999998863850188
_A1 = -0.3333259703369639
_A2 = 0.19985906815565882
_A3 = -0.14161229391314495
_A4 = 0.10498946472713672
_A5 = -0.0723485774264268
_A6 = 0.039781224444597835
_A7 = -0.014401356954857433
_A8 = 0.0024567240725950623

_OPTS = {"nogil": True, "cache": True, "error_model": "numpy"}


@njit(**_OPTS)
def _atan2(y: float, x: float) -> float:
    """Branch-free atan2 (vectorisable); atan2(0, 0) = 0."""
    ax = abs(x)
    ay = abs(y)
    hi = max(ax, ay)
    lo = min(ax, ay)
    t = lo / hi if hi > 0.0 else 0.0
    t2 = t * t
    p = _A8
    p = p * t2 + _A7
    p = p * t2 + _A6
    p = p * t2 + _A5
    p = p * t2 + _A4
    p = p * t2 + _A3
    p = p * t2 + _A2
    p = p * t2 + _A1
    p = p * t2 + _A0
    a = t * p
    a = _HALF_PI - a if ay > ax else a
    a = math.pi - a if x < 0.0 else a
    return -a if y < 0.0 else a


@njit(**_OPTS)
def _gray_to_binary(g: int) -> int:
    g ^= g >> 1
    g ^= g >> 2
    g ^= g >> 4
    g ^= g >> 8
    g ^= g >> 16
    return g


@njit(**_OPTS)
def _add_bit(d_row, bit, code, m1, m2):  # type: ignore[no-untyped-def]
    """Fold one Gray bit's signed contrast row ``d_row`` into code and the two smallest contrasts."""
    for x in range(d_row.shape[0]):
        d = d_row[x]
        code[x] |= np.int32(d > 0) << bit
        ad = abs(d)
        m2[x] = min(m2[x], max(m1[x], ad))
        m1[x] = min(m1[x], ad)


@njit(**_OPTS)
def _finish_row(r, code, m1, m2, ssum, csum, axis_tab, ph_tab, ph_period, rel, thr,  # type: ignore[no-untyped-def]
                u, v, mask, quality, cg, cc, ok, qa, qmin, allok):
    """Per-pixel final step shared by batch and streaming: gates, Gray index, phase, unwrapping.

    ``r`` int32 (W,): contrast range; ``code``/``m1``/``m2`` int32 (2, W); ``ssum``/``csum`` float64 (S, W);
    ``cg``, ``cc``, ``qa``, ``qmin`` float64 (W,) and ``ok``, ``allok`` bool (W,) are scratch.
    """
    w = r.shape[0]
    nset = ph_tab.shape[0]
    for x in range(w):
        rr = np.float64(r[x])
        allok[x] = (rr >= thr) and (rr > 0.0)
        qmin[x] = np.inf
    for a in range(2):
        out = u if a == 0 else v
        if axis_tab[a, 0] == 0:
            for x in range(w):
                out[x] = np.nan
            continue
        stripe = np.float64(axis_tab[a, 2])
        nstripes = axis_tab[a, 3]
        tolerate = axis_tab[a, 4] != 0
        centre = 0.5 * np.float64(axis_tab[a, 5] - 1)
        if axis_tab[a, 1] != 0:
            ca = code[a]
            m1a = m1[a]
            m2a = m2[a]
            for x in range(w):
                k = _gray_to_binary(ca[x])
                relv = rel * np.float64(r[x])
                q1 = np.float64(m1a[x])
                q2 = np.float64(m2a[x])
                strong1 = q1 >= relv
                strong2 = tolerate and q2 >= relv
                ok[x] = (strong1 or strong2) and k < nstripes
                qa[x] = q1 if strong1 else q2
                cg[x] = (np.float64(k) + 0.5) * stripe - 0.5
                cc[x] = cg[x]
        else:
            for x in range(w):
                ok[x] = True
                qa[x] = np.inf
                cg[x] = centre
                cc[x] = centre
        for s in range(nset):
            if ph_tab[s, 0] != a:
                continue
            period = ph_period[s]
            scale = 4.0 / np.float64(ph_tab[s, 1])
            src = ph_tab[s, 2]
            ss = ssum[s]
            cs = csum[s]
            for x in range(w):
                sv = ss[x]
                cv = cs[x]
                mod = scale * math.sqrt(sv * sv + cv * cv)
                ok[x] = ok[x] and mod >= rel * np.float64(r[x])
                qa[x] = min(qa[x], mod)
                c0 = cc[x] if src > 0 else cg[x]
                cph = period * _atan2(-sv, cv) / _TWO_PI
                cph = cph + period if cph < 0.0 else cph
                cc[x] = cph + period * math.floor((c0 - cph) / period + 0.5)
        for x in range(w):
            good = ok[x] and allok[x]
            out[x] = np.float32(cc[x]) if good else np.float32(np.nan)
            qmin[x] = min(qmin[x], qa[x])
            allok[x] = good
    for x in range(w):
        mask[x] = allok[x]
        quality[x] = np.float32(qmin[x]) if allok[x] else np.float32(0.0)


# --------------------------------------------------------------------------------------------------
# Contrast-range histogram (for the scene-adaptive shadow threshold)
# --------------------------------------------------------------------------------------------------


@njit(**_OPTS, parallel=True)
def range_hist(hi, lo, shift, nbins):  # type: ignore[no-untyped-def]
    """Histogram of ``max(hi - lo, 0) >> shift`` (clipped to ``nbins - 1``) over (H, W) images."""
    h = hi.shape[0]
    nch = min(h, 64)
    parts = np.zeros((nch, nbins), np.int64)
    for ch in prange(nch):
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            for x in range(hi.shape[1]):
                d = max(np.int32(hi[y, x]) - np.int32(lo[y, x]), 0) >> shift
                parts[ch, min(d, nbins - 1)] += 1
    return parts.sum(axis=0)


@njit(**_OPTS)
def _range_row(frames, y, wb, used, r, mx, mn, maxval):  # type: ignore[no-untyped-def]
    w = frames.shape[2]
    if wb[0] >= 0:
        hi = frames[wb[0], y]
        lo = frames[wb[1], y]
        for x in range(w):
            r[x] = np.int32(hi[x]) - np.int32(lo[x])
        return
    for x in range(w):
        mx[x] = 0
        mn[x] = maxval
    for i in range(used.shape[0]):
        row = frames[used[i], y]
        for x in range(w):
            val = np.int32(row[x])
            mx[x] = max(mx[x], val)
            mn[x] = min(mn[x], val)
    for x in range(w):
        r[x] = mx[x] - mn[x]


@njit(**_OPTS, parallel=True)
def range_hist_stack(frames, wb, used, maxval, shift, nbins):  # type: ignore[no-untyped-def]
    """Histogram of the contrast range of a (F, H, W) stack without white/black (max - min over ``used``)."""
    h = frames.shape[1]
    w = frames.shape[2]
    nch = min(h, 64)
    parts = np.zeros((nch, nbins), np.int64)
    for ch in prange(nch):
        r = np.empty(w, np.int32)
        mx = np.empty(w, np.int32)
        mn = np.empty(w, np.int32)
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            _range_row(frames, y, wb, used, r, mx, mn, maxval)
            for x in range(w):
                parts[ch, min(max(r[x], 0) >> shift, nbins - 1)] += 1
    return parts.sum(axis=0)


# --------------------------------------------------------------------------------------------------
# Batch: one fused pass over rows
# --------------------------------------------------------------------------------------------------


@njit(**_OPTS)
def _gray_row(frames, y, wb, gray_tab, d, code, m1, m2):  # type: ignore[no-untyped-def]
    w = frames.shape[2]
    for g in range(gray_tab.shape[0]):
        a = gray_tab[g, 0]
        bit = gray_tab[g, 1]
        ip = gray_tab[g, 2]
        ineg = gray_tab[g, 3]
        if ip >= 0 and ineg >= 0:
            p = frames[ip, y]
            n = frames[ineg, y]
            for x in range(w):
                d[x] = np.int32(p[x]) - np.int32(n[x])
        else:
            one = frames[ip if ip >= 0 else ineg, y]
            wr = frames[wb[0], y]
            br = frames[wb[1], y]
            sign = np.int32(1) if ip >= 0 else np.int32(-1)
            for x in range(w):
                d[x] = sign * (2 * np.int32(one[x]) - np.int32(wr[x]) - np.int32(br[x]))
        _add_bit(d, bit, code[a], m1[a], m2[a])


@njit(**_OPTS)
def _phase_row(frames, y, ph_tab, ph_idx, ph_sin, ph_cos, ssum, csum):  # type: ignore[no-untyped-def]
    w = frames.shape[2]
    for s in range(ph_tab.shape[0]):
        ss = ssum[s]
        cs = csum[s]
        for x in range(w):
            ss[x] = 0.0
            cs[x] = 0.0
        first = ph_tab[s, 3]
        for k in range(first, first + ph_tab[s, 1]):
            row = frames[ph_idx[k], y]
            sk = ph_sin[k]
            ck = ph_cos[k]
            for x in range(w):
                val = np.float64(row[x])
                ss[x] += val * sk
                cs[x] += val * ck


@njit(**_OPTS, parallel=True)
def decode_stack(frames, wb, used, maxval, gray_tab, axis_tab, ph_tab, ph_period, ph_idx, ph_sin, ph_cos,  # type: ignore[no-untyped-def]
                 rel, thr, u, v, mask, quality):
    """Decode a (F, H, W) stack into u, v, mask, quality (H, W) in one pass over rows."""
    h = frames.shape[1]
    w = frames.shape[2]
    nset = max(ph_tab.shape[0], 1)
    nch = min(h, 8 * numba.get_num_threads())
    for ch in prange(nch):
        r = np.empty(w, np.int32)
        d = np.empty(w, np.int32)
        mx = np.empty(w, np.int32)
        mn = np.empty(w, np.int32)
        code = np.empty((2, w), np.int32)
        m1 = np.empty((2, w), np.int32)
        m2 = np.empty((2, w), np.int32)
        ssum = np.empty((nset, w), np.float64)
        csum = np.empty((nset, w), np.float64)
        cg = np.empty(w, np.float64)
        cc = np.empty(w, np.float64)
        qa = np.empty(w, np.float64)
        qmin = np.empty(w, np.float64)
        ok = np.empty(w, np.bool_)
        allok = np.empty(w, np.bool_)
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            _range_row(frames, y, wb, used, r, mx, mn, maxval)
            code[:] = 0
            m1[:] = BIG
            m2[:] = BIG
            _gray_row(frames, y, wb, gray_tab, d, code, m1, m2)
            _phase_row(frames, y, ph_tab, ph_idx, ph_sin, ph_cos, ssum, csum)
            _finish_row(r, code, m1, m2, ssum, csum, axis_tab, ph_tab, ph_period, rel, thr,
                        u[y], v[y], mask[y], quality[y], cg, cc, ok, qa, qmin, allok)


# --------------------------------------------------------------------------------------------------
# Streaming: one small kernel per arriving frame, the same final step
# --------------------------------------------------------------------------------------------------


@njit(**_OPTS, parallel=True)
def stream_pair(pos, neg, bit, code, m1, m2):  # type: ignore[no-untyped-def]
    """Fold a (pattern, inverse) pair of (H, W) images into the axis state (H, W) arrays."""
    h, w = pos.shape
    for y in prange(h):
        d = np.empty(w, np.int32)
        p = pos[y]
        n = neg[y]
        for x in range(w):
            d[x] = np.int32(p[x]) - np.int32(n[x])
        _add_bit(d, bit, code[y], m1[y], m2[y])


@njit(**_OPTS, parallel=True)
def stream_single(img, sign, white, black, bit, code, m1, m2):  # type: ignore[no-untyped-def]
    """Fold a Gray frame without inverse, thresholded at (white + black) / 2, into the axis state."""
    h, w = img.shape
    for y in prange(h):
        d = np.empty(w, np.int32)
        one = img[y]
        wr = white[y]
        br = black[y]
        for x in range(w):
            d[x] = np.int32(sign) * (2 * np.int32(one[x]) - np.int32(wr[x]) - np.int32(br[x]))
        _add_bit(d, bit, code[y], m1[y], m2[y])


@njit(**_OPTS, parallel=True)
def stream_phase(img, sk, ck, ssum, csum):  # type: ignore[no-untyped-def]
    """Add one phase step (H, W) into the set's sums (exact: quantised coefficients)."""
    h, w = img.shape
    for y in prange(h):
        row = img[y]
        ss = ssum[y]
        cs = csum[y]
        for x in range(w):
            val = np.float64(row[x])
            ss[x] += val * sk
            cs[x] += val * ck


@njit(**_OPTS, parallel=True)
def stream_minmax(img, hi, lo):  # type: ignore[no-untyped-def]
    """Running per-pixel maximum / minimum (contrast range when there are no white/black frames)."""
    h, w = img.shape
    for y in prange(h):
        row = img[y]
        hr = hi[y]
        lr = lo[y]
        for x in range(w):
            hr[x] = max(hr[x], row[x])
            lr[x] = min(lr[x], row[x])


@njit(**_OPTS, parallel=True)
def stream_finish(hi, lo, code, m1, m2, ssum, csum, axis_tab, ph_tab, ph_period, rel, thr,  # type: ignore[no-untyped-def]
                  u, v, mask, quality):
    """Final step of streaming: state arrays (H, W) / (2, H, W) / (S, H, W) -> outputs (H, W)."""
    h, w = hi.shape
    nch = min(h, 8 * numba.get_num_threads())
    for ch in prange(nch):
        r = np.empty(w, np.int32)
        cg = np.empty(w, np.float64)
        cc = np.empty(w, np.float64)
        qa = np.empty(w, np.float64)
        qmin = np.empty(w, np.float64)
        ok = np.empty(w, np.bool_)
        allok = np.empty(w, np.bool_)
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            hr = hi[y]
            lr = lo[y]
            for x in range(w):
                r[x] = np.int32(hr[x]) - np.int32(lr[x])
            _finish_row(r, code[:, y, :], m1[:, y, :], m2[:, y, :], ssum[:, y, :], csum[:, y, :],
                        axis_tab, ph_tab, ph_period, rel, thr, u[y], v[y], mask[y], quality[y],
                        cg, cc, ok, qa, qmin, allok)
