"""The uvc backend's software-timed capture, against a fake V4L2 capture on a virtual clock."""

from __future__ import annotations

import asyncio
from collections import deque
from typing import Any

import numpy as np
import pytest

from appliance.config.backends import UvcCameraConfig
from appliance.errors import CameraError
from appliance.hardware.uvc import UvcCamera

H, W = 24, 32
FRAME_PERIOD_S = 1 / 30


class VirtualWorld:
    """A projector showing pattern numbers, a clock, and a webcam that films the projector at 30 fps."""

    def __init__(self) -> None:
        self.now = 0.0
        self.shown: list[tuple[float, int]] = [(0.0, -1)]

    def sleep(self, seconds: float) -> None:
        self.now += seconds

    def show(self, pattern: int) -> None:
        self.shown.append((self.now, pattern))

    def pattern_at(self, t: float) -> int:
        return [p for (ts, p) in self.shown if ts <= t][-1]


class FakeCapture:
    """V4L2-like: ``depth`` driver buffers; when they are full the driver stops (keeps the *old* frames)."""

    def __init__(self, world: VirtualWorld, depth: int = 4, bgr: bool = True) -> None:
        self.world, self.depth, self.bgr = world, depth, bgr
        self.queue: deque[tuple[int, float]] = deque()
        self.next_frame_t = 0.0
        self.opened = True
        self.props: dict[int, float] = {}
        self.released = False

    def _fill(self) -> None:
        while self.next_frame_t <= self.world.now:
            if len(self.queue) < self.depth:
                self.queue.append((self.world.pattern_at(self.next_frame_t), self.next_frame_t))
            self.next_frame_t += FRAME_PERIOD_S

    def isOpened(self) -> bool:
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def grab(self) -> bool:
        self._fill()
        if not self.queue:
            self.world.now = self.next_frame_t
            self._fill()
        self.last = self.queue.popleft()
        return True

    def read(self) -> tuple[bool, Any]:
        self.grab()
        value = self.last[0] + 1  # pattern -1 (nothing shown) reads as 0
        frame = np.full((H, W), value, np.uint8)
        return True, (np.dstack([frame] * 3) if self.bgr else frame)

    def release(self) -> None:
        self.released = True


async def scan(cam: UvcCamera, world: VirtualWorld, n: int) -> tuple[np.ndarray, list[int]]:
    info = await cam.open()
    out = np.zeros((n, info.height, info.width), np.uint8)
    order: list[int] = []
    await cam.arm(n, out, lambda i, _f: order.append(i))
    for i in range(n):
        world.show(i)
        await cam.trigger(i)
    await cam.wait_frames(1.0)
    return out, order


@pytest.mark.parametrize("bgr", [True, False])
def test_each_frame_shows_its_pattern(bgr: bool) -> None:
    world = VirtualWorld()
    cap = FakeCapture(world, bgr=bgr)
    cam = UvcCamera(
        "web",
        UvcCameraConfig(settle_ms=50, flush_frames=4, exposure=120, frame_timeout_ms=30000),
        capture_factory=lambda _dev: cap,
        sleep=world.sleep,
    )

    async def go() -> tuple[np.ndarray, list[int]]:
        try:
            return await scan(cam, world, 6)
        finally:
            await cam.close()

    out, order = asyncio.run(go())
    assert order == list(range(6))
    for i in range(6):
        assert np.all(out[i] == i + 1), f"frame {i} shows pattern {int(out[i][0, 0]) - 1}"
    assert cap.props[15] == 120 and cap.props[21] == 1.0  # manual exposure requested
    assert cap.released


def test_without_flushing_the_driver_queue_frames_are_stale() -> None:
    world = VirtualWorld()
    cam = UvcCamera(
        "web",
        UvcCameraConfig(settle_ms=50, flush_frames=0, frame_timeout_ms=30000),
        capture_factory=lambda _dev: FakeCapture(world),
        sleep=world.sleep,
    )

    async def go() -> np.ndarray:
        try:
            return (await scan(cam, world, 3))[0]
        finally:
            await cam.close()

    out = asyncio.run(go())
    # The queued frames were taken before the pattern changed: why flush_frames exists.
    assert any(int(out[i][0, 0]) != i + 1 for i in range(3))


def test_a_missing_trigger_names_the_frame() -> None:
    world = VirtualWorld()
    cam = UvcCamera(
        "web",
        UvcCameraConfig(settle_ms=0, frame_timeout_ms=30000),
        capture_factory=lambda _dev: FakeCapture(world),
        sleep=world.sleep,
    )

    async def go() -> None:
        try:
            info = await cam.open()
            out = np.zeros((3, info.height, info.width), np.uint8)
            await cam.arm(3, out)
            await cam.trigger(0)
            await cam.trigger(2)
            with pytest.raises(CameraError, match=r"camera 'web' \(uvc, /dev/video0\).*frame 1 "):
                await cam.wait_frames(0.01)
        finally:
            await cam.close()

    asyncio.run(go())


def test_unopenable_device_and_wrong_buffer() -> None:
    world = VirtualWorld()
    dead = FakeCapture(world)
    dead.opened = False
    cam = UvcCamera("web", UvcCameraConfig(), capture_factory=lambda _dev: dead)
    with pytest.raises(CameraError, match="cannot be opened"):
        asyncio.run(cam.open())
    asyncio.run(cam.close())  # as the scanner does: the camera's thread ends

    cam2 = UvcCamera(
        "web", UvcCameraConfig(), capture_factory=lambda _dev: FakeCapture(world), sleep=world.sleep
    )

    async def go() -> None:
        try:
            with pytest.raises(CameraError, match="cannot hold 2 frames"):
                await cam2.arm(2, np.zeros((2, 10, 10), np.uint8))
        finally:
            await cam2.close()

    asyncio.run(go())
