"""numba kernels of the separation of two copies of a phase pattern (private; see
:mod:`appliance.reconstruct.ghosts`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)

_TWO_PI = 2.0 * math.pi
_BIG = 1e30
_STRONGER = 1e6
"""Added to a fit whose second copy came out stronger than the first (the direct light is the stronger)."""
_NEG = 100.0
"""Weight of the squared negative part of an amplitude (amplitudes are >= 0)."""


@njit(nogil=True, cache=True)
def gather_stack_sums(frames, ys, xs, idx, sin_c, cos_c, first, steps, s_out, c_out):  # type: ignore[no-untyped-def]
    """The phase sums of one set at pixels (ys, xs) of a stack (F, H, W), in the decoder's order and numbers:
    ``s_out[i] = sum_n frames[idx[first + n], y, x] * sin_c[first + n]`` (int64 with integer coefficients,
    float64 with float ones), likewise ``c_out`` with ``cos_c``."""
    for i in range(ys.shape[0]):
        y = ys[i]
        x = xs[i]
        s = s_out.dtype.type(0)
        c = c_out.dtype.type(0)
        for n in range(first, first + steps):
            val = frames[idx[n], y, x]
            s += val * sin_c[n]
            c += val * cos_c[n]
        s_out[i] = s
        c_out[i] = c


@njit(nogil=True, cache=True, inline="always")
def _fit_cost(u1, u2, r, wre, wim, yy, k, periods, l2, sc):  # type: ignore[no-untyped-def]
    """Least-squares misfit of a pixel's sums to two copies of the pattern at codes ``u1`` (the stronger) and
    ``u2``: unknowns A, B (the copies' light in white - black) and c_s (the second copy's modulation per set,
    held near k_s B with weight ``sqrt(l2)``); the model ``r = A + B``, ``W_s = k_s A e^(i 2 pi u1 / P_s) + c_s
    e^(i 2 pi u2 / P_s)``. The normal equations' c_s block is diagonal: each c_s is eliminated, A and B solve
    a 2 x 2 system, and the misfit is ``yy - x . (M^T y)`` (``yy`` = r^2 + sum |W_s|^2). Negative amplitudes and
    a stronger second copy are penalised. ``sc`` (3, S) scratch."""
    ns = periods.shape[0]
    inv = 1.0 / (1.0 + l2)
    naa = 1.0
    nab = 1.0
    nbb = 1.0
    ba0 = r
    for s in range(ns):
        p1 = _TWO_PI * u1 / periods[s]
        p2 = _TWO_PI * u2 / periods[s]
        c1 = math.cos(p1)
        s1 = math.sin(p1)
        c2 = math.cos(p2)
        s2 = math.sin(p2)
        ks = k[s]
        naa += ks * ks
        nbb += l2 * ks * ks
        ba0 += ks * (wre[s] * c1 + wim[s] * s1)
        sc[0, s] = ks * (c1 * c2 + s1 * s2)  # A's coupling to c_s
        sc[1, s] = -l2 * ks  # B's coupling to c_s
        sc[2, s] = wre[s] * c2 + wim[s] * s2  # c_s's right-hand side
    ba = ba0
    bb = r
    for s in range(ns):
        q = sc[0, s]
        p = sc[1, s]
        naa -= q * q * inv
        nab -= q * p * inv
        nbb -= p * p * inv
        ba -= q * sc[2, s] * inv
        bb -= p * sc[2, s] * inv
    det = naa * nbb - nab * nab
    if det <= 1e-12:
        return _BIG
    a = (ba * nbb - nab * bb) / det
    b = (naa * bb - nab * ba) / det
    cost = yy - a * ba0 - b * r
    pen = 0.0
    for s in range(ns):
        c = (sc[2, s] - sc[0, s] * a - sc[1, s] * b) * inv
        cost -= c * sc[2, s]
        if c < 0.0:
            pen += c * c
    if a < 0.0:
        pen += a * a
    if b < 0.0:
        pen += b * b
    cost += _NEG * pen
    if a < b:
        cost += _STRONGER
    return cost


@njit(nogil=True, cache=True, parallel=True)
def init_fit(coarse, r, wre, wim, k, periods, lam_ratio, span, u1_out, u2_out):  # type: ignore[no-untyped-def]
    """Per pixel the two copies' codes by a grid search: the stronger within ``span`` px of ``coarse`` (0.5 px
    steps), the other over the coarsest period (2 px steps), then both on 5 x 5 grids of 1, 0.5, 0.25 and 0.1
    px steps around the best. ``u2_out`` is modulo the coarsest period. ``wre``, ``wim`` (S, N) the sums as ``C``,
    ``-S`` (the complex number whose angle is 2 pi u / P); ``k`` (S,) the clean modulation share per set;
    ``lam_ratio``: the weight of the prior c_s = k_s B is ``lam_ratio / (0.1 r)``."""
    n = coarse.shape[0]
    ns = periods.shape[0]
    p0 = periods[0]
    nsteps = int(span / 0.5)
    for i in prange(n):
        scratch = np.empty((3, ns))
        wr = np.empty(ns)
        wi = np.empty(ns)
        ri = r[i]
        yy = ri * ri
        for s in range(ns):
            wr[s] = wre[s, i]
            wi[s] = wim[s, i]
            yy += wr[s] * wr[s] + wi[s] * wi[s]
        lam = lam_ratio / (0.1 * ri + 1e-9)
        l2 = lam * lam
        best = _BIG
        b1 = coarse[i]
        b2 = 0.0
        for a in range(-nsteps, nsteps + 1):
            u1 = coarse[i] + 0.5 * a
            for q in range(int(p0)):
                c = _fit_cost(u1, float(q), ri, wr, wi, yy, k, periods, l2, scratch)
                if c < best:
                    best = c
                    b1 = u1
                    b2 = float(q)
        for step in (1.0, 0.5, 0.25, 0.1):
            c1 = b1
            c2 = b2
            for a in range(-2, 3):
                for q in range(-2, 3):
                    if a == 0 and q == 0:
                        continue
                    u1 = c1 + step * a
                    u2 = c2 + step * q
                    c = _fit_cost(u1, u2, ri, wr, wi, yy, k, periods, l2, scratch)
                    if c < best:
                        best = c
                        b1 = u1
                        b2 = u2
        u1_out[i] = b1
        u2_out[i] = b2 - p0 * math.floor(b2 / p0)


@njit(nogil=True, cache=True, inline="always")
def _wrap(x, p):  # type: ignore[no-untyped-def]
    """``x`` into [-p / 2, p / 2)."""
    return x - p * math.floor(x / p + 0.5)


@njit(nogil=True, cache=True, parallel=True)
def wrapped_planes(index, vals_in, cy, cx, p0, radius, min_scale, plane, inliers, scale):  # type: ignore[no-untyped-def]
    """Per centre (cy, cx) a robust plane through the values ``vals_in`` (modulo ``p0``; ``p0`` <= 0: not
    wrapped) of the pixels within ``radius`` (``index`` (H, W) int32: each pixel's entry, -1 for none): slopes
    from the median of the (wrapped) differences to the right and lower neighbours, the offset from the
    (circular) mean, then four reweighted least-squares steps on the residuals within 2.5 times their robust
    scale (at least ``min_scale``). ``plane`` (N, 3): value at the centre (modulo ``p0``), slope per column, per
    row; ``inliers`` the share of the window's pixels within that band, ``scale`` the robust scale; NaN / 0 where
    the window has fewer than 20 pixels."""
    h, w = index.shape
    n = cy.shape[0]
    side = 2 * radius + 1
    wrapped = p0 > 0.0
    for i in prange(n):
        y = cy[i]
        x = cx[i]
        y0 = max(y - radius, 0)
        y1 = min(y + radius + 1, h)
        x0 = max(x - radius, 0)
        x1 = min(x + radius + 1, w)
        vals = np.empty(side * side)
        dx = np.empty(side * side)
        dy = np.empty(side * side)
        gx = np.empty(side * side)
        gy = np.empty(side * side)
        cnt = 0
        ngx = 0
        ngy = 0
        for yy in range(y0, y1):
            for xx in range(x0, x1):
                j = index[yy, xx]
                if j < 0:
                    continue
                vals[cnt] = vals_in[j]
                dx[cnt] = float(xx - x)
                dy[cnt] = float(yy - y)
                cnt += 1
                # neighbours on the index's lattice: the next entry to the right and below within 4 px
                for d in range(1, 5):
                    if xx + d < x1 and index[yy, xx + d] >= 0:
                        t = vals_in[index[yy, xx + d]] - vals_in[j]
                        gx[ngx] = (_wrap(t, p0) if wrapped else t) / d
                        ngx += 1
                        break
                for d in range(1, 5):
                    if yy + d < y1 and index[yy + d, xx] >= 0:
                        t = vals_in[index[yy + d, xx]] - vals_in[j]
                        gy[ngy] = (_wrap(t, p0) if wrapped else t) / d
                        ngy += 1
                        break
        if cnt < 20 or ngx < 5 or ngy < 5:
            plane[i, 0] = np.nan
            plane[i, 1] = np.nan
            plane[i, 2] = np.nan
            inliers[i] = 0.0
            scale[i] = np.nan
            continue
        px = np.median(gx[:ngx])
        py = np.median(gy[:ngy])
        if wrapped:
            sre = 0.0
            sim = 0.0
            for j in range(cnt):
                t = _TWO_PI * (vals[j] - px * dx[j] - py * dy[j]) / p0
                sre += math.cos(t)
                sim += math.sin(t)
            c0 = math.atan2(sim, sre) * p0 / _TWO_PI
        else:
            for j in range(cnt):
                gx[j] = vals[j] - px * dx[j] - py * dy[j]
            c0 = np.median(gx[:cnt])
        res = np.empty(cnt)
        ares = np.empty(cnt)
        s = min_scale
        good = 0
        for _it in range(4):
            for j in range(cnt):
                t = vals[j] - c0 - px * dx[j] - py * dy[j]
                res[j] = _wrap(t, p0) if wrapped else t
                ares[j] = abs(res[j])
            s = max(min_scale, 1.4826 * np.median(ares))
            lim = 2.5 * s
            # least squares on the inliers: 3 x 3 normal equations of (1, dx, dy)
            a00 = 0.0
            a01 = 0.0
            a02 = 0.0
            a11 = 0.0
            a12 = 0.0
            a22 = 0.0
            b0 = 0.0
            b1 = 0.0
            b2 = 0.0
            good = 0
            for j in range(cnt):
                if ares[j] < lim:
                    good += 1
                    a00 += 1.0
                    a01 += dx[j]
                    a02 += dy[j]
                    a11 += dx[j] * dx[j]
                    a12 += dx[j] * dy[j]
                    a22 += dy[j] * dy[j]
                    b0 += res[j]
                    b1 += dx[j] * res[j]
                    b2 += dy[j] * res[j]
            det = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
            if good < 10 or abs(det) < 1e-9:
                break
            d0 = (b0 * (a11 * a22 - a12 * a12) - a01 * (b1 * a22 - a12 * b2) + a02 * (b1 * a12 - a11 * b2)) / det
            d1 = (a00 * (b1 * a22 - b2 * a12) - b0 * (a01 * a22 - a12 * a02) + a02 * (a01 * b2 - b1 * a02)) / det
            d2 = (a00 * (a11 * b2 - a12 * b1) - a01 * (a01 * b2 - b1 * a02) + b0 * (a01 * a12 - a11 * a02)) / det
            c0 += d0
            px += d1
            py += d2
        plane[i, 0] = c0 - p0 * math.floor(c0 / p0) if wrapped else c0
        plane[i, 1] = px
        plane[i, 2] = py
        inliers[i] = good / cnt
        scale[i] = s


@njit(nogil=True, cache=True, parallel=True)
def ghost_terms(index, cy, cx, u1, u2, r, wre, wim, k, periods, rho, ok, radius, gre, gim):  # type: ignore[no-untyped-def]
    """Per centre (cy, cx) and set the second copy's complex modulation: the median over the window's entries
    (``index``; those with ``ok``) of ``(W_s - k_s A e^(i 2 pi u1 / P_s)) e^(-i 2 pi u2 / P_s)`` with
    ``A = r / (1 + rho)``: the second copy's share and any phase its light carries beyond its code. ``u1``,
    ``u2``, ``r``, ``wre``, ``wim`` per entry; ``gre``, ``gim`` (S, N centres)."""
    h, w = index.shape
    n = cy.shape[0]
    ns = periods.shape[0]
    side = 2 * radius + 1
    for i in prange(n):
        y = cy[i]
        x = cx[i]
        bre = np.empty(side * side)
        bim = np.empty(side * side)
        for s in range(ns):
            cnt = 0
            for yy in range(max(y - radius, 0), min(y + radius + 1, h)):
                for xx in range(max(x - radius, 0), min(x + radius + 1, w)):
                    j = index[yy, xx]
                    if j < 0 or not ok[j]:
                        continue
                    a = r[j] / (1.0 + rho)
                    t1 = _TWO_PI * u1[j] / periods[s]
                    t2 = _TWO_PI * u2[j] / periods[s]
                    dre = wre[s, j] - k[s] * a * math.cos(t1)
                    dim = wim[s, j] - k[s] * a * math.sin(t1)
                    c2 = math.cos(t2)
                    s2 = math.sin(t2)
                    bre[cnt] = dre * c2 + dim * s2
                    bim[cnt] = dim * c2 - dre * s2
                    cnt += 1
            if cnt < 5:
                gre[s, i] = np.nan
                gim[s, i] = np.nan
            else:
                gre[s, i] = np.median(bre[:cnt])
                gim[s, i] = np.median(bim[:cnt])


@njit(nogil=True, cache=True, parallel=True)
def direct_codes(coarse, u2, wre, wim, gre, gim, periods, u1, agree, direct):  # type: ignore[no-untyped-def]
    """Per pixel the stronger copy's code once the second copy's terms are taken off every set's sums,
    unwrapped from ``coarse`` through the sets coarse to fine; ``agree`` the finest set's distance to the
    one before (px), ``direct`` (S, N) the stronger copy's modulation |W_s - G_s| per set."""
    n = coarse.shape[0]
    ns = periods.shape[0]
    for i in prange(n):
        prev = coarse[i]
        last = prev
        for s in range(ns):
            p = periods[s]
            t2 = _TWO_PI * u2[i] / p
            c2 = math.cos(t2)
            s2 = math.sin(t2)
            dre = wre[s, i] - (gre[s, i] * c2 - gim[s, i] * s2)
            dim = wim[s, i] - (gre[s, i] * s2 + gim[s, i] * c2)
            direct[s, i] = math.sqrt(dre * dre + dim * dim)
            frac = math.atan2(dim, dre) * p / _TWO_PI
            frac -= p * math.floor(frac / p)
            val = frac + p * math.floor((prev - frac) / p + 0.5)
            last = prev
            prev = val
        u1[i] = prev
        agree[i] = abs(prev - last) if ns > 1 else 0.0
