"""The uvc backend sets its exposure between the passes of an HDR scan (V4L2 counts 100 µs units), and a
webcam whose driver refuses manual exposure says so in one line."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
import pytest

from appliance.config.backends import UvcCameraConfig
from appliance.errors import CameraError
from appliance.hardware.base import exposure_control
from appliance.hardware.uvc import UvcCamera

_AUTO_EXPOSURE, _EXPOSURE = 21, 15  # cv2.CAP_PROP_AUTO_EXPOSURE, cv2.CAP_PROP_EXPOSURE


class ExposureCapture:
    """A V4L2-like capture whose frames show the exposure set (in device units), or one that refuses it."""

    def __init__(self, accepts_exposure: bool = True) -> None:
        self.accepts = accepts_exposure
        self.props: dict[int, float] = {}
        self.calls: list[tuple[int, float]] = []

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        self.calls.append((prop, value))
        if prop in (_AUTO_EXPOSURE, _EXPOSURE) and not self.accepts:
            return False
        self.props[prop] = value
        return True

    def grab(self) -> bool:
        return True

    def read(self) -> tuple[bool, Any]:
        return True, np.full((6, 8), int(self.props.get(_EXPOSURE, 0)) % 256, np.uint8)

    def release(self) -> None:
        return None


def _camera(cap: ExposureCapture) -> UvcCamera:
    return UvcCamera("web", UvcCameraConfig(settle_ms=0, flush_frames=0), capture_factory=lambda _d: cap,
                     sleep=lambda _s: None)  # fmt: skip


def test_exposure_is_set_in_v4l2_units_before_the_next_frames() -> None:
    cap = ExposureCapture()
    cam = _camera(cap)
    assert exposure_control(cam) is cam

    async def go() -> list[int]:
        seen = []
        try:
            info = await cam.open()
            out = np.zeros((1, info.height, info.width), np.uint8)
            for exposure_us in (2500.0, 10_000.0, 40_000.0):  # one pass each, as a scan does
                await cam.set_exposure(exposure_us)
                await cam.arm(1, out)
                await cam.trigger(0)
                await cam.wait_frames(1.0)
                seen.append(int(out[0, 0, 0]))
        finally:
            await cam.close()
        return seen

    assert asyncio.run(go()) == [25, 100, 400 % 256]
    assert cap.props[_AUTO_EXPOSURE] == 1.0  # manual exposure


def test_a_driver_without_manual_exposure_is_one_line() -> None:
    cam = _camera(ExposureCapture(accepts_exposure=False))

    async def go() -> None:
        try:
            await cam.set_exposure(2500.0)
        finally:
            await cam.close()

    with pytest.raises(CameraError) as err:
        asyncio.run(go())
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("camera 'web' (uvc, /dev/video0): exposure 2500 µs"), msg
    assert "no manual exposure control" in msg and "sequence.exposures_us" in msg, msg
