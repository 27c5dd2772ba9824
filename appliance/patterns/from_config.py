"""The configured pattern sequence: ``sequence:`` of the configuration -> :class:`Sequence`."""

from __future__ import annotations

from appliance.config.schema import SequenceConfig
from appliance.errors import ConfigError, PatternError
from appliance.patterns.sequence import Sequence, exposure_capture, gray_code_sequence, gray_phase_sequence


def build_sequence(cfg: SequenceConfig, width: int, height: int) -> Sequence:
    """The configured pattern sequence for a ``width`` x ``height`` projector (px).

    Raises
    ------
    ConfigError
        ``sequence.xor_base_bit`` leaves no coarser Gray bit to XOR on this projector.
    """
    xor_base = cfg.xor_base_bit if cfg.code == "xor" else None
    try:
        return _build(cfg, width, height, xor_base)
    except PatternError as exc:
        if xor_base is None:
            raise
        raise ConfigError(
            f"sequence.xor_base_bit = {xor_base}: {exc}; choose a lower base bit (0 = the finest)"
        ) from exc


def _build(cfg: SequenceConfig, width: int, height: int, xor_base: int | None) -> Sequence:
    if cfg.kind == "gray":
        return gray_code_sequence(width, height, cfg.axes, stripe=cfg.stripe_px, inverses=cfg.inverses,
                                  xor_base=xor_base)
    if len(cfg.periods_px) == 1:
        return gray_phase_sequence(width, height, cfg.axes, period=cfg.periods_px[0], steps=cfg.steps,
                                   inverses=cfg.inverses, xor_base=xor_base)
    return gray_phase_sequence(width, height, cfg.axes, periods=cfg.periods_px, steps=cfg.steps,
                               inverses=cfg.inverses, xor_base=xor_base)


def build_capture(
    cfg: SequenceConfig, width: int, height: int
) -> tuple[Sequence, tuple[tuple[float, float], ...] | None]:
    """What a scan captures: the configured sequence once per ``sequence.exposures_us`` pass (each at its
    ``sequence.intensities`` entry when given).

    Returns
    -------
    capture : Sequence
        The sequence, repeated per exposure (once when ``exposures_us`` is empty).
    exposures : tuple of (float, float) or None
        Per frame its ``(exposure_us, intensity)``; None when ``exposures_us`` is empty (one pass at each
        camera's own exposure).
    """
    one = build_sequence(cfg, width, height)
    if not cfg.exposures_us:
        return one, None
    return exposure_capture(one, [float(e) for e in cfg.exposures_us], intensities=[float(i) for i in cfg.intensities])

