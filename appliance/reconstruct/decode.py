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

The code lives in three modules: :mod:`~appliance.reconstruct.decode_plan` (the typed plan, its kernel tables,
the thresholds), :mod:`~appliance.reconstruct.decode_batch` (a whole stack) and
:mod:`~appliance.reconstruct.decode_stream` (frames as they arrive); this module keeps the public names.
"""

from __future__ import annotations

from appliance.reconstruct.decode_batch import (
    decode,
    empty_maps,
    reason_advice,
    reason_block,
    reason_counts,
    stripe_widths,
)
from appliance.reconstruct.decode_plan import (
    COEFFICIENT_QUANTUM,
    MAX_PERIOD_RATIO,
    DecodeParams,
    DecodePlan,
    DecodeTables,
    FrameStack,
    GrayAxisPlan,
    PhaseSetPlan,
    lit_threshold,
    otsu_threshold,
    plan_decode,
)
from appliance.reconstruct.decode_stream import StreamingDecoder
from appliance.reconstruct.types import DecodedMaps

__all__ = [
    "COEFFICIENT_QUANTUM",
    "MAX_PERIOD_RATIO",
    "DecodeParams",
    "DecodePlan",
    "DecodeTables",
    "DecodedMaps",
    "FrameStack",
    "GrayAxisPlan",
    "PhaseSetPlan",
    "StreamingDecoder",
    "decode",
    "empty_maps",
    "kernels_compiled",
    "lit_threshold",
    "otsu_threshold",
    "plan_decode",
    "reason_advice",
    "reason_block",
    "reason_counts",
    "stripe_widths",
]


def kernels_compiled() -> tuple[bool, str] | None:
    """Whether numba holds the decoder's compiled kernels on disk for this version and this processor.

    Returns
    -------
    (bool, str) or None
        False when the first decode of this process compiles them (30-60 s on a small PC, once per version),
        and the folder numba keeps them in; None when numba's cache cannot tell (another numba version).
    """
    from appliance._numba_cache import kernels_on_disk
    from appliance.reconstruct import _decode_kernels

    return kernels_on_disk(_decode_kernels.decode_stack)
