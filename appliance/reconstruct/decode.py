"""Structured-light decoding: a frame stack (or frames as they arrive) -> projector coordinates.

The decoder looks every frame up by what it is (never by position): a :class:`DecodePlan` built from
the :class:`~appliance.patterns.sequence.Sequence` says which frames code which axis, how each phase
set is unwrapped, and which frames are not used.

Per camera pixel:

* **Shadow.** The contrast range ``r = white - black`` (or, without white/black frames, the largest
  minus the smallest value over the coded frames) must reach a scene-adaptive threshold:
  ``max(min_contrast_dn, shadow_fraction * Otsu(r))``, Otsu's split of the histogram of ``r`` over the
  image between shadow and lit pixels.
* **Gray code.** Each bit is ``pattern > inverse`` (or ``pattern > (white + black) / 2`` without an
  inverse), with contrast ``|pattern - inverse|`` that must reach ``relative_contrast * r``. One weak bit
  per axis is tolerated: a pixel on a stripe edge has exactly one ambiguous bit, and either value is a
  neighbouring stripe (harmless for phase unwrapping with stripe <= period / 2; ± one stripe for
  Gray-only decoding). Gray-only decoding returns stripe centres, ``(k + 0.5) * stripe - 0.5``.
* **Phase.** ``S = Σ I_n sin θ_n``, ``C = Σ I_n cos θ_n`` with ``θ_n = offset + 2π n / N``; the wrapped
  coordinate is ``period * atan2(-S, C) / 2π`` in ``[0, period)``; the peak-to-peak modulation
  ``4 / N * sqrt(S² + C²)`` must reach ``relative_contrast * r``. Each set is unwrapped against a coarse
  estimate ``c0``: ``c = c_phase + period * round((c0 - c_phase) / period)``, where ``c0`` is the Gray
  stripe centre (coarsest set), the next coarser unwrapped set (finer sets), or the axis centre (a
  period covering the whole axis). The finest set gives the result.
* **Quality** is the weakest contrast the decode relied on (DN of the input data): Gray bit contrasts
  (without the tolerated edge bit) and phase modulations; 0 where masked.
"""

from __future__ import annotations

import functools
import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from appliance.errors import DecodeError, PatternError
from appliance.patterns.sequence import (
    Axis,
    BlackFrame,
    GrayFrame,
    OtherFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
    gray_bits_needed,
)
from appliance.reconstruct import _decode_kernels as _k
from appliance.reconstruct._pool import BufferPool
from appliance.reconstruct.types import DecodedMaps, Reason

FrameStack = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]

#: A coarser phase set unwraps a finer one only up to this period ratio (its phase error, scaled by the
#: ratio, must stay well inside half the finer period).
MAX_PERIOD_RATIO = 16.0
#: Phase coefficients are quantised to this step so that sums of products are exact in float64 (in any order:
#: streaming equals batch), and, for 8-bit frames and up to 128 steps a set, in int32 (the streaming decoder's
#: sums then take half the memory). A coefficient moves by at most 2**-17 (a phase error below 1e-5 rad).
COEFFICIENT_QUANTUM = 2.0**-16
_AXES: tuple[Axis, Axis] = ("x", "y")
#: Output blocks of decode() / StreamingDecoder.finish() without ``out`` (a few cameras' maps at once).
_POOL = BufferPool(max_blocks=4)


@dataclass(frozen=True)
class DecodeParams:
    """Thresholds of the decoder.

    Attributes
    ----------
    min_contrast_dn : float
        Floor of ``white - black`` for a lit pixel, in 8-bit digital numbers (scaled by
        ``max_value / 255`` for other data).
    relative_contrast : float
        Every Gray contrast ``|pattern - inverse|`` and phase modulation (peak to peak) must reach this
        fraction of the pixel's own ``white - black``.
    shadow_fraction : float
        The lit threshold is at least this fraction of the Otsu threshold of the image's
        ``white - black`` histogram (adapts to ambient light and noise).
    max_value : float or None
        Full scale of the data (DN): ``2**bits - 1`` of the camera's significant bits (4095 for Mono12 data
        in uint16). None: 255 for uint8, 65535 for uint16. Every DN threshold scales with it.
    finest_bit : bool
        Decode each pixel to the finest Gray bit that has contrast: where the finest stripes are below what
        the optics resolve (several weak bits from bit 0 up), those bits are dropped and the pixel gets the
        centre of the coarser stripe (``DecodedMaps.levels`` says how many bits). False: such pixels are
        rejected. Likewise a finer phase period without modulation leaves the pixel on the coarser period's
        (unwrapped, sub-pixel) coordinate.
    """

    min_contrast_dn: float = 6.0
    relative_contrast: float = 0.15
    shadow_fraction: float = 0.2
    max_value: float | None = None
    finest_bit: bool = True

    @staticmethod
    def for_bits(bits: int, **kwargs: Any) -> DecodeParams:
        """Parameters for data with ``bits`` significant bits (8..16), e.g. ``for_bits(12)`` for Mono12."""
        if not 1 <= int(bits) <= 16:
            raise DecodeError(f"decode params: bits = {bits}: must be 1..16 (significant bits of the data)")
        return DecodeParams(max_value=float((1 << int(bits)) - 1), **kwargs)

    def __post_init__(self) -> None:
        if not (self.min_contrast_dn >= 0.0 and math.isfinite(self.min_contrast_dn)):
            raise DecodeError(f"decode params: min_contrast_dn = {self.min_contrast_dn}: must be >= 0")
        if not 0.0 <= self.relative_contrast < 1.0:
            raise DecodeError(
                f"decode params: relative_contrast = {self.relative_contrast}: must be in [0, 1)"
            )
        if not 0.0 <= self.shadow_fraction <= 1.0:
            raise DecodeError(f"decode params: shadow_fraction = {self.shadow_fraction}: must be in [0, 1]")
        if self.max_value is not None and not self.max_value > 0:
            raise DecodeError(f"decode params: max_value = {self.max_value}: must be > 0 DN")


@dataclass(frozen=True)
class GrayAxisPlan:
    """The Gray code of one axis: ``frames[bit] = (pattern index, inverse index)``, -1 where absent."""

    axis: Axis
    stripe: int
    bits: int
    frames: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class PhaseSetPlan:
    """One phase set: frame indices in step order and its unwrapping source.

    ``source`` is ``'gray'`` (the Gray code), ``'axis'`` (the period covers the axis) or ``'period P'``.
    """

    axis: Axis
    period: float
    steps: int
    offset: float
    frames: tuple[int, ...]
    source: str


@dataclass(frozen=True)
class DecodePlan:
    """How a :class:`Sequence` is decoded (build it with :func:`plan_decode`).

    Attributes
    ----------
    sequence : Sequence
        The frames.
    axes : tuple of {'x', 'y'}
        The coded axes.
    white, black : int
        Frame indices of the white and black frames (-1: not used).
    gray : tuple of GrayAxisPlan
        One per Gray-coded axis.
    phase : tuple of PhaseSetPlan
        Phase sets, coarse to fine within each axis.
    ignored : list of str
        Frames not used, with the reason.
    mean_frames : tuple of int
        Without white and black frames: the phase set whose per-pixel mean thresholds the Gray frames that
        have no inverse (empty when not needed).
    """

    sequence: Sequence
    axes: tuple[Axis, ...]
    white: int
    black: int
    gray: tuple[GrayAxisPlan, ...]
    phase: tuple[PhaseSetPlan, ...]
    ignored: list[str] = field(default_factory=list)
    mean_frames: tuple[int, ...] = ()
    tables: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def used(self) -> tuple[int, ...]:
        """Indices of every frame the decoder reads, ascending."""
        return tuple(int(i) for i in self.tables["used"])


# --------------------------------------------------------------------------------------------------
# Planning
# --------------------------------------------------------------------------------------------------


def _ranges(values: Iterable[int]) -> str:
    vals = sorted(set(values))
    if not vals:
        return "none"
    out: list[str] = []
    start = prev = vals[0]
    for v in [*vals[1:], None]:
        if v is not None and v == prev + 1:
            prev = v
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if v is not None:
            start = prev = v
    return ", ".join(out)


def _describe(frame: Any) -> str:
    if isinstance(frame, GrayFrame):
        return f"gray {frame.axis} bit {frame.bit}{' inverted' if frame.inverted else ''}"
    if isinstance(frame, PhaseFrame):
        return f"phase {frame.axis} period {frame.period:g} step {frame.step}/{frame.steps}"
    return str(frame.pattern)


def plan_decode(sequence: Sequence) -> DecodePlan:
    """Work out how to decode ``sequence``, or refuse it saying what is missing.

    Parameters
    ----------
    sequence : Sequence
        The captured frames, in any order.

    Returns
    -------
    DecodePlan

    Raises
    ------
    PatternError
        When a coordinate cannot be determined: a missing Gray bit, a missing phase step, a phase set
        with nothing to unwrap it, mixed stripes, ... (every problem is listed, separated by ``;``).
    """
    ignored: list[str] = []
    problems: list[str] = []
    whites: list[int] = []
    blacks: list[int] = []
    gray: dict[Axis, dict[tuple[int, bool], int]] = {"x": {}, "y": {}}
    stripes: dict[Axis, set[int]] = {"x": set(), "y": set()}
    phases: dict[tuple[Axis, float], dict[int, int]] = defaultdict(dict)
    phase_kind: dict[tuple[Axis, float], set[tuple[int, float]]] = defaultdict(set)
    seen: dict[Any, int] = {}

    for i, f in enumerate(sequence.frames):
        if isinstance(f, OtherFrame):
            ignored.append(f"frame {i}: pattern {f.pattern!r} is not decodable; unused")
            continue
        key = f
        if key in seen:
            ignored.append(f"frame {i}: duplicate of frame {seen[key]} ({_describe(f)}); unused")
            continue
        seen[key] = i
        if isinstance(f, WhiteFrame):
            whites.append(i)
        elif isinstance(f, BlackFrame):
            blacks.append(i)
        elif isinstance(f, GrayFrame):
            gray[f.axis][(f.bit, f.inverted)] = i
            stripes[f.axis].add(f.stripe)
        elif isinstance(f, PhaseFrame):
            pk = (f.axis, f.period)
            if f.step in phases[pk]:
                ignored.append(
                    f"frame {i}: duplicate step of frame {phases[pk][f.step]} ({_describe(f)}); unused"
                )
                continue
            phases[pk][f.step] = i
            phase_kind[pk].add((f.steps, f.offset))

    white = black = -1
    if whites and blacks:
        white, black = whites[0], blacks[0]
    elif whites:
        ignored.append(f"frame {whites[0]}: white without a black frame; unused")
    elif blacks:
        ignored.append(f"frame {blacks[0]}: black without a white frame; unused")
    has_wb = white >= 0
    # without white/black, a Gray frame without inverse is thresholded at the mean of a complete phase set
    # (a sinusoid's mean is half way between its lit and dark levels): the most steps, then the finest
    complete = [
        pk for pk, kinds in phase_kind.items()
        if len(kinds) == 1 and all(s in phases[pk] for s in range(next(iter(kinds))[0]))
    ]  # fmt: skip
    mean_key = min(complete, key=lambda pk: (-next(iter(phase_kind[pk]))[0], pk[1], pk[0]), default=None)
    needs_mean = False

    gray_plans: dict[Axis, GrayAxisPlan] = {}
    for axis in _AXES:
        if not gray[axis]:
            continue
        if len(stripes[axis]) > 1:
            problems.append(
                f"gray code axis {axis}: frames use stripes {sorted(stripes[axis])} px; "
                "use one Gray code (one stripe) per axis"
            )
            continue
        stripe = next(iter(stripes[axis]))
        present = {b for b, _ in gray[axis]}
        needed = max(gray_bits_needed(sequence.axis_size(axis), stripe), max(present) + 1)
        missing = [b for b in range(needed) if b not in present]
        if missing:
            what = f"bit {missing[0]} is" if len(missing) == 1 else f"bits {_ranges(missing)} are"
            problems.append(
                f"gray code axis {axis}: {what} missing (bits present: {_ranges(present)}; "
                f"{needed} bits code {sequence.axis_size(axis)} px in stripes of {stripe} px); "
                "add the missing frames or fix the manifest"
            )
            continue
        frames_of_bit: list[tuple[int, int]] = []
        for b in range(needed):
            pos = gray[axis].get((b, False), -1)
            neg = gray[axis].get((b, True), -1)
            if (pos < 0 or neg < 0) and not has_wb:
                if mean_key is None:
                    problems.append(
                        f"gray code axis {axis}: bit {b} has no inverse frame and the sequence has no white "
                        "and black frames or complete phase set to threshold it against; add inverses, white "
                        "and black frames, or the phase frames"
                    )
                needs_mean = True
            frames_of_bit.append((pos, neg))
        gray_plans[axis] = GrayAxisPlan(axis, stripe, needed, tuple(frames_of_bit))

    phase_plans: list[PhaseSetPlan] = []
    for axis in _AXES:
        keys = sorted((k for k in phases if k[0] == axis), key=lambda k: -k[1])
        size = sequence.axis_size(axis)
        previous: float | None = None
        for pk in keys:
            period = pk[1]
            name = f"phase {axis} period {period:g}"
            kinds = phase_kind[pk]
            if len(kinds) > 1:
                problems.append(
                    f"{name}: frames disagree on steps/offset {sorted(kinds)}; use one set per period"
                )
                continue
            steps, offset = next(iter(kinds))
            missing = [s for s in range(steps) if s not in phases[pk]]
            if missing:
                problems.append(
                    f"{name}: step(s) {_ranges(missing)} of {steps} missing (steps present: "
                    f"{_ranges(phases[pk])}); add the frames or fix the manifest"
                )
                continue
            g = gray_plans.get(axis)
            source: str | None = None
            why = ""
            if previous is not None and previous / period <= MAX_PERIOD_RATIO:
                source = f"period {previous:g}"
            elif g is not None and g.stripe <= period:
                source = "gray"
            elif previous is None and period >= size:
                source = "axis"
            elif previous is not None:
                why = (
                    f"the next coarser period {previous:g} is {previous / period:.3g} times longer "
                    f"(at most {MAX_PERIOD_RATIO:g})"
                    + (f" and the Gray stripe {g.stripe} px is wider than the period" if g else "")
                    + "; add an intermediate period or a Gray code with stripe <= the period"
                )
            elif g is not None:
                why = (
                    f"the Gray code stripe ({g.stripe} px) is wider than the period; use a stripe of the "
                    "period or half of it, or add a coarser period"
                )
            elif gray[axis] or stripes[axis]:
                why = f"the Gray code of axis {axis} is unusable (see above)"
            else:
                why = (
                    f"axis {axis} has no Gray code and no coarser phase period; add a Gray code with stripe "
                    f"{int(period)} or {int(period) // 2} px, or a period >= {size} px"
                )
            if source is None:
                problems.append(f"{name}: cannot be unwrapped: {why}")
                continue
            frames_idx = tuple(phases[pk][s] for s in range(steps))
            phase_plans.append(PhaseSetPlan(axis, period, steps, offset, frames_idx, source))
            previous = period

    if problems:
        raise PatternError("; ".join(problems))
    axes = tuple(a for a in _AXES if a in gray_plans or any(p.axis == a for p in phase_plans))
    if not axes:
        raise PatternError(
            f"sequence ({sequence.describe()}): no Gray code or phase frames: nothing to decode"
        )
    mean_frames: tuple[int, ...] = ()
    if needs_mean and mean_key is not None:
        steps = next(iter(phase_kind[mean_key]))[0]
        mean_frames = tuple(phases[mean_key][s] for s in range(steps))
    plan = DecodePlan(sequence, axes, white, black, tuple(gray_plans.values()), tuple(phase_plans), ignored,
                      mean_frames)  # fmt: skip
    plan.tables.update(_tables(plan))
    return plan


def _gray_stripe(plan: DecodePlan, axis: Axis) -> int:
    return next(g.stripe for g in plan.gray if g.axis == axis)


def _tables(plan: DecodePlan) -> dict[str, Any]:
    seq = plan.sequence
    gray_rows: list[tuple[int, int, int, int]] = []
    axis_tab = np.zeros((2, 8), np.int64)
    for a, axis in enumerate(_AXES):
        axis_tab[a, 5] = seq.axis_size(axis)
        axis_tab[a, 2] = 1
        axis_tab[a, 3] = 1
        axis_tab[a, 0] = int(axis in plan.axes)
    for g in plan.gray:
        a = _AXES.index(g.axis)
        axis_tab[a, 1:5] = (1, g.stripe, -(-seq.axis_size(g.axis) // g.stripe), int(g.bits >= 2))
        axis_tab[a, 7] = g.bits
        gray_rows.extend((a, b, pos, neg) for b, (pos, neg) in enumerate(g.frames))
    ph_tab = np.zeros((len(plan.phase), 4), np.int64)
    ph_idx: list[int] = []
    ph_sin: list[float] = []
    ph_cos: list[float] = []
    for s, p in enumerate(plan.phase):
        src = 1 if p.source.startswith("period") else (-1 if p.source == "gray" else -2)
        if src == -1 and 2 * _gray_stripe(plan, p.axis) > p.period:
            src = -3  # stripe > period / 2: no margin at stripe edges; find the edge from the weak bit
        ph_tab[s] = (_AXES.index(p.axis), p.steps, src, len(ph_idx))
        if src == -3:
            axis_tab[_AXES.index(p.axis), 6] = 1
        for n, idx in enumerate(p.frames):
            theta = p.offset + 2.0 * math.pi * n / p.steps
            ph_idx.append(idx)
            ph_sin.append(round(math.sin(theta) / COEFFICIENT_QUANTUM) * COEFFICIENT_QUANTUM)
            ph_cos.append(round(math.cos(theta) / COEFFICIENT_QUANTUM) * COEFFICIENT_QUANTUM)
    used = sorted({i for row in gray_rows for i in row[2:] if i >= 0} | set(ph_idx) | set(plan.mean_frames))
    sin_q = np.rint(np.array(ph_sin, np.float64) / COEFFICIENT_QUANTUM).astype(np.int32)
    cos_q = np.rint(np.array(ph_cos, np.float64) / COEFFICIENT_QUANTUM).astype(np.int32)
    sets = [(int(first), int(first + steps)) for _, steps, _, first in ph_tab.tolist()]
    return {
        "wb": np.array([plan.white, plan.black], np.int64),
        "gray_tab": np.array(gray_rows, np.int64).reshape(-1, 4),
        "axis_tab": axis_tab,
        "ph_tab": ph_tab,
        "ph_period": np.array([p.period for p in plan.phase], np.float64),
        "ph_idx": np.array(ph_idx, np.int64),
        "ph_sin": np.array(ph_sin, np.float64),
        "ph_cos": np.array(ph_cos, np.float64),
        # the same coefficients in units of the quantum (exact integers), and the largest sum of their magnitudes
        # over one set: what a phase sum of frames up to 1 can reach, in quanta
        "ph_sin_q": sin_q,
        "ph_cos_q": cos_q,
        "ph_coef_bound": max((int(max(np.abs(sin_q[a:b]).sum(), np.abs(cos_q[a:b]).sum())) for a, b in sets),
                             default=0),
        "used": np.array(used, np.int64),
        "mean_idx": np.array(plan.mean_frames, np.int64),
    }


def _int_sums(tables: dict[str, Any], maxval: int) -> bool:
    """Whether the phase sums of frames up to ``maxval`` fit int32 in units of the coefficient quantum.

    The bound is the container's maximum (255 for 8-bit frames, 65535 for 16-bit, whatever the significant
    bits), so no frame can make a sum leave int32. Batch and streaming decodes take the same decision; either
    way the sums are exact, and the outputs identical.
    """
    return int(tables["ph_coef_bound"]) * maxval <= 2**31 - 1


# --------------------------------------------------------------------------------------------------
# Thresholds
# --------------------------------------------------------------------------------------------------


def _max_value(dtype: np.dtype[Any], params: DecodeParams) -> float:
    if params.max_value is not None:
        return float(params.max_value)
    return 255.0 if dtype == np.uint8 else 65535.0


def _bits(dtype: np.dtype[Any], params: DecodeParams) -> int:
    """Significant bits of the data: from ``max_value``, else the dtype's."""
    return max(1, math.ceil(math.log2(_max_value(dtype, params) + 1.0)))


def _hist_layout(dtype: np.dtype[Any], params: DecodeParams = DecodeParams()) -> tuple[int, int]:
    """(shift, bins) of the contrast-range histogram: one bin per DN up to 12 bits, 4096 bins above."""
    if dtype == np.uint8:
        return (0, 256)
    bits = min(_bits(dtype, params), 16)
    shift = max(bits - 12, 0)
    return (shift, 1 << (bits - shift))


def otsu_threshold(hist: npt.NDArray[np.int64]) -> int:
    """Otsu's threshold of a histogram: the first bin of the upper class (0 when degenerate)."""
    h = hist.astype(np.float64)
    total = h.sum()
    if total <= 0:
        return 0
    bins = np.arange(h.size, dtype=np.float64)
    w0 = np.cumsum(h)
    m0 = np.cumsum(h * bins)
    w1 = total - w0
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (m0 / w0 - (m0[-1] - m0) / w1) ** 2
    between[~np.isfinite(between)] = -1.0
    top = float(between.max())
    if top <= 0:
        return 0
    # two well separated classes give a plateau over the empty gap: take its middle
    plateau = np.flatnonzero(between >= top * (1.0 - 1e-9))
    return (int(plateau[0]) + int(plateau[-1])) // 2 + 1


def lit_threshold(hist: npt.NDArray[np.int64], dtype: np.dtype[Any], params: DecodeParams) -> float:
    """Scene-adaptive lit threshold on ``white - black`` (DN) from its histogram."""
    shift, _ = _hist_layout(dtype, params)
    floor = params.min_contrast_dn * _max_value(dtype, params) / 255.0
    return max(floor, params.shadow_fraction * float(otsu_threshold(hist) << shift))


# --------------------------------------------------------------------------------------------------
# Batch
# --------------------------------------------------------------------------------------------------


def _as_plan(sequence: Sequence | DecodePlan) -> DecodePlan:
    return sequence if isinstance(sequence, DecodePlan) else plan_decode(sequence)


def _check_out(out: DecodedMaps, shape: tuple[int, int]) -> None:
    for name, dtype in (("u", np.float32), ("v", np.float32), ("mask", np.bool_), ("quality", np.float32)):
        arr = getattr(out, name)
        if arr.shape != shape or arr.dtype != dtype or not arr.flags.c_contiguous:
            raise DecodeError(
                f"decode: out.{name} is {arr.shape} {arr.dtype}: must be a C-contiguous {shape} "
                f"{np.dtype(dtype).name} array"
            )


def empty_maps(shape: tuple[int, int]) -> DecodedMaps:
    """Uninitialised output maps of ``shape`` (H, W), for ``decode(..., out=)``."""
    return DecodedMaps(
        np.empty(shape, np.float32),
        np.empty(shape, np.float32),
        np.empty(shape, np.bool_),
        np.empty(shape, np.float32),
        levels=np.empty((2, *shape), np.uint8),
        reason=np.empty(shape, np.uint8),
    )


def _outputs(
    plan: DecodePlan, shape: tuple[int, int], out: DecodedMaps | None
) -> tuple[DecodedMaps, npt.NDArray[np.float32]]:
    """Output maps, and the v buffer the kernel writes (no rows: v is a read-only NaN map, not written)."""
    lev_shape = (2, *shape)
    if out is not None:
        _check_out(out, shape)
        lev = out.levels
        if lev is None or lev.shape != lev_shape or lev.dtype != np.uint8 or not lev.flags.c_contiguous:
            out.levels = np.empty(lev_shape, np.uint8)
        rsn = out.reason
        if rsn is None or rsn.shape != shape or rsn.dtype != np.uint8 or not rsn.flags.c_contiguous:
            out.reason = np.empty(shape, np.uint8)
        return out, out.v
    # outputs are views of blocks reused once the caller drops them (saves their first-touch page faults)
    if "y" in plan.axes:
        u, v, mask, quality, levels, reason = _POOL.arrays([(shape, np.float32), (shape, np.float32),
                                                            (shape, np.bool_), (shape, np.float32),
                                                            (lev_shape, np.uint8), (shape, np.uint8)])  # fmt: skip
        maps = DecodedMaps(u, v, mask, quality, levels=levels, reason=reason)  # type: ignore[arg-type]
        return maps, maps.v
    # the y axis is not coded: v is NaN everywhere, one shared read-only map instead of H x W stores per call
    u, mask, quality, levels, reason = _POOL.arrays([(shape, np.float32), (shape, np.bool_), (shape, np.float32),
                                                     (lev_shape, np.uint8), (shape, np.uint8)])  # fmt: skip
    maps = DecodedMaps(u, _nan_map(shape), mask, quality, levels=levels, reason=reason)  # type: ignore[arg-type]
    return maps, np.empty((0, shape[1]), np.float32)


@functools.lru_cache(maxsize=4)
def _nan_map(shape: tuple[int, int]) -> npt.NDArray[np.float32]:
    """A read-only all-NaN float32 map of ``shape`` (shared)."""
    nan = np.full(shape, np.nan, np.float32)
    nan.flags.writeable = False
    return nan


def _narrow(plan: DecodePlan, dtype: np.dtype[Any]) -> bool:
    """8-bit frames, at most 15 Gray bits per axis, no mean thresholding: Gray bits fold in 16-bit lanes."""
    return bool(dtype == np.uint8 and all(g.bits <= 15 for g in plan.gray) and not plan.mean_frames)


def _clip_plan(plan: DecodePlan) -> tuple[list[tuple[int, int]], list[tuple[int, int, int]]]:
    """The samples a code needs unclipped: (phase frame, flag) and (Gray positive, negative, flag) pairs."""
    t = plan.tables
    phase: list[tuple[int, int]] = []
    for s, (axis, steps, _src, first) in enumerate(t["ph_tab"].tolist()):
        del s
        flag = int(_k.CLIP_PHASE_X if axis == 0 else _k.CLIP_PHASE_Y)
        phase.extend((int(i), flag) for i in t["ph_idx"][first:first + steps].tolist())
    pairs = [
        (int(pos), int(neg), int(_k.CLIP_PAIR_X if a == 0 else _k.CLIP_PAIR_Y))
        for a, _bit, pos, neg in t["gray_tab"].tolist()
        if pos >= 0 and neg >= 0
    ]
    return phase, pairs


#: Clipped-map flags that drop a decoded pixel: a clipped phase sample biases its coordinate by up to a
#: large share of the period, so the point would be wrong while looking right. (A Gray pair clipped in both
#: frames already fails its contrast test.)
_DROP = int(_k.CLIP_PHASE_X | _k.CLIP_PHASE_Y)


def _saturation_and_reasons(
    out: DecodedMaps,
    v_arg: npt.NDArray[np.float32],
    clip: npt.NDArray[np.uint8],
    hi: npt.NDArray[Any],
    lo: npt.NDArray[Any],
    thr: float,
    dtype: np.dtype[Any],
    params: DecodeParams,
) -> None:
    """Drop the pixels whose needed samples are clipped, then write every pixel's :class:`Reason`."""
    assert out.levels is not None and out.reason is not None
    _k.drop_clipped(clip, _DROP, out.u, v_arg, v_arg.shape[0] > 0, out.mask, out.quality, out.levels)
    dark = params.min_contrast_dn * _max_value(dtype, params) / 255.0
    _k.decode_reasons(
        hi, lo, float(thr), float(dark), clip, out.mask, out.reason, int(Reason.DECODED), int(Reason.SHADOW),
        int(Reason.TOO_DARK), int(Reason.SATURATED), int(Reason.WEAK_CODE),
    )  # fmt: skip


def reason_counts(maps: DecodedMaps) -> dict[str, int]:
    """Pixels per :class:`Reason` of a decode (``{"decoded": n, "shadow": n, ...}``, zero counts left out).

    Parameters
    ----------
    maps : DecodedMaps
        A decode with ``reason``.

    Returns
    -------
    dict of str to int
        Pixel counts keyed by the reason's plain name; empty when ``maps.reason`` is None.
    """
    from appliance.reconstruct.types import REASON_NAMES

    if maps.reason is None:
        return {}
    counts = np.bincount(maps.reason.ravel(), minlength=len(REASON_NAMES))
    return {REASON_NAMES[i]: int(c) for i, c in enumerate(counts.tolist()) if c and i in REASON_NAMES}


def reason_block(maps: DecodedMaps) -> dict[str, dict[str, Any]]:
    """The sidecar's per-camera reason block: pixels and share of the image per :class:`Reason`.

    Parameters
    ----------
    maps : DecodedMaps
        A decode with ``reason``.

    Returns
    -------
    dict
        ``{"reasons": {name: pixels}, "reason_shares": {name: share of the image's pixels, 0..1}}`` (zero
        counts left out); empty when ``maps.reason`` is None.
    """
    counts = reason_counts(maps)
    if not counts:
        return {}
    total = max(int(maps.mask.size), 1)
    return {"reasons": counts, "reason_shares": {k: round(n / total, 6) for k, n in counts.items()}}


def decode(
    frames: FrameStack,
    sequence: Sequence | DecodePlan,
    params: DecodeParams = DecodeParams(),
    *,
    out: DecodedMaps | None = None,
) -> DecodedMaps:
    """Decode a captured frame stack into projector coordinates.

    Parameters
    ----------
    frames : ndarray, shape (F, H, W), uint8 or uint16
        One camera's frames in the order of ``sequence``.
    sequence : Sequence or DecodePlan
        What each frame shows (a plan from :func:`plan_decode` skips re-planning).
    params : DecodeParams
        Thresholds.
    out : DecodedMaps, optional
        Preallocated C-contiguous (H, W) outputs (see :func:`empty_maps`); filled and returned.

    Returns
    -------
    DecodedMaps
        ``u``, ``v`` (projector px, float32, NaN where undecoded or not coded), ``mask``, ``quality`` (DN).
        Without ``out``, ``v`` of a sequence that codes no rows is a shared read-only all-NaN map.

    Raises
    ------
    PatternError
        The sequence cannot be decoded (see :func:`plan_decode`).
    DecodeError
        ``frames`` has the wrong shape or dtype.
    """
    plan = _as_plan(sequence)
    frames_arr = np.asarray(frames)
    n = len(plan.sequence)
    if frames_arr.ndim != 3 or frames_arr.shape[0] != n:
        raise DecodeError(
            f"decode: frames have shape {frames_arr.shape}: must be ({n}, height, width), one image per "
            "frame of the sequence"
        )
    if frames_arr.dtype not in (np.uint8, np.uint16):
        raise DecodeError(f"decode: frames have dtype {frames_arr.dtype}: must be uint8 or uint16")
    stack = np.ascontiguousarray(frames_arr)
    shape = (int(stack.shape[1]), int(stack.shape[2]))
    out, v_arg = _outputs(plan, shape, out)
    t = plan.tables
    shift, nbins = _hist_layout(stack.dtype, params)
    maxval = 255 if stack.dtype == np.uint8 else 65535
    if plan.white >= 0:
        hist = _k.range_hist(stack[plan.white], stack[plan.black], shift, nbins)
    else:
        hist = _k.range_hist_stack(stack, t["wb"], t["used"], maxval, shift, nbins)
    thr = lit_threshold(hist, stack.dtype, params)
    assert out.levels is not None
    # exact phase sums: int32 in units of the quantum where they fit (8-bit frames), else float64
    ints = _int_sums(t, maxval)
    sin, cos = (t["ph_sin_q"], t["ph_cos_q"]) if ints else (t["ph_sin"], t["ph_cos"])
    _k.decode_stack(
        stack, t["wb"], t["used"], maxval, t["gray_tab"], t["mean_idx"], t["axis_tab"], t["ph_tab"],
        t["ph_period"], t["ph_idx"], sin, cos, COEFFICIENT_QUANTUM if ints else 1.0,
        float(params.relative_contrast), float(thr),
        bool(params.finest_bit), numba.get_num_threads(), _narrow(plan, stack.dtype), out.u, v_arg, out.mask,
        out.quality, out.levels,
    )  # fmt: skip
    full = int(_max_value(stack.dtype, params))
    clip = np.zeros(shape, np.uint8)
    phase, pairs = _clip_plan(plan)
    for idx, flag in phase:
        _k.mark_clipped(stack[idx], full, flag, clip)
    for pos, neg, flag in pairs:
        _k.mark_clipped_pair(stack[pos], stack[neg], full, flag, clip)
    if plan.white >= 0:
        hi, lo = stack[plan.white], stack[plan.black]
    else:
        hi, lo = np.empty(shape, stack.dtype), np.empty(shape, stack.dtype)
        _k.stack_range(stack, t["used"], hi, lo)
    _saturation_and_reasons(out, v_arg, clip, hi, lo, thr, stack.dtype, params)
    out.ignored = list(plan.ignored)
    return out


def stripe_widths(maps: DecodedMaps, sequence: Sequence | DecodePlan) -> dict[str, dict[float, float]]:
    """Distribution of effective code widths over the decoded pixels, per coded axis.

    Parameters
    ----------
    maps : DecodedMaps
        A decode of ``sequence`` (with ``levels``).
    sequence : Sequence or DecodePlan
        What was decoded.

    Returns
    -------
    dict of axis to {width: share}
        ``width`` in projector px: ``stripe * 2**level`` for a Gray-only axis, 0.0 for an axis whose phase
        gives sub-pixel coordinates; ``share`` of the decoded pixels (0..1).
    """
    plan = _as_plan(sequence)
    decoded = maps.mask
    n = int(decoded.sum())
    out: dict[str, dict[float, float]] = {}
    for a, axis in enumerate(_AXES):
        if axis not in plan.axes:
            continue
        if any(p.axis == axis for p in plan.phase) or n == 0:
            out[axis] = {0.0: 1.0} if n else {}
            continue
        stripe = _gray_stripe(plan, axis)
        if maps.levels is None:
            counts = np.array([n], np.int64)
        else:
            lev = np.ascontiguousarray(maps.levels[a], np.uint8)
            counts = _k.level_counts(lev, np.ascontiguousarray(decoded, np.bool_))
        out[axis] = {float(stripe << k): float(c) / n for k, c in enumerate(counts) if c}
    return out


# --------------------------------------------------------------------------------------------------
# Streaming
# --------------------------------------------------------------------------------------------------


class StreamingDecoder:
    """Decode frames one at a time, as they arrive; :meth:`finish` equals :func:`decode` bit for bit.

    Every frame does its share of the work in :meth:`push` (a Gray pair when both frames are in, a
    Gray frame without inverse once its reference is in: white and black, or the whole mean phase set;
    a phase step at once). All state is allocated here and reused after :meth:`reset`.

    Parameters
    ----------
    sequence : Sequence or DecodePlan
        What each frame shows.
    shape : tuple of int
        (H, W) of the camera images.
    dtype : numpy dtype
        ``np.uint8`` or ``np.uint16``.
    params : DecodeParams
        Thresholds (``max_value`` gives the significant bits of uint16 data).
    borrow_frames : bool
        The caller keeps every pushed frame unchanged until :meth:`finish` (a scan's frame buffer): the first
        frame of a Gray pair, or a Gray frame waiting for its reference, is kept by reference instead of
        copied, which saves one image per Gray bit (10 MB for 8 bits of 1280x1024).
    """

    def __init__(
        self,
        sequence: Sequence | DecodePlan,
        shape: tuple[int, int],
        dtype: Any = np.uint8,
        params: DecodeParams = DecodeParams(),
        *,
        borrow_frames: bool = False,
    ) -> None:
        self.plan = _as_plan(sequence)
        self.params = params
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.uint8, np.uint16):
            raise DecodeError(f"streaming decoder: dtype {self.dtype}: must be uint8 or uint16")
        if len(shape) != 2 or min(shape) < 1:
            raise DecodeError(f"streaming decoder: shape {shape}: must be (height, width) >= 1")
        self.shape = (int(shape[0]), int(shape[1]))
        h, w = self.shape
        t = self.plan.tables
        self._maxval = 255 if self.dtype == np.uint8 else 65535
        # hi/lo: white/black, or running max/min when the sequence has no white/black
        self._hi = np.empty((h, w), self.dtype)
        self._lo = np.empty((h, w), self.dtype)
        self._code = np.empty((2, h, w), np.uint32)
        self._gray_axes = sorted({int(a) for a in t["gray_tab"][:, 0]})
        # per-bit contrasts: |pos - neg| of 8-bit pairs fits uint8; a single frame against white and black
        # (|2 f - w - b|, up to 510) or 16-bit data needs uint16
        pairs_only = bool(np.all(t["gray_tab"][:, 2:] >= 0)) if len(t["gray_tab"]) else True
        cst_dtype = np.uint8 if self.dtype == np.uint8 and pairs_only else np.uint16
        self._cst = np.zeros((max(len(t["gray_tab"]), 1), h, w), cst_dtype)
        nset = len(self.plan.phase)
        # phase sums: int32 in units of the coefficient quantum where no sum can leave int32, else float64;
        # both exact, so the order of the pushes does not matter
        self._int_sums = _int_sums(t, self._maxval)
        sum_dtype = np.int32 if self._int_sums else np.float64
        self._quantum = COEFFICIENT_QUANTUM if self._int_sums else 1.0
        self._ssum = np.empty((max(nset, 1), h, w), sum_dtype)
        self._csum = np.empty((max(nset, 1), h, w), sum_dtype)
        self._mean = frozenset(self.plan.mean_frames) if self.plan.white < 0 else frozenset()
        self._msum = np.empty((h, w) if self._mean else (0, 0), np.int32)
        # role of each frame: ("white"|"black"|"pos"|"neg"|"single"|"phase"|"mean", row in its table)
        self._role: dict[int, tuple[str, int]] = {}
        if self.plan.white >= 0:
            self._role[self.plan.white] = ("white", 0)
            self._role[self.plan.black] = ("black", 0)
        # the first-arrived frame of each Gray pair, or a single Gray frame waiting for its reference
        self._borrow = borrow_frames
        self._pending: dict[int, npt.NDArray[Any]] = {}
        self._pending_index: dict[int, int] = {}  # Gray row -> index of the frame held for it
        for g, (a, bit, pos, neg) in enumerate(t["gray_tab"].tolist()):
            del a, bit
            if pos >= 0 and neg >= 0:
                self._role[pos] = ("pos", g)
                self._role[neg] = ("neg", g)
            else:
                self._role[pos if pos >= 0 else neg] = ("single", g)
            if not borrow_frames:
                self._pending[g] = np.empty((h, w), self.dtype)
        for k, idx in enumerate(t["ph_idx"].tolist()):
            self._role[idx] = ("phase", k)
        for idx in self._mean:
            self._role.setdefault(idx, ("mean", 0))
        self._ph_set = np.repeat(np.arange(nset), [p.steps for p in self.plan.phase]).astype(np.int64)
        self._pushed: set[int] = set()
        self._waiting: set[int] = set()  # gray rows with one frame stored in _pending
        self._levels_shape = (2, h, w)
        # samples at full scale, per pixel (flags of _decode_kernels.CLIP_*), and which frames set which flag
        self._full = int(_max_value(self.dtype, params))
        self._clip = np.zeros((h, w), np.uint8)
        phase, pairs = _clip_plan(self.plan)
        self._clip_flag = dict(phase)
        del pairs
        self.reset()

    def reset(self) -> None:
        """Forget the frames pushed so far; buffers are kept for the next scan."""
        # the per-bit contrasts need no reset: every Gray row's push overwrites all of its row; an axis without
        # Gray bits is never read, and left untouched its pages stay unmapped (5 MB a 1280x1024 camera)
        for a in self._gray_axes:
            self._code[a].fill(0)
        self._ssum.fill(0)
        self._csum.fill(0)
        self._msum.fill(0)
        self._clip.fill(0)
        if self.plan.white < 0:
            self._hi.fill(0)
            self._lo.fill(self._maxval)
        self._pushed.clear()
        self._waiting.clear()
        if self._borrow:
            self._pending.clear()

    def _reference_ready(self) -> bool:
        """Whether single Gray frames can be thresholded: white and black, or every mean frame, pushed."""
        if self.plan.white >= 0:
            return self.plan.white in self._pushed and self.plan.black in self._pushed
        return bool(self._mean) and self._mean <= self._pushed

    def push(self, index: int, frame: npt.NDArray[Any]) -> None:
        """Add frame ``index`` of the sequence (any order).

        Parameters
        ----------
        index : int
            Position of the frame in the sequence.
        frame : ndarray, shape (H, W), the decoder's dtype
            The camera image.

        Raises
        ------
        DecodeError
            Bad index, shape or dtype, or a frame pushed twice (call :meth:`reset` between scans).
        """
        n = len(self.plan.sequence)
        if not 0 <= index < n:
            raise DecodeError(f"streaming decoder: frame index {index}: must be in 0..{n - 1}")
        img = np.asarray(frame)
        if img.shape != self.shape or img.dtype != self.dtype:
            raise DecodeError(
                f"streaming decoder: frame {index} is {img.shape} {img.dtype}: "
                f"must be {self.shape} {self.dtype}"
            )
        if index in self._pushed:
            raise DecodeError(f"streaming decoder: frame {index} pushed twice; call reset() between scans")
        self._pushed.add(index)
        role = self._role.get(index)
        if role is None:
            return
        img = np.ascontiguousarray(img)
        kind, row = role
        t = self.plan.tables
        if kind in ("white", "black"):
            np.copyto(self._hi if kind == "white" else self._lo, img)
            self._flush_singles()
            return
        if self.plan.white < 0:
            _k.stream_minmax(img, self._hi, self._lo)
        if index in self._mean:
            _k.stream_sum(img, self._msum)
        if kind == "phase":
            _k.mark_clipped(img, self._full, self._clip_flag[index], self._clip)
            s = int(self._ph_set[row])
            if self._int_sums:
                sk, ck = int(t["ph_sin_q"][row]), int(t["ph_cos_q"][row])
                _k.stream_phase(img, sk, ck, self._ssum[s], self._csum[s])
            else:
                fs, fc = float(t["ph_sin"][row]), float(t["ph_cos"][row])
                _k.stream_phase(img, fs, fc, self._ssum[s], self._csum[s])
        elif kind == "single":
            if self._reference_ready():
                self._single(row, img)
            else:
                self._keep(row, img, index)
        elif kind in ("pos", "neg"):
            if row in self._waiting:
                a, bit, _, _ = (int(x) for x in t["gray_tab"][row])
                other = self._pending[row]
                pos, neg = (img, other) if kind == "pos" else (other, img)
                _k.stream_pair(pos, neg, bit, self._code[a], self._cst[row])
                _k.mark_clipped_pair(pos, neg, self._full, self._pair_flag_of(row), self._clip)
                self._waiting.discard(row)
            else:
                self._keep(row, img, index)
        if index in self._mean:
            self._flush_singles()

    def _pair_flag_of(self, row: int) -> int:
        a = int(self.plan.tables["gray_tab"][row, 0])
        return int(_k.CLIP_PAIR_X if a == 0 else _k.CLIP_PAIR_Y)

    def _keep(self, row: int, img: npt.NDArray[Any], index: int) -> None:
        """Hold Gray row ``row``'s frame until its partner (or reference) arrives: a reference or a copy."""
        if self._borrow:
            self._pending[row] = img
        else:
            np.copyto(self._pending[row], img)
        self._pending_index[row] = index
        self._waiting.add(row)

    @property
    def borrowed(self) -> frozenset[int]:
        """Indices of the pushed frames this decoder still reads from the caller's memory (``borrow_frames``);
        every other pushed frame may be overwritten or released."""
        if not self._borrow:
            return frozenset()
        return frozenset(self._pending_index[r] for r in self._waiting)

    def _flush_singles(self) -> None:
        if not self._reference_ready():
            return
        gray_tab = self.plan.tables["gray_tab"]
        for g in sorted(self._waiting):
            if min(int(gray_tab[g, 2]), int(gray_tab[g, 3])) < 0:  # a single, not a pair
                self._single(g, self._pending[g])
                self._waiting.discard(g)

    def _single(self, g: int, img: npt.NDArray[Any]) -> None:
        a, bit, pos, _ = (int(x) for x in self.plan.tables["gray_tab"][g])
        sign = 1 if pos >= 0 else -1
        if self.plan.white >= 0:
            _k.stream_single(img, sign, self._hi, self._lo, bit, self._code[a], self._cst[g])
        else:
            _k.stream_single_mean(img, sign, self._msum, len(self._mean), bit, self._code[a], self._cst[g])

    @property
    def missing(self) -> list[int]:
        """Indices of the frames the decoder still needs."""
        need = self.plan.used + ((self.plan.white, self.plan.black) if self.plan.white >= 0 else ())
        return sorted(i for i in set(need) if i not in self._pushed)

    def finish(self, *, out: DecodedMaps | None = None) -> DecodedMaps:
        """Final per-pixel step; identical to :func:`decode` on the same frames.

        Raises
        ------
        DecodeError
            When frames the decoder needs were not pushed (names their indices).
        """
        missing = self.missing
        if missing:
            desc = ", ".join(f"{i} ({_describe(self.plan.sequence.frames[i])})" for i in missing[:12])
            more = f" and {len(missing) - 12} more" if len(missing) > 12 else ""
            raise DecodeError(
                f"streaming decoder: {len(missing)} frame(s) not pushed: {desc}{more}; push every frame "
                "of the sequence before finish()"
            )
        out, v_arg = _outputs(self.plan, self.shape, out)
        assert out.levels is not None
        t = self.plan.tables
        shift, nbins = _hist_layout(self.dtype, self.params)
        hist = _k.range_hist(self._hi, self._lo, shift, nbins)
        thr = lit_threshold(hist, self.dtype, self.params)
        _k.stream_finish(
            self._hi, self._lo, self._code, self._cst, t["gray_tab"], self._ssum, self._csum, self._quantum,
            t["axis_tab"],
            t["ph_tab"], t["ph_period"], float(self.params.relative_contrast), float(thr),
            bool(self.params.finest_bit), numba.get_num_threads(), out.u, v_arg, out.mask, out.quality,
            out.levels,
        )  # fmt: skip
        _saturation_and_reasons(out, v_arg, self._clip, self._hi, self._lo, thr, self.dtype, self.params)
        out.ignored = list(self.plan.ignored)
        return out
