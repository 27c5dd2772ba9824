"""The optics' blur from fringe contrast at two periods (``appliance.procedures.optics_blur``), against the blur
the virtual rig renders with: the default scene (a tilted textured plane, a sphere and a box, 480 x 384) at
camera and projector blurs of 0-1.5 px; frames made with numpy and OpenCV of a code with one slope (no split);
and a dark scene (nothing to measure)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.patterns.sequence import BlackFrame, Sequence, WhiteFrame
from appliance.procedures.optics_blur import BlurEstimate, estimate, fringe_frames
from appliance.sim.rig import VirtualRig

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "accuracy"))
from hard_scenes import scene_text  # noqa: E402


def _measure(camera_px: float, projector_px: float, gain_dn: float = 180.0) -> BlurEstimate | None:
    text = scene_text("default", gain_dn=gain_dn).replace(
        "seed: 3,", f"seed: 3, camera_blur_px: {camera_px}, projector_blur_px: {projector_px},")
    rig = VirtualRig(parse_config(text, "blur.yaml").virtual_rig)
    seq = Sequence(rig.projector.width, rig.projector.height, (WhiteFrame(), BlackFrame(), *fringe_frames()))
    stack = rig.render(seq, "cam0")
    return estimate("cam0", stack[2:], stack[0], stack[1], 255.0)


@pytest.mark.parametrize(("camera_px", "projector_px"), [(1.5, 1.5), (1.0, 0.3), (0.0, 1.5), (1.5, 0.0)])
def test_camera_and_projector_blur_are_told_apart(camera_px: float, projector_px: float) -> None:
    # measured: 1.49 / 1.51, 1.00 / 0.28, 0.04 / 1.50, 1.50 / 0.07 (code slopes 1.56-2.06, 147 k pixels)
    e = _measure(camera_px, projector_px)
    print(e)
    assert e is not None and e.camera_px is not None and e.projector_px is not None, e
    assert abs(e.camera_px - camera_px) <= 0.08, e
    assert abs(e.projector_px - projector_px) <= 0.12, e
    assert e.pixels > 100_000 and "camera blur sigma" in e.line()


def test_the_virtual_rig_default_blur() -> None:
    # the rig's defaults, camera 0.5 px, projector 0.6 px: a Gaussian of 0.5 px sampled on the pixel grid blurs
    # a little less than a continuous one (measured 0.45 / 0.62)
    e = _measure(0.5, 0.6)
    assert e is not None and e.camera_px is not None and e.projector_px is not None, e
    assert 0.4 <= e.camera_px <= 0.55 and abs(e.projector_px - 0.6) <= 0.1, e


def _made_here(slopes: tuple[float, ...], camera_px: float, projector_px: float) -> BlurEstimate | None:
    """Frames made here, in numpy and OpenCV: a code of one slope (projector px per camera px) per band of rows of
    a 240 x 320 image, each fringe's contrast lowered by the projector's blur and pixel (analytically), then
    blurred by the camera (``cv2.GaussianBlur``); 40 DN black, 200 DN white."""
    import cv2

    band = np.repeat(np.asarray(slopes, np.float64), -(-240 // len(slopes)))[:240, None]
    u = band * np.arange(320, dtype=np.float64)[None, :] + 7.3
    frames = []
    for f in fringe_frames():
        m = np.sinc(1.0 / f.period) * np.exp(-2.0 * np.pi**2 * projector_px**2 / f.period**2)
        light = (1.0 + m * np.cos(2.0 * np.pi * u / f.period + 2.0 * np.pi * f.step / f.steps)) / 2.0
        frames.append(cv2.GaussianBlur(40.0 + 160.0 * light, (0, 0), camera_px))
    return estimate("cam", np.stack(frames), np.full((240, 320), 200.0), np.full((240, 320), 40.0), 255.0)


def test_one_code_slope_gives_the_total_only() -> None:
    # a code of one slope everywhere (a flat part filling a narrow view): camera and projector blur cannot be
    # told apart; the total along the code is known (measured 1.676 px of 1.676), and the line says what to do
    e = _made_here((1.6,), 1.0, 0.5)
    assert e is not None and e.camera_px is None and e.projector_px is None, e
    total = np.hypot(0.5, 1.0 * 1.6)
    assert abs(e.total_px - total) <= 0.03 * total, (e, total)
    assert "too alike to tell" in e.line() and "curved" in e.line()


def test_slopes_made_here_tell_camera_and_projector_apart() -> None:
    # four bands of code slopes 1.0-2.2 in frames no renderer of the product made: measured 1.000 / 0.500
    e = _made_here((1.0, 1.4, 1.8, 2.2), 1.0, 0.5)
    assert e is not None and e.camera_px is not None and e.projector_px is not None, e
    assert abs(e.camera_px - 1.0) <= 0.05 and abs(e.projector_px - 0.5) <= 0.08, e


def test_a_dark_scene_gives_nothing() -> None:
    assert _measure(0.5, 0.6, gain_dn=5.0) is None
