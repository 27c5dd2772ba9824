"""The ``Sequence`` data model: the ordered frames a scan projects and captures.

The same object drives pattern generation, the projector, the decoder and the manifest format
(``SEQUENCE-MANIFEST.md``). No code anywhere hard-codes a pattern order: everything looks frames up
by what they are.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

from appliance.errors import PatternError

Axis = Literal["x", "y"]


@dataclass(frozen=True)
class GrayFrame:
    """Bit ``bit`` (0 = least significant) of the reflected Gray code of ``floor(c / stripe)``.

    A projector pixel is lit where the bit is 1 (0 when ``inverted``). With ``xor_with`` the frame shows bit
    ``bit`` XOR bit ``xor_with`` instead (a logical XOR code: every pattern keeps the base bit's high spatial
    frequency, so indirect light splits evenly between a pattern and its inverse).
    """

    axis: Axis
    bit: int
    inverted: bool = False
    stripe: int = 1
    xor_with: int | None = None
    pattern: Literal["gray"] = field(default="gray", init=False)

    def __post_init__(self) -> None:
        if self.axis not in ("x", "y"):
            raise PatternError(f"gray frame: axis = {self.axis!r}: must be 'x' or 'y'")
        if self.bit < 0 or self.bit > 30:
            raise PatternError(f"gray frame: bit = {self.bit}: must be in 0..30")
        if self.stripe < 1:
            raise PatternError(f"gray frame: stripe = {self.stripe}: must be >= 1 projector pixel")
        if self.xor_with is not None and not (0 <= self.xor_with <= 30 and self.xor_with != self.bit):
            raise PatternError(
                f"gray frame: xor_with = {self.xor_with}: must be another bit (0..30, not {self.bit}) of the code"
            )


@dataclass(frozen=True)
class PhaseFrame:
    """Step ``step`` of an N-step phase shift: I(c) = (1 + cos(2π c / period + offset + 2π step / steps)) / 2."""

    axis: Axis
    period: float
    step: int
    steps: int
    offset: float = 0.0
    pattern: Literal["phase"] = field(default="phase", init=False)

    def __post_init__(self) -> None:
        if self.axis not in ("x", "y"):
            raise PatternError(f"phase frame: axis = {self.axis!r}: must be 'x' or 'y'")
        if not (self.period > 1.0) or not math.isfinite(self.period):
            raise PatternError(f"phase frame: period = {self.period}: must be a finite number > 1 pixel")
        if self.steps < 3:
            raise PatternError(f"phase frame: steps = {self.steps}: must be >= 3")
        if not 0 <= self.step < self.steps:
            raise PatternError(f"phase frame: step = {self.step}: must be in 0..{self.steps - 1}")


@dataclass(frozen=True)
class WhiteFrame:
    """All projector pixels on."""

    pattern: Literal["white"] = field(default="white", init=False)


@dataclass(frozen=True)
class BlackFrame:
    """All projector pixels off."""

    pattern: Literal["black"] = field(default="black", init=False)


@dataclass(frozen=True)
class OtherFrame:
    """A frame of a kind this software does not decode (kept so manifests round-trip; decoders skip it)."""

    pattern: str
    params: tuple[tuple[str, str], ...] = ()


Frame = GrayFrame | PhaseFrame | WhiteFrame | BlackFrame | OtherFrame


def gray_bits_needed(size_px: int, stripe: int = 1) -> int:
    """Number of Gray bits that give every stripe of a ``size_px`` axis its own code.

    Parameters
    ----------
    size_px : int
        Projector size along the axis (pixels).
    stripe : int
        Stripe width (pixels).

    Returns
    -------
    int
        ``ceil(log2(ceil(size_px / stripe)))``, at least 1.
    """
    codes = -(-size_px // stripe)
    return max(1, math.ceil(math.log2(codes)))


@dataclass(frozen=True)
class Sequence:
    """An ordered list of frames for a projector of ``width`` x ``height`` pixels.

    Parameters
    ----------
    width, height : int
        Projector resolution (pixels).
    frames : tuple of Frame
        Frames in projection (= capture) order.
    """

    width: int
    height: int
    frames: tuple[Frame, ...]

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise PatternError(
                f"sequence: projector size {self.width}x{self.height}: must be at least 1x1 pixels"
            )

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    def __add__(self, other: Sequence) -> Sequence:
        if (self.width, self.height) != (other.width, other.height):
            raise PatternError(
                f"sequence: cannot join a {self.width}x{self.height} and a {other.width}x{other.height} "
                "sequence; use one projector size"
            )
        return Sequence(self.width, self.height, self.frames + other.frames)

    def axis_size(self, axis: Axis) -> int:
        """Projector size along ``axis`` (pixels)."""
        return self.width if axis == "x" else self.height

    def describe(self) -> str:
        """A one-line human summary, e.g. ``'1280x800: white, black, gray x 11 bits +inv, phase x P16 4 steps'``."""
        parts: list[str] = []
        kinds = {type(f).__name__ for f in self.frames}
        if "WhiteFrame" in kinds:
            parts.append("white")
        if "BlackFrame" in kinds:
            parts.append("black")
        for axis in ("x", "y"):
            grays = [f for f in self.frames if isinstance(f, GrayFrame) and f.axis == axis]
            if grays:
                bits = {f.bit for f in grays}
                inv = any(f.inverted for f in grays)
                stripes = sorted({f.stripe for f in grays})
                bases = sorted({f.xor_with for f in grays if f.xor_with is not None})
                parts.append(
                    f"gray {axis} {len(bits)} bits{' +inv' if inv else ''}"
                    + (f" stripe {stripes[0]}" if stripes != [1] else "")
                    + (f" xor bit {bases[0]}" if len(bases) == 1 else (f" xor bits {bases}" if bases else ""))
                )
            periods = sorted(
                {(f.period, f.steps) for f in self.frames if isinstance(f, PhaseFrame) and f.axis == axis}
            )
            for period, steps in periods:
                parts.append(f"phase {axis} P{period:g} {steps} steps")
        return f"{self.width}x{self.height}, {len(self.frames)} frames: " + ", ".join(parts)


# --------------------------------------------------------------------------------------------------
# Generators
# --------------------------------------------------------------------------------------------------


def gray_code_frames(
    size_px: int,
    axis: Axis,
    *,
    stripe: int = 1,
    bits: int | None = None,
    inverses: bool = True,
    xor_base: int | None = None,
) -> tuple[Frame, ...]:
    """Gray code frames for one axis, most significant bit first, each optionally followed by its inverse.

    Parameters
    ----------
    size_px : int
        Projector size along ``axis`` (pixels).
    axis : {'x', 'y'}
        ``'x'`` codes columns, ``'y'`` codes rows.
    stripe : int
        Stripe width (projector pixels); codes are ``floor(c / stripe)``.
    bits : int, optional
        Number of bits; default: enough for every stripe.
    inverses : bool
        Add the inverse of each bit (recommended: robust thresholds and contrast rejection).
    xor_base : int, optional
        XOR codes (Gupta et al. 2011): every bit above ``xor_base`` is projected XOR the base bit, which is
        projected plain (bits below it are finer than the base and stay plain). None: the plain Gray code.
    """
    n = gray_bits_needed(size_px, stripe) if bits is None else bits
    if xor_base is not None and not 0 <= xor_base < n - 1:
        raise PatternError(
            f"gray code axis {axis}: xor base bit {xor_base}: must be in 0..{n - 2} (the code has {n} bits; "
            "the base needs at least one coarser bit to XOR)"
        )
    out: list[Frame] = []
    for bit in range(n - 1, -1, -1):
        xor = xor_base if xor_base is not None and bit > xor_base else None
        out.append(GrayFrame(axis, bit, False, stripe, xor))
        if inverses:
            out.append(GrayFrame(axis, bit, True, stripe, xor))
    return tuple(out)


def phase_shift_frames(axis: Axis, period: float, steps: int = 4, offset: float = 0.0) -> tuple[Frame, ...]:
    """``steps`` phase-shifted sinusoids of ``period`` projector pixels along ``axis``."""
    return tuple(PhaseFrame(axis, float(period), s, steps, offset) for s in range(steps))


def gray_code_sequence(
    width: int, height: int, axes: str = "x", *, stripe: int = 1, inverses: bool = True,
    xor_base: int | None = None,
) -> Sequence:
    """White, black, then a full Gray code (with inverses) on each of ``axes`` ('x', 'y' or 'xy');
    ``xor_base``: XOR codes on that base bit (see :func:`gray_code_frames`)."""
    frames: list[Frame] = [WhiteFrame(), BlackFrame()]
    for axis in axes:
        if axis not in ("x", "y"):
            raise PatternError(f"gray_code_sequence: axes = {axes!r}: use 'x', 'y' or 'xy'")
        size = width if axis == "x" else height
        frames.extend(gray_code_frames(size, axis, stripe=stripe, inverses=inverses,  # type: ignore[arg-type]
                                       xor_base=xor_base))
    return Sequence(width, height, tuple(frames))


def gray_phase_sequence(
    width: int,
    height: int,
    axes: str = "x",
    *,
    period: int = 16,
    steps: int = 4,
    inverses: bool = True,
    periods: tuple[int, ...] | list[int] | None = None,
    xor_base: int | None = None,
) -> Sequence:
    """The standard sequence: white, black, complementary Gray code (stripe = period / 2), phase shift.

    The Gray code carries one bit more than the period count needs (stripe = half the period), so the
    phase is unwrapped against the centre of a half period: a Gray error of up to a quarter period at a
    fringe edge cannot cause a period jump. With several ``periods`` the Gray stripe is half the coarsest
    one; each period, once unwrapped, unwraps the next finer one, and the finest sets the result.

    Parameters
    ----------
    width, height : int
        Projector resolution (pixels).
    axes : str
        'x', 'y' or 'xy'.
    period : int
        Fringe period (projector pixels, even, >= 4); used when ``periods`` is not given.
    steps : int
        Phase steps (>= 3).
    inverses : bool
        Project the inverse of every Gray bit.
    periods : sequence of int, optional
        Several fringe periods (projector pixels, each even, >= 4), projected coarsest first.
    xor_base : int, optional
        Project the Gray code as XOR codes on this base bit (see :func:`gray_code_frames`).
    """
    chosen = (period,) if periods is None else tuple(int(p) for p in periods)
    if not chosen:
        raise PatternError("gray_phase_sequence: periods = (): give at least one period")
    for p in chosen:
        if p < 4 or p % 2:
            raise PatternError(f"gray_phase_sequence: period = {p}: must be an even number >= 4 pixels")
    if len(set(chosen)) != len(chosen):
        raise PatternError(f"gray_phase_sequence: periods = {chosen}: must be different")
    ordered = sorted(chosen, reverse=True)
    frames: list[Frame] = [WhiteFrame(), BlackFrame()]
    for axis in axes:
        if axis not in ("x", "y"):
            raise PatternError(f"gray_phase_sequence: axes = {axes!r}: use 'x', 'y' or 'xy'")
        size = width if axis == "x" else height
        frames.extend(gray_code_frames(size, axis, stripe=ordered[0] // 2, inverses=inverses,  # type: ignore[arg-type]
                                       xor_base=xor_base))
        for p in ordered:
            frames.extend(phase_shift_frames(axis, p, steps))  # type: ignore[arg-type]
    return Sequence(width, height, tuple(frames))


def exposure_capture(
    sequence: Sequence,
    exposures_us: tuple[float, ...] | list[float],
    intensity: float = 1.0,
    intensities: tuple[float, ...] | list[float] = (),
) -> tuple[Sequence, tuple[tuple[float, float], ...]]:
    """A multi-exposure capture: ``sequence`` once per exposure, one full pass after the other.

    The frames and the per-frame ``(exposure_us, intensity)`` a scan captures and a manifest records
    (``exposure_us`` / ``intensity`` of SEQUENCE-MANIFEST.md), so that a scan and an offline decode of its
    recording group the same frames into the same passes
    (:class:`appliance.reconstruct.hdr.HdrStreamingDecoder`, :func:`appliance.reconstruct.hdr.decode_passes`).

    Parameters
    ----------
    sequence : Sequence
        One pass.
    exposures_us : sequence of float
        Camera exposure of each pass (µs, > 0, each once), in capture order.
    intensity : float
        Projector brightness of every pass (0-1 of full scale) when ``intensities`` is empty.
    intensities : sequence of float
        Projector brightness of each pass (0-1 of full scale), one per exposure; a pass is one
        ``(exposure_us, intensity)`` pair, each listed once.

    Returns
    -------
    capture : Sequence
        ``len(exposures_us) * len(sequence)`` frames.
    exposures : tuple of (float, float)
        Per frame of ``capture`` its ``(exposure_us, intensity)``.
    """
    passes = [float(e) for e in exposures_us]
    if not passes:
        raise PatternError("exposure capture: exposures_us = []: give at least one exposure (µs)")
    for e in passes:
        if not (e > 0 and math.isfinite(e)):
            raise PatternError(f"exposure capture: exposure {e} µs: must be a finite number > 0")
    levels = [float(i) for i in intensities] or [float(intensity)] * len(passes)
    if len(levels) != len(passes):
        raise PatternError(
            f"exposure capture: {len(levels)} intensities for {len(passes)} exposures: give one per pass"
        )
    for i in levels:
        if not (0.0 < i <= 1.0):
            raise PatternError(f"exposure capture: intensity = {i}: must be in (0, 1]")
    pairs = list(zip(passes, levels, strict=True))
    if len(set(pairs)) != len(pairs):
        what = "exposures_us" if not intensities else "(exposure_us, intensity) pairs"
        raise PatternError(f"exposure capture: {what} = {passes if not intensities else pairs}: lists a pass twice; "
                           "list each once")  # fmt: skip
    frames = sequence.frames * len(passes)
    per_frame = tuple(p for p in pairs for _ in sequence.frames)
    return Sequence(sequence.width, sequence.height, frames), per_frame
