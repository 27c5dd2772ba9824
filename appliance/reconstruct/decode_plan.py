"""Decode planning: which frames of a :class:`~appliance.patterns.sequence.Sequence` code what, as a typed
:class:`DecodePlan` (and its kernel tables, :class:`DecodeTables`), the decoder's thresholds
(:class:`DecodeParams`) and the scene-adaptive lit threshold. Shared by the batch decoder
(:mod:`~appliance.reconstruct.decode_batch`) and the streaming one (:mod:`~appliance.reconstruct.decode_stream`);
:mod:`appliance.reconstruct.decode` describes the decode and re-exports the public names.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

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
from appliance.reconstruct.settings import ReconstructionSettings

FrameStack = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]

#: A coarser phase set unwraps a finer one only up to this period ratio (its phase error, scaled by the
#: ratio, must stay well inside half the finer period).
MAX_PERIOD_RATIO = 16.0
#: Phase coefficients are quantised to this step so that sums of products are exact in float64 (in any order:
#: streaming equals batch), and, for 8-bit frames and up to 128 steps a set, in int32 (the streaming decoder's
#: sums then take half the memory). A coefficient moves by at most 2**-17 (a phase error below 1e-5 rad).
COEFFICIENT_QUANTUM = 2.0**-16
_AXES: tuple[Axis, Axis] = ("x", "y")

CORRECTABLE_BLUR_PX = 0.75
"""Several exposures: with ``reconstruction.edge_blur_px`` above 0 and up to this (px) a pixel may take a pass where
a neighbour clipped, the albedo-edge correction taking that neighbour's light out (its first-order formula holds
for such blur: the dark-and-shiny scene at 0.5 px, 0 beyond 5 sigma). Blurrier optics take the clean rule
(``DecodeParams.clean_neighbours``) instead: at 1.5 px a pass of 40 ms that clipped half the default scene put
0.1 % of the points beyond 5 sigma, corrected or not."""
CLEAN_SIGMAS = 3.0
"""The clean rule's radius in blur sigmas (``reconstruction.edge_blur_px``): a clipped region's light beyond it
is under 0.2 % of its level."""


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
    blend_ratio : float
        The check for two copies of the pattern (a mirror-like face, strong interreflection): a pixel fails with
        reason ``INTERREFLECTION`` where two or more of its fine decoded Gray bits (period up to 512 projector
        px) have a contrast under this fraction of its ``white - black`` (a clean pixel has at most one, at a
        stripe edge), and 3 of its 8 neighbours are marked too (see ``_decode_kernels.BLEND_PERIOD_PX``). 0: off.
    clean_neighbours : bool
        Several exposures: take a pixel only from a pass where none of its 8 neighbours clipped (the clipped
        neighbour's light, of unknown level, blurs into it). False where the reconstruction corrects albedo
        edges from the fused white level (``reconstruction.edge_blur_px`` > 0): the neighbour's level is then
        known from a darker pass, and the pixel takes the brightest pass that did not clip it.
    clean_radius : int
        ... the neighbourhood of that rule: a square of this radius (px; 1: the 8 neighbours). Optics that blur
        farther than a pixel carry a clipped pixel's light farther: :meth:`from_settings` takes
        :data:`CLEAN_SIGMAS` times ``reconstruction.edge_blur_px``.
    partial_cover : bool
        Undecode (reason ``EDGE``) a pixel lit over a small part of its footprint beside an unlit one (an
        occlusion or shadow edge: ``_decode_kernels.COVER_RATIO``). The decode of one exposure pass of several
        leaves it to the fused maps (:func:`appliance.reconstruct.decode_batch.drop_partial_cover`), whose
        neighbours may come from other passes.
    separate_copies : bool
        Give the pixels the blend check drops their direct code back where the two copies of the pattern come
        apart (two or more phase sets per coded axis, each period dividing the coarsest; see
        :mod:`appliance.reconstruct.ghosts`).
    """

    min_contrast_dn: float = 6.0
    relative_contrast: float = 0.15
    shadow_fraction: float = 0.2
    max_value: float | None = None
    finest_bit: bool = True
    blend_ratio: float = 0.4
    clean_neighbours: bool = True
    clean_radius: int = 1
    partial_cover: bool = True
    separate_copies: bool = True

    @property
    def fusion_radius(self) -> int:
        """The exposure fusion's clean-rule square (px): :attr:`clean_radius`, or 0 without
        :attr:`clean_neighbours` (the brightest pass that did not clip the pixel itself)."""
        return self.clean_radius if self.clean_neighbours else 0

    @staticmethod
    def from_settings(settings: ReconstructionSettings, max_value: float | None = None) -> DecodeParams:
        """The decoder's thresholds from the reconstruction settings (``reconstruction`` of the configuration),
        as the scan and the replay path both take them; ``max_value`` as the attribute."""
        blur = float(settings.edge_blur_px)
        return DecodeParams(min_contrast_dn=settings.min_contrast_dn, relative_contrast=settings.relative_contrast,
                            max_value=max_value, blend_ratio=settings.blend_ratio,
                            separate_copies=settings.separate_copies,
                            clean_neighbours=not 0 < blur <= CORRECTABLE_BLUR_PX,
                            clean_radius=max(1, math.ceil(CLEAN_SIGMAS * blur)))  # fmt: skip

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
        if not 0.0 <= self.blend_ratio < 1.0:
            raise DecodeError(f"decode params: blend_ratio = {self.blend_ratio}: must be in [0, 1) (0: no check)")
        if not 0.0 <= self.shadow_fraction <= 1.0:
            raise DecodeError(f"decode params: shadow_fraction = {self.shadow_fraction}: must be in [0, 1]")
        if self.max_value is not None and not self.max_value > 0:
            raise DecodeError(f"decode params: max_value = {self.max_value}: must be > 0 DN")


#: The default thresholds (a shared immutable instance, usable as an argument default).
DEFAULT_PARAMS = DecodeParams()


@dataclass(frozen=True)
class GrayAxisPlan:
    """The Gray code of one axis: ``frames[bit] = (pattern index, inverse index)``, -1 where absent.

    ``xor_bits`` are projected XOR bit ``xor_base`` (a logical XOR code; -1 and () for a plain Gray code).
    """

    axis: Axis
    stripe: int
    bits: int
    frames: tuple[tuple[int, int], ...]
    xor_base: int = -1
    xor_bits: tuple[int, ...] = ()


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
class DecodeTables:
    """A :class:`DecodePlan` as the integer and float tables the numba kernels read.

    Attributes
    ----------
    wb : ndarray, shape (2,), int64
        Frame indices of white and black (-1: absent).
    gray_tab : ndarray, shape (G, 4), int64
        Per Gray row: axis (0 x, 1 y), bit, pattern frame, inverse frame (-1: absent).
    axis_tab : ndarray, shape (2, 10), int64
        Per axis: coded, Gray-coded, stripe, stripe count, >= 2 bits, axis size, edge from weak bit, bits,
        XOR base bit (-1: plain Gray code), mask of the bits projected XOR the base.
    ph_tab : ndarray, shape (S, 4), int64
        Per phase set: axis, steps, unwrapping source (1 coarser set, -1 Gray, -2 axis, -3 Gray edge), first row.
    ph_period : ndarray, shape (S,), float64
        Period of each set (projector px).
    ph_idx : ndarray, shape (N,), int64
        Frame index of each phase step, sets in order.
    ph_sin, ph_cos : ndarray, shape (N,), float64
        Quantised coefficients of each step.
    ph_sin_q, ph_cos_q : ndarray, shape (N,), int32
        The same coefficients in units of :data:`COEFFICIENT_QUANTUM`.
    ph_coef_bound : int
        The largest sum of coefficient magnitudes over one set, in quanta.
    used : ndarray, shape (U,), int64
        Every frame the decoder reads, ascending.
    mean_idx : ndarray, shape (M,), int64
        The frames whose mean thresholds single Gray frames (empty when not needed).
    """

    wb: npt.NDArray[np.int64]
    gray_tab: npt.NDArray[np.int64]
    axis_tab: npt.NDArray[np.int64]
    ph_tab: npt.NDArray[np.int64]
    ph_period: npt.NDArray[np.float64]
    ph_idx: npt.NDArray[np.int64]
    ph_sin: npt.NDArray[np.float64]
    ph_cos: npt.NDArray[np.float64]
    ph_sin_q: npt.NDArray[np.int32]
    ph_cos_q: npt.NDArray[np.int32]
    ph_coef_bound: int
    used: npt.NDArray[np.int64]
    mean_idx: npt.NDArray[np.int64]


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
    tables: DecodeTables = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "tables", _tables(self))

    @property
    def used(self) -> tuple[int, ...]:
        """Indices of every frame the decoder reads, ascending."""
        return tuple(int(i) for i in self.tables.used)


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
        xor = f" xor bit {frame.xor_with}" if frame.xor_with is not None else ""
        return f"gray {frame.axis} bit {frame.bit}{xor}{' inverted' if frame.inverted else ''}"
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
            other = gray[f.axis].get((f.bit, f.inverted))
            if other is not None and sequence.frames[other].xor_with is None:  # type: ignore[union-attr]
                # the plain frame of a bit decodes it; an XOR frame of the same bit is left over
                ignored.append(f"frame {i}: {_describe(f)}: the plain frame {other} of the bit is used; unused")
                continue
            if other is not None:
                ignored.append(f"frame {other}: {_describe(sequence.frames[other])}: the plain frame {i} of "
                               "the bit is used; unused")
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
        xor_of: dict[int, int] = {}  # bit -> the base it is projected XOR with
        for b in range(needed):
            pos = gray[axis].get((b, False), -1)
            neg = gray[axis].get((b, True), -1)
            with_ = {sequence.frames[i].xor_with for i in (pos, neg) if i >= 0}  # type: ignore[union-attr]
            if len(with_) > 1:
                problems.append(
                    f"gray code axis {axis}: bit {b}'s pattern and inverse disagree on xor_with "
                    f"({sorted(with_, key=str)}); give both frames the same xor_with"
                )
            elif with_ and (k := next(iter(with_))) is not None:
                xor_of[b] = int(k)
            if (pos < 0 or neg < 0) and not has_wb:
                if mean_key is None:
                    problems.append(
                        f"gray code axis {axis}: bit {b} has no inverse frame and the sequence has no white "
                        "and black frames or complete phase set to threshold it against; add inverses, white "
                        "and black frames, or the phase frames"
                    )
                needs_mean = True
            frames_of_bit.append((pos, neg))
        bases = sorted(set(xor_of.values()))
        if len(bases) > 1:
            problems.append(
                f"gray code axis {axis}: frames are XORed with different bits {bases}; use one base bit per axis"
            )
            continue
        if bases and (bases[0] >= needed or bases[0] in xor_of):
            problems.append(
                f"gray code axis {axis}: xor_with = {bases[0]}: the base bit must be one of the code's "
                f"{needed} bits, projected plain (without xor_with); add its plain frames or fix the manifest"
            )
            continue
        gray_plans[axis] = GrayAxisPlan(axis, stripe, needed, tuple(frames_of_bit),
                                        bases[0] if bases else -1, tuple(sorted(xor_of)))

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
            if source == "gray" and g is not None and g.xor_base >= 0 and 2 * g.stripe > period:
                problems.append(
                    f"{name}: an XOR-coded Gray code needs a stripe of at most half the period (stripe "
                    f"{g.stripe} px); use a stripe of {int(period) // 2} px or the plain Gray code"
                )
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
    return plan


def _gray_stripe(plan: DecodePlan, axis: Axis) -> int:
    return next(g.stripe for g in plan.gray if g.axis == axis)


def _tables(plan: DecodePlan) -> DecodeTables:
    seq = plan.sequence
    gray_rows: list[tuple[int, int, int, int]] = []
    axis_tab = np.zeros((2, 10), np.int64)
    axis_tab[:, 8] = -1
    for a, axis in enumerate(_AXES):
        axis_tab[a, 5] = seq.axis_size(axis)
        axis_tab[a, 2] = 1
        axis_tab[a, 3] = 1
        axis_tab[a, 0] = int(axis in plan.axes)
    for g in plan.gray:
        a = _AXES.index(g.axis)
        axis_tab[a, 1:5] = (1, g.stripe, -(-seq.axis_size(g.axis) // g.stripe), int(g.bits >= 2))
        axis_tab[a, 7] = g.bits
        axis_tab[a, 8] = g.xor_base
        axis_tab[a, 9] = sum(1 << b for b in g.xor_bits)
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
    return DecodeTables(
        wb=np.array([plan.white, plan.black], np.int64),
        gray_tab=np.array(gray_rows, np.int64).reshape(-1, 4),
        axis_tab=axis_tab,
        ph_tab=ph_tab,
        ph_period=np.array([p.period for p in plan.phase], np.float64),
        ph_idx=np.array(ph_idx, np.int64),
        ph_sin=np.array(ph_sin, np.float64),
        ph_cos=np.array(ph_cos, np.float64),
        # the same coefficients in units of the quantum (exact integers), and the largest sum of their magnitudes
        # over one set: what a phase sum of frames up to 1 can reach, in quanta
        ph_sin_q=sin_q,
        ph_cos_q=cos_q,
        ph_coef_bound=max((int(max(np.abs(sin_q[a:b]).sum(), np.abs(cos_q[a:b]).sum())) for a, b in sets),
                             default=0),
        used=np.array(used, np.int64),
        mean_idx=np.array(plan.mean_frames, np.int64),
    )


def _int_sums(tables: DecodeTables, maxval: int) -> bool:
    """Whether the phase sums of frames up to ``maxval`` fit int32 in units of the coefficient quantum.

    The bound is the container's maximum (255 for 8-bit frames, 65535 for 16-bit, whatever the significant
    bits), so no frame can make a sum leave int32. Batch and streaming decodes take the same decision; either
    way the sums are exact, and the outputs identical.
    """
    return int(tables.ph_coef_bound) * maxval <= 2**31 - 1


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


def _as_plan(sequence: Sequence | DecodePlan) -> DecodePlan:
    return sequence if isinstance(sequence, DecodePlan) else plan_decode(sequence)


def _clip_plan(plan: DecodePlan) -> tuple[list[tuple[int, int]], list[tuple[int, int, int]]]:
    """The samples a code needs unclipped: (phase frame, flag) and (Gray positive, negative, flag) pairs."""
    t = plan.tables
    phase: list[tuple[int, int]] = []
    for s, (axis, steps, _src, first) in enumerate(t.ph_tab.tolist()):
        del s
        flag = int(_k.CLIP_PHASE_X if axis == 0 else _k.CLIP_PHASE_Y)
        phase.extend((int(i), flag) for i in t.ph_idx[first:first + steps].tolist())
    pairs = [
        (int(pos), int(neg), int(_k.CLIP_PAIR_X if a == 0 else _k.CLIP_PAIR_Y))
        for a, _bit, pos, neg in t.gray_tab.tolist()
        if pos >= 0 and neg >= 0
    ]
    return phase, pairs
