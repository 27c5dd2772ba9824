"""Projector images for the frames of a :class:`~appliance.patterns.sequence.Sequence`."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from appliance.errors import PatternError
from appliance.patterns.sequence import BlackFrame, Frame, GrayFrame, OtherFrame, PhaseFrame, WhiteFrame


def frame_profile(frame: Frame, size_px: int) -> npt.NDArray[np.float64]:
    """Intensity of ``frame`` along its coded axis, in [0, 1], for projector pixel centres 0..size_px-1.

    Parameters
    ----------
    frame : GrayFrame or PhaseFrame
        A coded frame.
    size_px : int
        Projector size along the frame's axis (pixels).

    Returns
    -------
    ndarray, shape (size_px,), float64
    """
    c = np.arange(size_px, dtype=np.int64)
    if isinstance(frame, GrayFrame):
        code = c // frame.stripe
        gray = code ^ (code >> 1)
        lit = gray >> frame.bit
        if frame.xor_with is not None:  # a logical XOR code: the bit XOR the base bit
            lit = lit ^ (gray >> frame.xor_with)
        bit = (lit & 1).astype(np.float64)
        return np.asarray(1.0 - bit if frame.inverted else bit, dtype=np.float64)
    if isinstance(frame, PhaseFrame):
        arg = 2 * np.pi * c / frame.period + frame.offset + 2 * np.pi * frame.step / frame.steps
        return np.asarray(0.5 * (1.0 + np.cos(arg)), dtype=np.float64)
    raise PatternError(f"frame_profile: {frame!r} has no axis profile")


def frame_intensity(frame: Frame, width: int, height: int) -> npt.NDArray[np.float64]:
    """Relative projector intensity in [0, 1] of ``frame``; shape (height, width), float64."""
    if isinstance(frame, WhiteFrame):
        return np.ones((height, width))
    if isinstance(frame, BlackFrame):
        return np.zeros((height, width))
    if isinstance(frame, OtherFrame):
        raise PatternError(f"render: frame kind {frame.pattern!r} is not known; cannot render it")
    if frame.axis == "x":
        return np.broadcast_to(frame_profile(frame, width)[None, :], (height, width)).copy()
    return np.broadcast_to(frame_profile(frame, height)[:, None], (height, width)).copy()


def render_frame(frame: Frame, width: int, height: int, bit_depth: int = 8) -> npt.NDArray[np.uint8]:
    """Projector image of ``frame`` quantised to ``bit_depth`` bits (8 -> uint8 0..255).

    Returns
    -------
    ndarray, shape (height, width), uint8
    """
    if bit_depth != 8:
        raise PatternError(f"render_frame: bit_depth = {bit_depth}: only 8-bit projector images are supported")
    return np.rint(frame_intensity(frame, width, height) * 255.0).astype(np.uint8)
