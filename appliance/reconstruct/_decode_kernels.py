"""numba kernels of the structured-light decoder (private; see :mod:`appliance.reconstruct.decode`).

Bit-exact streaming: everything a frame contributes before the final per-pixel step is exact
(integers, and phase sums of products with coefficients quantised to 2**-20, which float64 adds
exactly in any order). Batch and streaming then run the same :func:`_finish_row`, so both give
the same bits whatever order frames arrive in.

Plan tables (built by ``decode.plan_decode``):

- ``gray_tab`` int64 (G, 4): axis (0 = x, 1 = y), bit, positive frame, negative frame (-1: absent).
  The positive frame is lit where the bit is 1; a bit with one frame is compared to (white + black) / 2,
  or without white and black to the mean of the reference phase set ``mean_idx`` (frame indices).
  Each bit's contrast ``|d|`` is kept per pixel (uint16, clipped at 65535) for the final step, which
  finds the weak bits against the pixel's own contrast floor and drops the finest unresolved ones.
- ``axis_tab`` int64 (2, 10): coded, has Gray, stripe (px), stripe count, tolerate one weak bit, size (px),
  edge-aware unwrapping (a phase set with source -3), Gray bits, XOR base bit (-1: plain Gray code), mask of
  the bits projected XOR the base. An XOR axis folds its bits as projected (bit b XOR the base) and un-XORs
  them in the final step; it never has edge-aware unwrapping, so its ``m1`` state carries the faint mask
  (:func:`_fold_faint`) instead of the edge keys.
- ``ph_tab`` int64 (S, 4): axis, steps, source (-2 axis centre, -1 Gray stripe centre, -3 Gray edge-aware,
  1 previous set), first row
  in ``ph_idx`` / ``ph_sin`` / ``ph_cos``; sets ordered coarse to fine within an axis.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import appliance._numba_cache  # noqa: F401  (the cache folder, before any kernel is defined)
from appliance.reconstruct._geom_kernels import true_span

BIG = np.uint32(0x7FFFFFFF)  # "no contrast seen yet"
#: A Gray bit whose contrast is below this fraction of the next weakest bit marks a stripe edge.
EDGE_RATIO = 0.75
#: A finer phase period whose modulation is below this fraction of the coarser period's is blurred away by
#: the optics (attenuation grows with 1/period**2), not merely noisy: the pixel keeps the coarser result.
BLUR_RATIO = 0.5
#: ... and only when the coarser period is at least this many times longer (periods [16, 8] qualify): close
#: periods (66.7 / 100 px) are attenuated almost alike by blur, so a weak finer one means a bad pixel, not blur.
FALLBACK_PERIOD_RATIO = 2.0
#: Gray against phase: a pixel's unwrapped phase coordinate lies inside its Gray stripe (half a stripe from the
#: stripe centre), with this margin for blur and noise, in stripes; farther means the Gray code and the phase
#: saw different light (a second copy of the pattern by interreflection, a mixed pixel): the pixel is dropped.
CONSISTENCY_MARGIN = 0.25
#: Two phase frequencies against each other: a finer set unwrapped by the coarser result lands within half its period
#: of it by construction; a pixel farther than this share of the finer period from the coarser estimate is dropped.
#: On one surface lit once the coarser estimate's error is a small share of the finer period (a 4:1 ratio at
#: 0.05 rad of phase noise: 0.03 periods); near half a period the unwrapping picks a whole period at random, and a
#: second copy of the pattern (interreflection), which shifts the two frequencies' phases by unrelated amounts,
#: lands anywhere in it.
FREQUENCY_MARGIN = 0.35
#: An occlusion or shadow edge: a decoded pixel whose lit range (white - black) is below this share of the
#: brightest decoded 8-neighbour's, beside a neighbour with no projector light (shadow, too dark), takes its
#: light from the small part of its footprint that is lit: its centre most likely sees the unlit surface (a
#: pixel half covered reaches about half), so its code is a neighbouring surface's. At an occluding edge that is
#: another depth: the point lies on the lit surface behind, up to tens of mm from what the pixel's centre sees.
COVER_RATIO = 0.4
#: XOR codes: at an edge of the base bit every XOR bit has an edge too, so all of them are weak at once. Such a
#: pixel keeps its code (counted as one weak bit, the base's) where the base and every XOR bit still reach this
#: fraction of the Gray contrast floor: their signs then agree on the side of the edge, and bit b = its XOR
#: frame's bit XOR the base's is right on either side. Fainter, the signs are noise and the pixel is dropped.
XOR_FAINT_RATIO = 0.5
#: Two copies of the pattern (a mirror-like face re-projects it; interreflection): where the light of two projector
#: pixels adds, every Gray bit on which their codes differ has the contrast |a - b| instead of a + b, while a clean
#: pixel has at most one bit short of full contrast (the one whose stripe edge it sits on). A pixel is dropped
#: (reason interreflection) where two or more of its decoded Gray bits of period up to :data:`BLEND_PERIOD_PX` stay
#: under the decoder's blend ratio (``DecodeParams.blend_ratio``, of white - black), and at least
#: :data:`BLEND_NEIGHBOURS` of its 8 neighbours are marked too: a re-projected pattern covers a region, while a
#: lone pixel marked on a matte surface is noise or diffuse indirect light (dropping it would also cost its
#: neighbours their points in the neighbour filter). Only fine bits count: diffuse indirect light of a coarse
#: pattern lowers its contrast without changing its sign, and averages out on a fine one. Where the optics blur the
#: finest bits away, contrast falls off toward the finest kept bits: the run of such bits from the finest kept bit
#: up is that fall-off, not a second pattern, and does not count (a second pattern dims bits at random).
BLEND_PERIOD_PX = 512
BLEND_NEIGHBOURS = 3
#: The flag in ``levels[0]`` (Gray bits dropped: < 32) of a pixel the blend check marked, until
#: :func:`blend_regions` has decided (then clear again).
BLEND_FLAG = 0x80
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


_U1 = np.uint32(1)
_U2 = np.uint32(2)
_U4 = np.uint32(4)
_U8 = np.uint32(8)
_U16 = np.uint32(16)
_U5 = np.uint32(5)
_U31 = np.uint32(31)


@njit(nogil=True, cache=True, error_model="numpy")
def _gray_to_binary(g):  # type: ignore[no-untyped-def]
    """Prefix XOR of a uint32 Gray code (uint32 shift amounts keep it vectorisable)."""
    g ^= g >> _U1
    g ^= g >> _U2
    g ^= g >> _U4
    g ^= g >> _U8
    g ^= g >> _U16
    return g


@njit(nogil=True, cache=True, error_model="numpy")
def _add_bit(d_row, bit, code, cst):  # type: ignore[no-untyped-def]
    """Fold one Gray bit's signed contrast row ``d_row`` into code (uint32) and its contrast row (uint16, or
    uint8 when the caller knows every ``|d|`` is at most 255)."""
    on = np.uint32(1 << bit)
    off = np.uint32(0)
    for x in range(d_row.shape[0]):
        code[x] |= on if d_row[x] > 0 else off
    for x in range(d_row.shape[0]):  # uint16, or uint8 where every contrast fits (pairs of 8-bit frames)
        cst[x] = min(abs(d_row[x]), 65535)


@njit(nogil=True, cache=True, error_model="numpy")
def _popcount(v):  # type: ignore[no-untyped-def]
    """Set bits of a uint32 (SWAR without a multiply, so that numba's 64-bit promotion cannot spill)."""
    v = np.uint32(v)
    v = np.uint32(v - ((v >> _U1) & np.uint32(0x55555555)))
    v = np.uint32((v & np.uint32(0x33333333)) + ((v >> _U2) & np.uint32(0x33333333)))
    v = np.uint32((v + (v >> _U4)) & np.uint32(0x0F0F0F0F))
    v = np.uint32(v + (v >> _U8))
    v = np.uint32(v + (v >> _U16))
    return np.uint32(v & np.uint32(0x3F))


# The final step is split into short loops over a row, each touching few arrays, so that LLVM
# vectorises them (numba cannot declare arrays non-aliasing; long loops over many arrays stay scalar).


# The per-pixel arithmetic is float32 (8 SIMD lanes): coordinates up to 2**14 px keep ~1e-3 px, far below
# decoding noise; the exact float64 phase sums are rounded once, identically in batch and streaming.
_F0 = np.float32(0.0)
_FHALF = np.float32(0.5)
_F1 = np.float32(1.0)
_FNAN = np.float32(np.nan)
_FINF = np.float32(np.inf)
_FPI = np.float32(math.pi)
_FHALF_PI = np.float32(0.5 * math.pi)
_FEDGE = np.float32(EDGE_RATIO)
_B0 = np.float32(_A0)
_B1 = np.float32(_A1)
_B2 = np.float32(_A2)
_B3 = np.float32(_A3)
_B4 = np.float32(_A4)
_B5 = np.float32(_A5)
_B6 = np.float32(_A6)
_B7 = np.float32(_A7)
_B8 = np.float32(_A8)


_FTINY = np.float32(1e-30)


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _atan2_f32(y, x):  # type: ignore[no-untyped-def]
    """Branch-free atan2 in float32 (error ~1e-7 rad; atan2(0, 0) = 0): selects only, so a loop vectorises 8 wide."""
    ax = abs(x)
    ay = abs(y)
    swap = ay > ax
    hi = ay if swap else ax
    lo = ax if swap else ay
    t = lo / (hi if hi > _FTINY else _FTINY)  # hi = 0 means lo = 0: t = 0
    t2 = t * t
    p = _B8
    p = p * t2 + _B7
    p = p * t2 + _B6
    p = p * t2 + _B5
    p = p * t2 + _B4
    p = p * t2 + _B3
    p = p * t2 + _B2
    p = p * t2 + _B1
    p = p * t2 + _B0
    a = t * p
    a = _FHALF_PI - a if swap else a
    a = _FPI - a if x < _F0 else a
    return -a if y < _F0 else a


@njit(nogil=True, cache=True, error_model="numpy")
def _fold_weak(c, bit, relg, weak, qa, relb, soft):  # type: ignore[no-untyped-def]
    """One bit's contrasts ``c`` (float32) into the weak-bit mask, the weakest strong contrast ``qa`` and the
    mask of bits under the blend floor ``relb`` (``soft``).

    Bits below the dropped level are all weak, so the weakest strong bit is the weakest one the decode
    relied on, whatever the level.
    """
    on = np.uint32(1) << np.uint32(bit)
    zero = np.uint32(0)
    for x in range(c.shape[0]):
        strong = c[x] >= relg[x]
        weak[x] |= zero if strong else on
        soft[x] |= zero if c[x] >= relb[x] else on
        qa[x] = np.fmin(qa[x], c[x] if strong else _FINF)


@njit(nogil=True, cache=True, error_model="numpy")
def _fold_keys(c, bit, m1, m2):  # type: ignore[no-untyped-def]
    """The two smallest keys ``contrast * 32 + bit`` (for the edge-aware unwrapping)."""
    b = np.uint32(bit)
    for x in range(c.shape[0]):
        key = (np.uint32(np.int32(c[x])) << _U5) | b
        m2[x] = min(m2[x], max(m1[x], key))
        m1[x] = min(m1[x], key)


@njit(nogil=True, cache=True, error_model="numpy")
def _fold_faint(c, bit, relg, keep):  # type: ignore[no-untyped-def]
    """XOR axes: clear bit ``bit`` of ``keep`` (initially :data:`BIG`) where the contrast ``c`` is below
    :data:`XOR_FAINT_RATIO` of the Gray floor ``relg``."""
    off = ~(np.uint32(1) << np.uint32(bit))
    every = np.uint32(0xFFFFFFFF)
    ratio = np.float32(XOR_FAINT_RATIO)
    for x in range(c.shape[0]):
        keep[x] &= every if c[x] >= ratio * relg[x] else off


@njit(nogil=True, cache=True, error_model="numpy")
def _faint_bit(axis_tab, a, bit):  # type: ignore[no-untyped-def]
    """Whether Gray bit ``bit`` of axis ``a`` is the XOR base or projected XOR it (its contrast folds into the faint
    mask)."""
    base = axis_tab[a, 8]
    return base >= 0 and (bit == base or ((axis_tab[a, 9] >> bit) & 1) != 0)


@njit(nogil=True, cache=True, error_model="numpy")
def _xor_weak(weak, keep, base, xmask):  # type: ignore[no-untyped-def]
    """XOR axes: at an edge of the base bit every XOR bit flips too, so the base and any of them may be weak. Where
    the base is weak, or two or more of these bits are, and none of them is faint, their weakness is the base's:
    only the base counts as weak. Where one of them is faint the pixel fails (every bit weak): a wrong sign there
    would flip XOR bits far from the edge. One weak XOR bit alone (the base strong) is that bit's own edge."""
    bb = np.uint32(1) << np.uint32(base)
    need = np.uint32(bb | np.uint32(xmask))
    every = np.uint32(0xFFFFFFFF)
    zero = np.uint32(0)
    for x in range(weak.shape[0]):
        w = np.uint32(weak[x])
        e = np.uint32(w & need)
        edge = ((e & bb) != zero) | (np.uint32(e & np.uint32(e - _U1)) != zero)
        clear = (np.uint32(keep[x]) & need) == need
        weak[x] = (np.uint32((w & ~need) | bb) if clear else every) if edge else w


@njit(nogil=True, cache=True, error_model="numpy")
def _xor_code(code, fl, base, xmask, out, ok):  # type: ignore[no-untyped-def]
    """The Gray code of an XOR axis: its XOR bits XOR the base bit; a pixel whose base bit was dropped (finer than
    the optics resolve: ``fl`` > base) cannot un-XOR and fails."""
    b = np.uint32(base)
    xm = np.uint32(xmask)
    zero = np.uint32(0)
    for x in range(code.shape[0]):
        c = np.uint32(code[x])
        out[x] = c ^ (xm if ((c >> b) & _U1) != zero else zero)
        ok[x] = ok[x] & (fl[x] <= b)


@njit(nogil=True, cache=True, error_model="numpy")
def _fold_d(d, bit, relg, keys, cf, code, weak, qa, m1, m2, relb, soft, faint=False):  # type: ignore[no-untyped-def]
    """Batch: a bit's signed contrast row ``d`` into the code and the axis' gate state (``cf`` scratch)."""
    on = np.uint32(1 << bit)
    off = np.uint32(0)
    for x in range(d.shape[0]):
        code[x] |= on if d[x] > 0 else off
    for x in range(d.shape[0]):
        cf[x] = np.float32(min(abs(d[x]), 65535))
    _fold_weak(cf, bit, relg, weak, qa, relb, soft)
    if keys:
        _fold_keys(cf, bit, m1, m2)
    elif faint:
        _fold_faint(cf, bit, relg, m1)


@njit(nogil=True, cache=True, error_model="numpy")
def _fold_cst(cst, bit, relg, keys, cf, weak, qa, m1, m2, relb, soft, faint=False):  # type: ignore[no-untyped-def]
    """Streaming: a bit's stored contrasts (uint8 or uint16) into the axis' gate state, as :func:`_fold_d` does."""
    for x in range(cst.shape[0]):
        cf[x] = np.float32(cst[x])
    _fold_weak(cf, bit, relg, weak, qa, relb, soft)
    if keys:
        _fold_keys(cf, bit, m1, m2)
    elif faint:
        _fold_faint(cf, bit, relg, m1)


@njit(nogil=True, cache=True, error_model="numpy")
def _gray_level(weak, tol, nbits, finest, fl, ok):  # type: ignore[no-untyped-def]
    """Bits dropped per pixel (``fl``) and whether the rest decodes.

    At most ``tol`` weak bits: full resolution (one weak bit is a stripe edge). Otherwise, with ``finest``,
    the contiguous weak bits from bit 0 (stripes finer than the optics resolve) are dropped and at most
    ``tol`` weak bits may remain above them.
    """
    one = tol != 0
    nb = np.uint32(nbits)
    zero = np.uint32(0)
    for x in range(weak.shape[0]):
        w = np.uint32(weak[x])
        full = (w == zero) | (one & (np.uint32(w & np.uint32(w - _U1)) == zero))  # at most tol (0 or 1) bits
        below = np.uint32(np.uint32(w ^ np.uint32(w + _U1)) >> _U1)  # the contiguous weak bits from bit 0
        f = _popcount(below)
        rest = np.uint32(w & np.uint32(~below))
        trunc = finest & ((rest == zero) | (one & (np.uint32(rest & np.uint32(rest - _U1)) == zero))) & (f < nb)
        fl[x] = np.uint32(0) if full else f
        ok[x] = full | trunc


@njit(nogil=True, cache=True, error_model="numpy")
def _blend_gate(soft, fl, ok, blend, nfine):  # type: ignore[no-untyped-def]
    """Two copies of the pattern (see :data:`BLEND_PERIOD_PX`): mark in ``blend`` the pixels where two or more of
    the fine bits ``fl .. nfine - 1`` are under the blend floor, not counting the run of such bits from bit ``fl``
    up (the optics' fall-off toward the finest bits)."""
    fine = np.uint32((np.uint32(1) << np.uint32(nfine)) - _U1)
    two = np.uint32(2)
    for x in range(soft.shape[0]):
        s = np.uint32(np.uint32(soft[x]) & fine) >> np.uint32(fl[x])
        run = np.uint32(np.uint32(s ^ np.uint32(s + _U1)) >> _U1)  # the contiguous bits from bit fl
        blend[x] |= ok[x] & (_popcount(np.uint32(s & ~run)) >= two)


@njit(nogil=True, cache=True, error_model="numpy")
def _mark_blend(blend, lev):  # type: ignore[no-untyped-def]
    """:data:`BLEND_FLAG` into ``lev`` where the blend check marked the pixel (:func:`blend_regions` decides)."""
    flag = np.uint8(BLEND_FLAG)
    zero = np.uint8(0)
    for x in range(blend.shape[0]):
        lev[x] |= flag if blend[x] else zero


@njit(nogil=True, cache=True, error_model="numpy")
def _gray_index(code, fl, stripe, nstripes, cg, ok):  # type: ignore[no-untyped-def]
    """Stripe centre of the code without its ``fl`` dropped bits (Gray: the top bits of G(k) are G(k >> fl))."""
    stripe = np.float32(stripe)
    for x in range(code.shape[0]):
        f = fl[x]
        k = np.int32(_gray_to_binary(code[x] >> f))  # int32 -> float vectorises on AVX2
        n = np.int32((np.uint32(nstripes) + (_U1 << f) - _U1) >> f)
        width = stripe * np.float32(np.int32(_U1 << f))
        cg[x] = (np.float32(k) + _FHALF) * width - _FHALF
        ok[x] = ok[x] & (k < n)


@njit(nogil=True, cache=True, error_model="numpy")
def _gray_edge(code, m1, m2, stripe, cg, cb):  # type: ignore[no-untyped-def]
    """Edge-aware coarse estimate: the stripe edge where the weakest bit flips, if it is clearly weak.

    With stripe = period, both edges of a stripe have the same phase, so a pixel on an edge needs to
    know which edge; the weakest bit names it (the edge to the neighbouring stripe where it flips).
    """
    stripe = np.float32(stripe)
    for x in range(code.shape[0]):
        g = code[x]
        k = np.int32(_gray_to_binary(g))
        flip = np.uint32(1) << (m1[x] & _U31)
        k2 = np.int32(_gray_to_binary(g ^ flip))
        weak = np.float32(np.int32(m1[x] >> _U5)) < _FEDGE * np.float32(np.int32(m2[x] >> _U5))
        near = weak & (abs(k2 - k) == 1)
        edge = np.float32(max(k, k2)) * stripe - _FHALF
        cb[x] = edge if near else cg[x]


@njit(nogil=True, cache=True, error_model="numpy", fastmath={"contract"})
def _phase_wrapped(ss, cs, quantum, scale, period, mod, cph):  # type: ignore[no-untyped-def]
    """Modulation and wrapped coordinate of a row. The exact sums (float64, or int32 in units of ``quantum``)
    are rounded to float32 first: rounding an int32 and then scaling it by a power of two gives the float32
    that rounding the float64 sum gives."""
    scale = np.float32(scale)
    q = np.float32(quantum)
    per = np.float32(period)
    k = np.float32(period / _TWO_PI)
    for x in range(ss.shape[0]):  # the conversion apart, so the next loop is all 8-lane float32
        mod[x] = np.float32(ss[x]) * q
        cph[x] = np.float32(cs[x]) * q
    for x in range(ss.shape[0]):
        sv = mod[x]
        cv = cph[x]
        c = k * _atan2_f32(-sv, cv)
        cph[x] = c + per if c < _F0 else c
        mod[x] = scale * math.sqrt(sv * sv + cv * cv)


@njit(nogil=True, cache=True, error_model="numpy")
def _unwrap(cph, c0, period, cc):  # type: ignore[no-untyped-def]
    per = np.float32(period)
    inv = np.float32(1.0 / period)
    for x in range(cph.shape[0]):
        c = cph[x]
        cc[x] = c + per * np.floor((c0[x] - c) * inv + _FHALF)


@njit(nogil=True, cache=True, error_model="numpy")
def _phase_gate(mod, relv, ok, qa):  # type: ignore[no-untyped-def]
    for x in range(mod.shape[0]):
        ok[x] = ok[x] & (mod[x] >= relv[x])
    for x in range(mod.shape[0]):
        qa[x] = np.fmin(qa[x], mod[x])


@njit(nogil=True, cache=True, error_model="numpy")
def _phase_fallback(mod, mprev, relv, prev, cc, ok, qa, scale):  # type: ignore[no-untyped-def]
    """A finer phase set counts where it has modulation and is the more precise of the two: its modulation at
    least ``scale`` (this period / the coarser one) times the coarser set's ``mprev``, where the two phase noises
    are equal. Elsewhere the coarser result ``prev`` stays: where the finer set is less precise, or has no
    modulation because the optics blur it away (under :data:`BLUR_RATIO` of ``mprev``); a finer set that is
    merely weak (noise, shadow edge) still rejects the pixel.

    The code noise a sigma is computed from assumes the finest period (``uncertainty.CodeNoise``: the phase
    noise in projector px grows with the period over the modulation), so a pixel left on the coarser set has
    its quality ``qa`` scaled by ``scale`` = this period / the coarser one: its sigma is then that of the
    coarser period (scaled again at each set it falls back through)."""
    ratio = np.float32(BLUR_RATIO)
    sc = np.float32(scale)
    for x in range(mod.shape[0]):
        good = mod[x] >= relv[x]
        blurred = mod[x] < ratio * mprev[x]
        better = mod[x] >= sc * mprev[x]
        fine = good & better
        cc[x] = cc[x] if fine else prev[x]
        ok[x] = ok[x] & (fine | ~better | blurred)
        qa[x] = np.fmin(qa[x], mod[x]) if fine else qa[x] * sc
        mprev[x] = mod[x] if fine else mprev[x]


@njit(nogil=True, cache=True, error_model="numpy")
def _unwrap_gate(fl, stripe, period, ok):  # type: ignore[no-untyped-def]
    """A Gray code unwraps a phase set only while its effective stripe is at most half the period."""
    half = np.float32(0.5 * period)
    st = np.float32(stripe)
    for x in range(fl.shape[0]):
        f = fl[x]
        ok[x] = ok[x] & ((f == np.uint32(0)) | (st * np.float32(np.int32(_U1 << f)) <= half))


@njit(nogil=True, cache=True, error_model="numpy")
def _consistency_gate(cc, cg, fl, stripe, ok):  # type: ignore[no-untyped-def]
    """Gray against phase: keep a pixel only where its unwrapped coordinate ``cc`` lies within half its Gray
    stripe (``stripe * 2**fl`` wide, centre ``cg``) plus :data:`CONSISTENCY_MARGIN` stripes."""
    st = np.float32(stripe)
    margin = np.float32(CONSISTENCY_MARGIN * stripe)
    half = np.float32(0.5)
    for x in range(cc.shape[0]):
        lim = half * st * np.float32(np.int32(_U1 << fl[x])) + margin
        ok[x] = ok[x] & (abs(cc[x] - cg[x]) <= lim)


@njit(nogil=True, cache=True, error_model="numpy")
def _frequency_gate(cc, cb, period, mod, relv, ok):  # type: ignore[no-untyped-def]
    """Two phase frequencies: where the finer set has modulation (``mod >= relv``), keep a pixel only where its
    unwrapped coordinate ``cc`` lies within :data:`FREQUENCY_MARGIN` finer periods of the coarser result ``cb``."""
    lim = np.float32(FREQUENCY_MARGIN * period)
    for x in range(cc.shape[0]):
        ok[x] = ok[x] & ((mod[x] < relv[x]) | (abs(cc[x] - cb[x]) <= lim))


@njit(nogil=True, cache=True, error_model="numpy")
def _emit_axis(cc, ok, lit, out):  # type: ignore[no-untyped-def]
    for x in range(cc.shape[0]):
        good = ok[x] & lit[x]
        out[x] = cc[x] if good else _FNAN
        lit[x] = good


@njit(nogil=True, cache=True, error_model="numpy")
def _lit_row(r, rel, thr, relv, relg, lit, blend, relb):  # type: ignore[no-untyped-def]
    """Contrast floors: ``relv`` for phase modulations, ``relg`` = ceil of it for integer Gray contrasts
    (an integer c >= rel * r exactly when c >= ceil(rel * r), so float32 decides as float64 would); ``relb``
    = ceil(blend * r), the blend check's floor (0: off)."""
    for x in range(r.shape[0]):
        rr = np.float64(r[x])
        f = rel * rr
        relv[x] = np.float32(f)
        relg[x] = np.float32(np.ceil(f))
        lit[x] = (rr >= thr) & (rr > 0.0)
        relb[x] = np.float32(np.ceil(blend * rr))


@njit(nogil=True, cache=True, error_model="numpy")
def _min_into(a, b):  # type: ignore[no-untyped-def]
    for x in range(a.shape[0]):
        a[x] = np.fmin(a[x], b[x])


@njit(nogil=True, cache=True, error_model="numpy")
def _mask_quality(lit, qmin, mask, quality):  # type: ignore[no-untyped-def]
    for x in range(lit.shape[0]):
        mask[x] = lit[x]
        quality[x] = qmin[x] if lit[x] else _F0


@njit(nogil=True, cache=True, error_model="numpy")
def _fringe_share(pmod, rng, lit, out):  # type: ignore[no-untyped-def]
    """``out`` = round(100 * pmod / rng), at most 255; 0 where unlit, without a modulation or a range."""
    for x in range(out.shape[0]):
        m = np.float64(pmod[x])
        rr = np.float64(rng[x])
        ok = lit[x] and rr > 0.0 and m < np.inf
        out[x] = np.uint8(min(100.0 * m / rr + 0.5, 255.0)) if ok else np.uint8(0)


@njit(nogil=True, cache=True, error_model="numpy")
def _emit_level(fl, lit, lev):  # type: ignore[no-untyped-def]
    for x in range(fl.shape[0]):
        lev[x] = np.uint8(min(fl[x], np.uint32(255))) if lit[x] else np.uint8(0)


@njit(nogil=True, cache=True, error_model="numpy")
def _gate_init(weak, qg, m1, m2, soft):  # type: ignore[no-untyped-def]
    soft[:] = np.uint32(0)
    weak[:] = np.uint32(0)
    qg[:] = _FINF
    m1[:] = BIG
    m2[:] = BIG


@njit(nogil=True, cache=True, error_model="numpy")
def _round_robin(ch, nch, nthreads):  # type: ignore[no-untyped-def]
    """Block of rows that prange iteration ``ch`` of ``nch`` takes: prange hands each thread a contiguous run
    of iterations, and this spreads each thread's blocks over the whole image (lit rows cluster) while rows
    within a block stay contiguous (the frames' rows stream in order)."""
    per = nch // nthreads
    if per * nthreads != nch:
        return ch
    return (ch % per) * nthreads + ch // per


@njit(nogil=True, cache=True, error_model="numpy")
def _copy(dst, src):  # type: ignore[no-untyped-def]
    """dst = src, elementwise (a loop: numba's slice assignment of one array to another is ~8x slower)."""
    for x in range(dst.shape[0]):
        dst[x] = src[x]


@njit(nogil=True, cache=True, error_model="numpy")
def _unlit_outside(u, v, mask, quality, lev0, lev1, c0, c1):  # type: ignore[no-untyped-def]
    """Outputs of the pixels of a row outside its lit span c0 .. c1 - 1 (all of it when the span is empty):
    what the final step gives an unlit pixel, no code and no quality. One fill per output: a loop storing to
    all six stays scalar (numba cannot say they do not overlap); six fills vectorise (2 ms less on the
    reference scene, where half the pixels are unlit)."""
    w = u.shape[0]
    for lo, hi in ((0, c0), (max(c0, c1), w)):
        if hi > lo:
            u[lo:hi] = _FNAN
            v[lo:hi] = _FNAN
            mask[lo:hi] = False
            quality[lo:hi] = _F0
            lev0[lo:hi] = np.uint8(0)
            lev1[lo:hi] = np.uint8(0)


@njit(nogil=True, cache=True, error_model="numpy")
def _finish_row(  # type: ignore[no-untyped-def]
    lit_row, code, weak, qg, m1, m2, ssum, csum, quantum, axis_tab, ph_tab, ph_period, finest, u_row, v_row,
    mask_row, quality_row, lev0_row, lev1_row, scratch, fl_row, ok_row, c0, c1, xc_row, soft, blend_row, r_row,
    fr_row,
):  # fmt: skip
    """Per-pixel final step shared by batch and streaming: Gray level and index, phase, unwrapping.

    Runs over columns ``c0 .. c1 - 1`` (the row's lit span, see ``true_span``); the caller gives the
    pixels outside it their unlit outputs (:func:`_unlit_outside`). ``lit_row`` bool (W,) and ``scratch[0]`` (phase
    floor), ``scratch[8]`` (Gray floor) come from :func:`_lit_row`; ``code``, ``weak``, ``m1``, ``m2`` uint32
    (2, W) and ``qg`` float32 (2, W) hold each axis' folded Gray bits; ``ssum``/``csum`` (S, W) the phase sums,
    float64, or int32 in units of ``quantum`` (1.0 for float64);
    ``u_row``, ``v_row``, ``mask_row``, ``quality_row`` (W,) out; ``lev0_row``/``lev1_row`` uint8 (W,) out: Gray
    bits dropped on x / y; ``scratch`` float32 (11, W), ``fl_row`` uint32 (W,), ``ok_row`` bool (W,) are scratch
    (``scratch[10]``: the blend floor, from :func:`_lit_row`);
    ``xc_row`` uint32 (W,) holds an XOR axis' Gray code (``code`` stays as folded: streaming state); ``soft``
    uint32 (2, W) each axis' bits under the blend floor, ``blend_row`` bool (W,) scratch: the pixels the blend
    check marked get :data:`BLEND_FLAG` in ``lev0_row`` (see :func:`_blend_gate`, :func:`blend_regions`).
    ``r_row`` (W,) is the range (white - black) and ``fr_row`` uint8 (W,) out the fringe share: the weakest
    axis' last phase modulation in percent of the range (0 without a phase set or where unlit; see
    ``DecodedMaps.fringe``). ``scratch[11]`` holds that modulation.
    """
    lit = lit_row[c0:c1]
    fl = fl_row[c0:c1]
    ok = ok_row[c0:c1]
    relv = scratch[0, c0:c1]
    cg = scratch[1, c0:c1]
    cc = scratch[2, c0:c1]
    qs = scratch[3, c0:c1]
    qmin = scratch[4, c0:c1]
    mod = scratch[5, c0:c1]
    cph = scratch[6, c0:c1]
    cb = scratch[7, c0:c1]
    mprev = scratch[9, c0:c1]
    blend = blend_row[c0:c1]
    blend[:] = False
    qmin[:] = _FINF
    pmin = scratch[11, c0:c1]
    pmin[:] = _FINF
    for a in range(2):
        out = u_row[c0:c1] if a == 0 else v_row[c0:c1]
        lev = lev0_row[c0:c1] if a == 0 else lev1_row[c0:c1]
        if axis_tab[a, 0] == 0:
            out[:] = _FNAN
            lev[:] = np.uint8(0)
            continue
        stripe = np.float64(axis_tab[a, 2])
        ca = code[a, c0:c1]
        if axis_tab[a, 1] != 0:
            tol = 1 if axis_tab[a, 4] != 0 else 0
            base = axis_tab[a, 8]
            if base >= 0:
                _xor_weak(weak[a, c0:c1], m1[a, c0:c1], base, axis_tab[a, 9])
            _gray_level(weak[a, c0:c1], tol, axis_tab[a, 7], finest, fl, ok)
            if base < 0:
                nfine = 0
                while nfine < 31 and (axis_tab[a, 2] << (nfine + 2)) <= BLEND_PERIOD_PX:
                    nfine += 1
                _blend_gate(soft[a, c0:c1], fl, ok, blend, nfine)
            if base >= 0:
                _xor_code(code[a, c0:c1], fl, base, axis_tab[a, 9], xc_row[c0:c1], ok)
                ca = xc_row[c0:c1]
            _gray_index(ca, fl, stripe, axis_tab[a, 3], cg, ok)
            qa = qg[a, c0:c1]  # the weakest contrasts, lowered in place by the phase gates (qg is per-row state)
        else:
            ok[:] = True
            qa = qs
            qa[:] = _FINF
            fl[:] = np.uint32(0)
            cg[:] = np.float32(0.5 * np.float64(axis_tab[a, 5] - 1))
        res = cg  # the axis' coordinates: the Gray code's until a phase set writes cc (no copy)
        pprev = np.inf
        phased = False
        for s in range(ph_tab.shape[0]):
            if ph_tab[s, 0] != a:
                continue
            phased = True
            period = ph_period[s]
            _phase_wrapped(ssum[s, c0:c1], csum[s, c0:c1], quantum, 4.0 / np.float64(ph_tab[s, 1]), period, mod,
                           cph)  # fmt: skip
            src = ph_tab[s, 2]
            if src == -2:
                cb[:] = np.float32(0.5 * np.float64(axis_tab[a, 5] - 1))
                _unwrap(cph, cb, period, cc)
            elif src == -3:
                _gray_edge(ca, m1[a, c0:c1], m2[a, c0:c1], stripe, cg, cb)
                _unwrap(cph, cb, period, cc)
                _unwrap_gate(fl, stripe, period, ok)
            elif src > 0:
                _copy(cb, res)
                _unwrap(cph, cb, period, cc)
                _frequency_gate(cc, cb, period, mod, relv, ok)
                res = cc
                if finest and pprev >= FALLBACK_PERIOD_RATIO * period:
                    # a finer period the optics blur away leaves the pixel on the coarser one
                    _phase_fallback(mod, mprev, relv, cb, cc, ok, qa, period / pprev)
                    pprev = period
                    continue
            else:
                _unwrap(cph, cg, period, cc)
                _unwrap_gate(fl, stripe, period, ok)
                _consistency_gate(cc, cg, fl, stripe, ok)
            res = cc
            _phase_gate(mod, relv, ok, qa)
            _copy(mprev, mod)
            pprev = period
        _emit_axis(res, ok, lit, out)
        _emit_level(fl, lit, lev)
        _min_into(qmin, qa)
        if phased:
            _min_into(pmin, mod)
    _mask_quality(lit, qmin, mask_row[c0:c1], quality_row[c0:c1])
    _fringe_share(pmin, r_row[c0:c1], lit, fr_row[c0:c1])
    _mark_blend(blend, lev0_row[c0:c1])


# --------------------------------------------------------------------------------------------------
# Contrast-range histogram (for the scene-adaptive shadow threshold)
# --------------------------------------------------------------------------------------------------


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def range_hist(hi, lo, shift, nbins):  # type: ignore[no-untyped-def]
    """Histogram of ``max(hi - lo, 0) >> shift`` (clipped to ``nbins - 1``) over (H, W) images."""
    h, w = hi.shape[0], hi.shape[1]
    nch = min(h, 64)
    # neighbouring pixels mostly fall in one bin: four sub-histograms (small ones only) keep the increments
    # of consecutive pixels independent
    ways = 4 if nbins <= 1024 else 1
    parts = np.zeros((nch, ways, nbins), np.int64)
    top = np.int32(nbins - 1)
    for ch in prange(nch):
        dd = np.empty(w, np.int32)
        p = parts[ch]
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            a = hi[y]
            b = lo[y]
            for x in range(w):
                dd[x] = min(max(np.int32(a[x]) - np.int32(b[x]), 0) >> shift, top)
            m = 0
            if ways == 4:
                m = w - w % 4
                for x in range(0, m, 4):
                    p[0, dd[x]] += 1
                    p[1, dd[x + 1]] += 1
                    p[2, dd[x + 2]] += 1
                    p[3, dd[x + 3]] += 1
            for x in range(m, w):
                p[0, dd[x]] += 1
    out = np.zeros(nbins, np.int64)
    for ch in range(nch):
        for k in range(ways):
            for i in range(nbins):
                out[i] += parts[ch, k, i]
    return out


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def level_counts(lev, mask):  # type: ignore[no-untyped-def]
    """How many pixels with ``mask`` have each value 0..255 of ``lev`` (uint8, (H, W))."""
    h = lev.shape[0]
    nch = min(h, 64)
    parts = np.zeros((nch, 256), np.int64)
    for ch in prange(nch):
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            for x in range(lev.shape[1]):
                parts[ch, lev[y, x]] += np.int64(mask[y, x])
    return parts.sum(axis=0)


@njit(nogil=True, cache=True, error_model="numpy")
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


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
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


@njit(nogil=True, cache=True, error_model="numpy")
def _mean_diff(one, msum, n, sign, d):  # type: ignore[no-untyped-def]
    """Signed contrast of a frame against the mean of ``n`` phase frames (sum ``msum``), in pair units."""
    # floor(num / n) by a float64 division (vectorises; an integer division does not): num is an exact integer
    # in float64, so the quotient is exact where it is an integer and at least 1/n away from one elsewhere
    nf = np.float64(n)
    for x in range(d.shape[0]):
        num = np.float64(2 * (n * np.int32(one[x]) - msum[x]))
        d[x] = sign * np.int32(np.floor(num / nf))


@njit(nogil=True, cache=True, error_model="numpy")
def _gray_row(  # type: ignore[no-untyped-def]
    frames, y, c0, c1, wb, gray_tab, mean_idx, axis_tab, relg_row, d_row, cf_row, msum_row, code, weak, qg, m1, m2,
    relb_row, soft,
):
    """Every Gray bit of row ``y``, columns ``c0 .. c1 - 1``: pairs compare pattern and inverse, single
    frames (white + black) / 2 or, without white and black, the mean of the reference phase set ``mean_idx``."""
    w = c1 - c0
    relg, d, cf, msum = relg_row[c0:c1], d_row[c0:c1], cf_row[c0:c1], msum_row[c0:c1]
    nmean = np.int32(mean_idx.shape[0])
    if nmean > 0 and wb[0] < 0:
        for x in range(w):
            msum[x] = 0
        for i in range(mean_idx.shape[0]):
            row = frames[mean_idx[i], y, c0:c1]
            for x in range(w):
                msum[x] += np.int32(row[x])
    for g in range(gray_tab.shape[0]):
        a = gray_tab[g, 0]
        bit = gray_tab[g, 1]
        ip = gray_tab[g, 2]
        ineg = gray_tab[g, 3]
        if ip >= 0 and ineg >= 0:
            p = frames[ip, y, c0:c1]
            n = frames[ineg, y, c0:c1]
            for x in range(w):
                d[x] = np.int32(p[x]) - np.int32(n[x])
        else:
            one = frames[ip if ip >= 0 else ineg, y, c0:c1]
            sign = np.int32(1) if ip >= 0 else np.int32(-1)
            if wb[0] >= 0:
                wr = frames[wb[0], y, c0:c1]
                br = frames[wb[1], y, c0:c1]
                for x in range(w):
                    d[x] = sign * (2 * np.int32(one[x]) - np.int32(wr[x]) - np.int32(br[x]))
            else:
                _mean_diff(one, msum, nmean, sign, d)
        _fold_d(d, bit, relg, axis_tab[a, 6] != 0, cf, code[a, c0:c1], weak[a, c0:c1], qg[a, c0:c1], m1[a, c0:c1],
                m2[a, c0:c1], relb_row[c0:c1], soft[a, c0:c1], _faint_bit(axis_tab, a, bit))


_N5 = np.uint16(5)
_NBIG = np.uint16(0x7FFF)  # "no contrast seen yet" of the 16-bit lanes
_NINF = np.int16(0x7FFF)


@njit(nogil=True, cache=True, error_model="numpy")
def _relg16(relg, rg16):  # type: ignore[no-untyped-def]
    for x in range(relg.shape[0]):
        rg16[x] = np.int16(min(relg[x], np.float32(32767.0)))


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _diff16(p, n, wr, br, sign, pair, x):  # type: ignore[no-untyped-def]
    """Signed contrast of pixel ``x`` in 16-bit lanes: pattern - inverse for a pair, else
    sign (2 pattern - white - black)."""
    if pair:
        return np.int16(np.int16(p[x]) - np.int16(n[x]))
    return np.int16(sign * (2 * np.int16(p[x]) - np.int16(wr[x]) - np.int16(br[x])))


@njit(nogil=True, cache=True, error_model="numpy")
def _fold_row16(p, n, wr, br, sign, pair, bit, rg16, keys, code, weak, qa, m1, m2, rb16, soft):  # type: ignore[no-untyped-def]
    """:func:`_fold_d` in 16-bit lanes (8-bit frames: |contrast| <= 510, Gray bits <= 15), the same values, with
    each pixel's contrast formed in the loop (see :func:`_diff16`; no row of contrasts stored and read back)."""
    on = np.uint16(1 << bit)
    zero = np.uint16(0)
    for x in range(p.shape[0]):
        d = _diff16(p, n, wr, br, sign, pair, x)
        c = np.int16(abs(d))
        strong = c >= rg16[x]
        code[x] |= on if d > 0 else zero
        weak[x] |= zero if strong else on
        soft[x] |= zero if c >= rb16[x] else on
        qa[x] = min(qa[x], c if strong else _NINF)
    if keys:
        b = np.uint16(bit)
        for x in range(p.shape[0]):
            key = np.uint16((np.uint16(abs(_diff16(p, n, wr, br, sign, pair, x))) << _N5) | b)
            m2[x] = min(m2[x], max(m1[x], key))
            m1[x] = min(m1[x], key)


@njit(nogil=True, cache=True, error_model="numpy")
def _widen16(c16, w16, q16, a16, b16, keys, code, weak, qg, m1, m2, s16, soft):  # type: ignore[no-untyped-def]
    for x in range(code.shape[0]):
        code[x] = np.uint32(c16[x])
        weak[x] = np.uint32(w16[x])
        soft[x] = np.uint32(s16[x])
    for x in range(code.shape[0]):
        qg[x] = _FINF if q16[x] == _NINF else np.float32(q16[x])
    if keys:
        for x in range(code.shape[0]):
            m1[x] = BIG if a16[x] == _NBIG else np.uint32(a16[x])
            m2[x] = BIG if b16[x] == _NBIG else np.uint32(b16[x])


@njit(nogil=True, cache=True, error_model="numpy")
def _gray_row16(frames, y, c0, c1, wb, gray_tab, axis_tab, rg16, c16, w16, q16, a16, b16, rb16, s16):  # type: ignore[no-untyped-def]
    """:func:`_gray_row` for 8-bit frames with white/black or inverses, in 16-bit lanes."""
    rg = rg16[c0:c1]
    for g in range(gray_tab.shape[0]):
        a = gray_tab[g, 0]
        bit = gray_tab[g, 1]
        ip = gray_tab[g, 2]
        ineg = gray_tab[g, 3]
        pair = ip >= 0 and ineg >= 0
        one = frames[ip if ip >= 0 else ineg, y, c0:c1]
        # a pair's inverse, or the white and black rows that a single frame is thresholded against
        other = frames[ineg, y, c0:c1] if pair else one
        white = one if pair else frames[wb[0], y, c0:c1]
        black = one if pair else frames[wb[1], y, c0:c1]
        _fold_row16(one, other, white, black, np.int16(1) if ip >= 0 else np.int16(-1), pair, bit, rg,
                    axis_tab[a, 6] != 0, c16[a, c0:c1], w16[a, c0:c1], q16[a, c0:c1], a16[a, c0:c1],
                    b16[a, c0:c1], rb16[c0:c1], s16[a, c0:c1])  # fmt: skip


@njit(nogil=True, cache=True, error_model="numpy")
def _phase_row(frames, y, c0, c1, ph_tab, ph_idx, ph_sin, ph_cos, ssum, csum):  # type: ignore[no-untyped-def]
    """The phase sets' sine and cosine sums of row ``y``, columns c0 .. c1 - 1, exactly: float64 sums with
    float64 coefficients, or int32 sums with int32 coefficients in units of the quantum (8-bit frames: 16
    SIMD lanes instead of 8, 1.7x faster; the caller checked that no sum can leave int32)."""
    w = c1 - c0
    for s in range(ph_tab.shape[0]):
        ss = ssum[s, c0:c1]
        cs = csum[s, c0:c1]
        for x in range(w):
            ss[x] = 0.0
            cs[x] = 0.0
        first = ph_tab[s, 3]
        for k in range(first, first + ph_tab[s, 1]):
            row = frames[ph_idx[k], y, c0:c1]
            sk = ph_sin[k]
            ck = ph_cos[k]
            for x in range(w):
                ss[x] += row[x] * sk
                cs[x] += row[x] * ck


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def decode_stack(  # type: ignore[no-untyped-def]
    frames, wb, used, maxval, gray_tab, mean_idx, axis_tab, ph_tab, ph_period, ph_idx, ph_sin, ph_cos, quantum,
    rel, blend, thr, finest, nthreads, narrow, u, v, mask, quality, levels, fringe,
):  # fmt: skip
    """Decode a (F, H, W) stack into u, v, mask, quality, fringe (H, W) and levels (2, H, W) in one pass over rows.

    ``ph_sin``, ``ph_cos``: the phase coefficients, float64 (``quantum`` 1.0), or int32 in units of
    ``quantum`` where no phase sum can leave int32; the sums take their type.

    ``narrow``: 8-bit frames, <= 15 Gray bits per axis, no mean thresholding: Gray bits are folded in 16-bit
    lanes (twice the SIMD width, the same values). ``v`` with no rows: the y axis is not coded and not written.
    """
    h = frames.shape[1]
    w = frames.shape[2]
    nset = max(ph_tab.shape[0], 1)
    nch = min(h, 8 * nthreads)
    for ch in prange(nch):
        r = np.empty(w, np.int32)
        d = np.empty(w, np.int32)
        mx = np.empty(w, np.int32)
        mn = np.empty(w, np.int32)
        msum = np.empty(w, np.int32)
        cf = np.empty(w, np.float32)
        code = np.empty((2, w), np.uint32)
        weak = np.empty((2, w), np.uint32)
        m1 = np.empty((2, w), np.uint32)
        m2 = np.empty((2, w), np.uint32)
        qg = np.empty((2, w), np.float32)
        soft = np.empty((2, w), np.uint32)
        bl = np.empty(w, np.bool_)
        ssum = np.empty((nset, w), ph_sin.dtype)
        csum = np.empty((nset, w), ph_sin.dtype)
        scratch = np.empty((12, w), np.float32)
        fl = np.empty(w, np.uint32)
        xc = np.empty(w, np.uint32)
        ok = np.empty(w, np.bool_)
        lit = np.empty(w, np.bool_)
        vnone = np.empty(w, np.float32)
        rg16 = np.empty(w, np.int16)
        c16 = np.empty((2, w), np.uint16)
        w16 = np.empty((2, w), np.uint16)
        q16 = np.empty((2, w), np.int16)
        a16 = np.empty((2, w), np.uint16)
        b16 = np.empty((2, w), np.uint16)
        rb16 = np.empty(w, np.int16)
        s16 = np.empty((2, w), np.uint16)
        b = _round_robin(ch, nch, nthreads)
        for y in range(b * h // nch, (b + 1) * h // nch):
            _range_row(frames, y, wb, used, r, mx, mn, maxval)
            _lit_row(r, rel, thr, scratch[0], scratch[8], lit, blend, scratch[10])
            # only the lit span of the row is decoded: unlit pixels decode to nothing whatever their frames
            c0, c1 = true_span(lit)
            vrow = v[y] if v.shape[0] == h else vnone
            _unlit_outside(u[y], vrow, mask[y], quality[y], levels[0, y], levels[1, y], c0, c1)
            if c1 <= c0:
                continue
            if narrow:
                _relg16(scratch[8, c0:c1], rg16[c0:c1])
                _relg16(scratch[10, c0:c1], rb16[c0:c1])
                for a in range(2):
                    s16[a, c0:c1] = np.uint16(0)
                    c16[a, c0:c1] = np.uint16(0)
                    w16[a, c0:c1] = np.uint16(0)
                    q16[a, c0:c1] = _NINF
                    a16[a, c0:c1] = _NBIG
                    b16[a, c0:c1] = _NBIG
                _gray_row16(frames, y, c0, c1, wb, gray_tab, axis_tab, rg16, c16, w16, q16, a16, b16, rb16, s16)
                for a in range(2):
                    if axis_tab[a, 1] != 0:
                        _widen16(c16[a, c0:c1], w16[a, c0:c1], q16[a, c0:c1], a16[a, c0:c1], b16[a, c0:c1],
                                 axis_tab[a, 6] != 0, code[a, c0:c1], weak[a, c0:c1], qg[a, c0:c1], m1[a, c0:c1],
                                 m2[a, c0:c1], s16[a, c0:c1], soft[a, c0:c1])  # fmt: skip
            else:
                for a in range(2):
                    code[a, c0:c1] = np.uint32(0)
                    _gate_init(weak[a, c0:c1], qg[a, c0:c1], m1[a, c0:c1], m2[a, c0:c1], soft[a, c0:c1])
                _gray_row(frames, y, c0, c1, wb, gray_tab, mean_idx, axis_tab, scratch[8], d, cf, msum, code, weak,
                          qg, m1, m2, scratch[10], soft)  # fmt: skip
            _phase_row(frames, y, c0, c1, ph_tab, ph_idx, ph_sin, ph_cos, ssum, csum)
            _finish_row(
                lit, code, weak, qg, m1, m2, ssum, csum, quantum, axis_tab, ph_tab, ph_period, finest,
                u[y], vrow, mask[y], quality[y], levels[0, y], levels[1, y], scratch, fl, ok, c0, c1, xc, soft, bl,
                r, fringe[y],
            )  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Streaming: one small kernel per arriving frame, the same final step
# --------------------------------------------------------------------------------------------------


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stream_pair(pos, neg, bit, code, cst):  # type: ignore[no-untyped-def]
    """Fold a (pattern, inverse) pair of (H, W) images into the axis code and the bit's contrasts (H, W)."""
    h, w = pos.shape
    for y in prange(h):
        d = np.empty(w, np.int32)
        p = pos[y]
        n = neg[y]
        for x in range(w):
            d[x] = np.int32(p[x]) - np.int32(n[x])
        _add_bit(d, bit, code[y], cst[y])


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stream_single(img, sign, white, black, bit, code, cst):  # type: ignore[no-untyped-def]
    """Fold a Gray frame without inverse, thresholded at (white + black) / 2, into the axis state."""
    h, w = img.shape
    for y in prange(h):
        d = np.empty(w, np.int32)
        one = img[y]
        wr = white[y]
        br = black[y]
        for x in range(w):
            d[x] = np.int32(sign) * (2 * np.int32(one[x]) - np.int32(wr[x]) - np.int32(br[x]))
        _add_bit(d, bit, code[y], cst[y])


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stream_single_mean(img, sign, msum, n, bit, code, cst):  # type: ignore[no-untyped-def]
    """Fold a Gray frame without inverse, thresholded at the mean of ``n`` phase frames (sum ``msum``)."""
    h, w = img.shape
    for y in prange(h):
        d = np.empty(w, np.int32)
        _mean_diff(img[y], msum[y], np.int32(n), np.int32(sign), d)
        _add_bit(d, bit, code[y], cst[y])


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stream_sum(img, msum):  # type: ignore[no-untyped-def]
    """Add an (H, W) frame into an int32 per-pixel sum."""
    h, w = img.shape
    for y in prange(h):
        row = img[y]
        acc = msum[y]
        for x in range(w):
            acc[x] += np.int32(row[x])


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stream_phase(img, sk, ck, ssum, csum):  # type: ignore[no-untyped-def]
    """Add one phase step (H, W) into the set's sums, exactly: float64 sums with the quantised coefficients as
    floats, or int32 sums with them as integers in units of the quantum (the caller checked that no sum can
    leave int32; the product is formed in 64 bits)."""
    h, w = img.shape
    for y in prange(h):
        row = img[y]
        ss = ssum[y]
        cs = csum[y]
        for x in range(w):
            ss[x] += row[x] * sk
            cs[x] += row[x] * ck


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
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


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stream_finish(  # type: ignore[no-untyped-def]
    hi, lo, code, cst, gray_tab, ssum, csum, quantum, axis_tab, ph_tab, ph_period, rel, blend, thr, finest, nthreads,
    u, v, mask, quality, levels, fringe,
):  # fmt: skip
    """Final step of streaming: state arrays (H, W) / (2, H, W) / (G, H, W) / (S, H, W) -> outputs.

    ``ssum``/``csum`` are float64 sums, or int32 sums in units of ``quantum`` (1.0 for float64), as in
    :func:`decode_stack`: each row is copied, unscaled, into a contiguous row of the same type for the shared
    final step."""
    h, w = hi.shape
    nch = min(h, 8 * nthreads)
    for ch in prange(nch):
        r = np.empty(w, np.int32)
        cf = np.empty(w, np.float32)
        weak = np.empty((2, w), np.uint32)
        m1 = np.empty((2, w), np.uint32)
        m2 = np.empty((2, w), np.uint32)
        qg = np.empty((2, w), np.float32)
        soft = np.empty((2, w), np.uint32)
        bl = np.empty(w, np.bool_)
        scratch = np.empty((12, w), np.float32)
        fl = np.empty(w, np.uint32)
        xc = np.empty(w, np.uint32)
        ok = np.empty(w, np.bool_)
        lit = np.empty(w, np.bool_)
        vnone = np.empty(w, np.float32)
        ssr = np.empty((ssum.shape[0], w), ssum.dtype)
        csr = np.empty((ssum.shape[0], w), ssum.dtype)
        b = _round_robin(ch, nch, nthreads)
        for y in range(b * h // nch, (b + 1) * h // nch):
            hr = hi[y]
            lr = lo[y]
            for x in range(w):
                r[x] = np.int32(hr[x]) - np.int32(lr[x])
            _lit_row(r, rel, thr, scratch[0], scratch[8], lit, blend, scratch[10])
            c0, c1 = true_span(lit)  # as in decode_stack: the same outputs
            vrow = v[y] if v.shape[0] == h else vnone
            _unlit_outside(u[y], vrow, mask[y], quality[y], levels[0, y], levels[1, y], c0, c1)
            if c1 <= c0:
                continue
            for s in range(ssum.shape[0]):
                for x in range(c0, c1):
                    ssr[s, x] = ssum[s, y, x]
                    csr[s, x] = csum[s, y, x]
            _gate_init(weak, qg, m1, m2, soft)
            for g in range(gray_tab.shape[0]):
                a = gray_tab[g, 0]
                _fold_cst(cst[g, y, c0:c1], gray_tab[g, 1], scratch[8, c0:c1], axis_tab[a, 6] != 0, cf[c0:c1],
                          weak[a, c0:c1], qg[a, c0:c1], m1[a, c0:c1], m2[a, c0:c1], scratch[10, c0:c1], soft[a, c0:c1],
                          _faint_bit(axis_tab, a, gray_tab[g, 1]))  # fmt: skip
            _finish_row(
                lit, code[:, y, :], weak, qg, m1, m2, ssr, csr, quantum, axis_tab, ph_tab, ph_period,
                finest, u[y], vrow, mask[y], quality[y], levels[0, y], levels[1, y], scratch, fl, ok, c0, c1, xc, soft,
                bl, r, fringe[y],
            )  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Saturation and the reason a pixel has no code
# --------------------------------------------------------------------------------------------------

#: Flags of the per-pixel clipped map: a phase sample of axis x / y at full scale.
CLIP_PHASE_X = np.uint8(1)
CLIP_PHASE_Y = np.uint8(2)
#: Both frames of a Gray pair of axis x / y at full scale (the bit is unknown).
CLIP_PAIR_X = np.uint8(4)
CLIP_PAIR_Y = np.uint8(8)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def mark_clipped(img, full, flag, clip):  # type: ignore[no-untyped-def]
    """``clip |= flag`` where ``img >= full`` (img (H, W) uint8/uint16; clip (H, W) uint8)."""
    h, w = img.shape
    for y in prange(h):
        for x in range(w):
            if img[y, x] >= full:
                clip[y, x] |= flag


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def mark_clipped_pair(pos, neg, full, flag, clip):  # type: ignore[no-untyped-def]
    """``clip |= flag`` where both frames of a Gray pair are at full scale."""
    h, w = pos.shape
    for y in prange(h):
        for x in range(w):
            if pos[y, x] >= full and neg[y, x] >= full:
                clip[y, x] |= flag


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _undecode(u, v, has_v, mask, quality, lev, y, x):  # type: ignore[no-untyped-def]
    """Pixel (y, x) loses its code: NaN coordinates, mask False, quality 0, levels 0."""
    mask[y, x] = False
    u[y, x] = np.float32(np.nan)
    if has_v:
        v[y, x] = np.float32(np.nan)
    quality[y, x] = np.float32(0.0)
    lev[0, y, x] = np.uint8(0)
    lev[1, y, x] = np.uint8(0)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def drop_clipped(clip, drop, u, v, has_v, mask, quality, lev):  # type: ignore[no-untyped-def]
    """Unmask every pixel with a flag of ``drop`` in ``clip``: NaN coordinates, quality 0, levels 0."""
    h, w = clip.shape
    for y in prange(h):
        for x in range(w):
            if clip[y, x] & drop:
                _undecode(u, v, has_v, mask, quality, lev, y, x)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def decode_reasons(hi, lo, thr, dark, clip, mask, reason, fringe, r_ok, r_shadow, r_dark, r_sat, r_weak, r_blend):  # type: ignore[no-untyped-def]
    """Per pixel why it has no code (``r_ok`` where decoded): clipped samples, no lit range above ``dark``
    (shadow), a lit range below the threshold ``thr`` (too dark), two copies of the pattern (``reason`` = 1 on
    entry: :func:`blend_regions`), else a code too weak or inconsistent. ``fringe`` (H, W) uint8 is set to 0
    on every undecoded pixel (the decode step wrote it on the lit ones)."""
    h, w = mask.shape
    for y in prange(h):
        for x in range(w):
            blend = reason[y, x] == 1
            if mask[y, x]:
                reason[y, x] = r_ok
                continue
            fringe[y, x] = np.uint8(0)
            if clip[y, x] != 0:
                reason[y, x] = r_sat
            else:
                r = float(hi[y, x]) - float(lo[y, x])
                if r < dark:
                    reason[y, x] = r_shadow
                elif r < thr:
                    reason[y, x] = r_dark
                elif blend:
                    reason[y, x] = r_blend
                else:
                    reason[y, x] = r_weak


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _lit_range(hi, lo, fused, y, x):  # type: ignore[no-untyped-def]
    """A pixel's lit range: ``hi - lo``, or with ``fused`` the level ``hi`` alone."""
    return float(hi[y, x]) - (0.0 if fused else float(lo[y, x]))


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _unlit_column(reason, choice, top, fused, y0, y1, x, r_shadow, r_dark):  # type: ignore[no-untyped-def]
    """Whether column ``x`` of rows ``y0 .. y1 - 1`` holds a pixel of reason ``r_shadow`` or ``r_dark`` (with
    ``fused``: whose verdict came from pass ``top``, the brightest)."""
    found = False
    for yy in range(y0, y1):
        q = reason[yy, x]
        found |= (q == r_shadow) | (q == r_dark)
    if found and fused:  # rare: only beside an unlit pixel, and only in the maps of several passes
        found = False
        for yy in range(y0, y1):
            q = reason[yy, x]
            found |= ((q == r_shadow) | (q == r_dark)) & (choice[yy, x] == top)
    return found


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def drop_partial(  # type: ignore[no-untyped-def]
    hi, lo, choice, top, fused, ratio, u, v, has_v, mask, quality, lev, fringe, reason, r_ok, r_shadow, r_dark, r_edge
):  # fmt: skip
    """Undecode the pixels lit over a small part of their footprint (see :data:`COVER_RATIO`): a decoded pixel
    (``reason == r_ok``) whose ``hi - lo`` is below ``ratio`` times the largest of its decoded 8-neighbours',
    with an 8-neighbour of reason ``r_shadow`` or ``r_dark``. Two passes (mark with 255, then clear), so every
    pixel is judged by the decode it had. ``fused``: the maps of several exposure passes, the level ``hi`` alone
    (``lo`` unread), and a neighbour counts as unlit only where its result came from the brightest pass
    (``choice == top``): one from a darker pass (the brighter clipped it) says nothing of its light. Returns
    the number undecoded (reason ``r_edge``)."""
    h, w = mask.shape
    mark = np.uint8(255)
    per_row = np.zeros(h, np.int64)
    for y in prange(h):
        y0, y1 = max(y - 1, 0), min(y + 2, h)
        # whether columns x - 1, x, x + 1 of rows y0..y1 hold an unlit pixel, rolled along the row: three reads a
        # pixel, and the level comparison only beside an unlit one (most decoded pixels have none)
        prev = False
        cur = _unlit_column(reason, choice, top, fused, y0, y1, 0, r_shadow, r_dark)
        for x in range(w):
            nxt = _unlit_column(reason, choice, top, fused, y0, y1, min(x + 1, w - 1), r_shadow, r_dark) & (x + 1 < w)
            if (prev | cur | nxt) & (reason[y, x] == r_ok):
                best = 0.0
                for yy in range(y0, y1):
                    for xx in range(max(x - 1, 0), min(x + 2, w)):
                        q = reason[yy, xx]
                        if q == r_ok or q == mark:
                            best = max(best, _lit_range(hi, lo, fused, yy, xx))
                if _lit_range(hi, lo, fused, y, x) < ratio * best:
                    reason[y, x] = mark
                    per_row[y] += 1
            prev, cur = cur, nxt
    for y in prange(h):
        if per_row[y] == 0:
            continue
        for x in range(w):
            if reason[y, x] == mark:
                reason[y, x] = r_edge
                fringe[y, x] = np.uint8(0)
                _undecode(u, v, has_v, mask, quality, lev, y, x)
    return per_row.sum()


@njit(nogil=True, cache=True, error_model="numpy")
def _row_flagged(lev_row):  # type: ignore[no-untyped-def]
    """Whether any pixel of a ``levels[0]`` row carries :data:`BLEND_FLAG` (a branch-free OR over the row)."""
    acc = np.uint8(0)
    for x in range(lev_row.shape[0]):
        acc |= lev_row[x]
    return (acc & np.uint8(BLEND_FLAG)) != np.uint8(0)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def blend_regions(lev, region, flagged, per_row):  # type: ignore[no-untyped-def]
    """The blend check's regions: ``region`` = 1 on a pixel marked (:data:`BLEND_FLAG` in ``lev[0]``) with at
    least :data:`BLEND_NEIGHBOURS` marked neighbours, 0 elsewhere; ``per_row`` (H,) int64 their count per row.
    The marks stay (:func:`blend_undecode` clears them). ``region`` (H, W) uint8; ``flagged`` (H,) bool scratch.
    Rows without a mark nearby cost one read."""
    h, w = region.shape
    flag = np.uint8(BLEND_FLAG)
    for y in prange(h):
        flagged[y] = _row_flagged(lev[0, y])
    for y in prange(h):
        reg = region[y]
        reg[:] = np.uint8(0)
        per_row[y] = 0
        if not flagged[y]:
            continue
        y0, y1 = max(y - 1, 0), min(y + 2, h)
        for x in range(w):
            if lev[0, y, x] & flag:
                n = -1  # the pixel itself
                for yy in range(y0, y1):
                    if flagged[yy]:
                        for xx in range(max(x - 1, 0), min(x + 2, w)):
                            n += 1 if (lev[0, yy, xx] & flag) != 0 else 0
                if n >= BLEND_NEIGHBOURS:
                    reg[x] = np.uint8(1)
                    per_row[y] += 1


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def blend_undecode(lev, u, v, has_v, mask, quality, region, flagged, starts, codes):  # type: ignore[no-untyped-def]
    """Every pixel of a :func:`blend_regions` region loses its code (NaN, mask False, quality 0, levels 0) after
    its row, column and code go to ``codes`` (N, 4) float32 from ``starts[y]`` on in row y (v NaN when not
    coded): the stronger copy's code, which the reconstruction uses only as evidence of a surface in front of
    another point (never as a point). The blend marks are cleared."""
    h, w = region.shape
    keep = np.uint8(0xFF ^ BLEND_FLAG)
    for y in prange(h):
        if not flagged[y]:
            continue
        reg = region[y]
        i = starts[y]
        for x in range(w):
            lev[0, y, x] &= keep
            if reg[x]:
                codes[i, 0] = np.float32(y)
                codes[i, 1] = np.float32(x)
                codes[i, 2] = u[y, x]
                codes[i, 3] = v[y, x] if has_v else np.float32(np.nan)
                i += 1
                _undecode(u, v, has_v, mask, quality, lev, y, x)


@njit(nogil=True, cache=True, parallel=True, error_model="numpy")
def stack_range(frames, used, hi, lo):  # type: ignore[no-untyped-def]
    """Per pixel max / min over the frames ``used`` of a stack (F, H, W) into hi / lo (H, W)."""
    _, h, w = frames.shape
    for y in prange(h):
        for x in range(w):
            a = frames[used[0], y, x]
            b = a
            for k in range(1, used.shape[0]):
                val = frames[used[k], y, x]
                if val > a:
                    a = val
                if val < b:
                    b = val
            hi[y, x] = a
            lo[y, x] = b
