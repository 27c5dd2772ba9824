"""Timing logic of the ``display`` (HDMI/DP) projector, and its flip loop against a fake screen."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import numpy.typing as npt
import pytest

from appliance.config.backends import DisplayProjectorConfig
from appliance.errors import BackendUnavailableError, ProjectorError
from appliance.hardware import display as dm
from appliance.hardware.display import DisplayProjector, DisplayTiming
from appliance.patterns import gray_code_sequence, render_frame


def test_frame_and_pattern_periods() -> None:
    t = DisplayTiming(60.0, latency_frames=2, frames_per_pattern=3)
    assert t.frame_period_us == pytest.approx(16666.667, abs=1e-3)
    assert t.pattern_period_us == pytest.approx(50000.0, abs=1e-6)
    assert t.total_frames(10) == 32  # 10 patterns x 3 frames + 2 frames of latency for the last one


@pytest.mark.parametrize(("exposure_us", "frames"), [(16667, 1), (16660, 1), (33333, 2), (50000, 3)])
def test_whole_multiples_of_the_frame_period_are_accepted(exposure_us: float, frames: int) -> None:
    assert DisplayTiming(60.0, 2, 3).exposure_frames(exposure_us) == frames


def test_banding_exposures_are_refused_with_the_nearest_valid_values() -> None:
    t = DisplayTiming(60.0, 2, 3)
    with pytest.raises(
        ProjectorError, match=r"exposure_us = 25000 at 60 Hz: must be a whole multiple.*16667 or 33333"
    ):
        t.exposure_frames(25000)
    with pytest.raises(ProjectorError, match="whole multiple"):
        t.exposure_frames(5000)  # under one frame
    with pytest.raises(ProjectorError, match=r"spans 4 frames.*frames_per_pattern = 3"):
        t.exposure_frames(66667)


@pytest.mark.parametrize("refresh_hz", [60.0, 59.94, 120.0])
@pytest.mark.parametrize("latency", [0, 1, 3])
@pytest.mark.parametrize(("per_pattern", "k"), [(1, 1), (2, 1), (3, 1), (3, 2), (4, 4), (5, 2)])
def test_each_exposure_lies_inside_its_own_patterns_light_centred(
    refresh_hz: float, latency: int, per_pattern: int, k: int
) -> None:
    t = DisplayTiming(refresh_hz, latency, per_pattern)
    exposure = k * t.frame_period_us
    slots = t.schedule(6, exposure)
    margin = t.margin_us(exposure)
    assert margin == pytest.approx((per_pattern - k) * t.frame_period_us / 2, abs=1e-6)
    for i, s in enumerate(slots):
        assert s.flip_frame == i * per_pattern
        assert s.light_start_us == pytest.approx((i * per_pattern + latency) * t.frame_period_us)
        # [trigger, trigger + exposure] sits in the pattern's light with the same margin on both sides
        assert s.trigger_us - s.light_start_us == pytest.approx(margin, abs=1e-6)
        assert s.light_end_us - (s.trigger_us + exposure) == pytest.approx(margin, abs=1e-6)
        if i:  # never overlaps the previous pattern's light
            assert s.trigger_us >= slots[i - 1].light_end_us - 1e-6
    assert t.trigger_offset_us(exposure) == pytest.approx(slots[0].trigger_us)


def test_dropped_flips_are_found() -> None:
    t = DisplayTiming(100.0, 1, 2)  # 10 ms frames
    ms = 1_000_000
    flips = [0, 10 * ms, 20 * ms, 41 * ms, 51 * ms, 61 * ms, 75 * ms]  # a missed vsync at 3, 14 ms ok at 6
    assert t.dropped_flips(flips) == [3]
    assert t.dropped_flips([]) == []


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ProjectorError, match="frames_per_pattern = 0"):
        DisplayTiming(60.0, 1, 0)
    with pytest.raises(ProjectorError, match="refresh_hz"):
        DisplayTiming(0.0, 1, 1)


# --- the flip loop with a fake screen -------------------------------------------------------------------


class FakeScreen:
    """Records what is drawn and when flips happen (no real vsync: flips return at once)."""

    def __init__(self, cfg: DisplayProjectorConfig, size: tuple[int, int] = (32, 8)) -> None:
        self.size = size
        self.images: list[npt.NDArray[np.uint8]] = []
        self.shown: list[tuple[int, int]] = []  # (flip count before the draw, image index)
        self.flips = 0
        self.closed = False
        self.thread: threading.Thread | None = None

    def prepare(self, images: list[npt.NDArray[np.uint8]]) -> None:
        self.images = images

    def show(self, index: int) -> None:
        self.shown.append((self.flips, index))

    def flip(self) -> None:
        self.thread = threading.current_thread()
        self.flips += 1

    def close(self) -> None:
        self.closed = True


def test_the_flip_loop_shows_every_pattern_and_triggers_once_per_pattern_in_order() -> None:
    cfg = DisplayProjectorConfig(refresh_hz=500.0, latency_frames=2, frames_per_pattern=3)
    screens: list[FakeScreen] = []
    fired: list[tuple[int, int]] = []

    def factory(c: DisplayProjectorConfig) -> FakeScreen:
        screens.append(FakeScreen(c))
        return screens[-1]

    proj = DisplayProjector(
        cfg, exposure_us=4000.0, on_trigger=lambda i, t: fired.append((i, t)), screen_factory=factory
    )
    seq = gray_code_sequence(32, 8, "x")

    async def go() -> None:
        await proj.open()
        await proj.load(seq)
        await proj.start()
        await proj.stop()
        await proj.close()
        await proj.close()

    asyncio.run(go())
    screen = screens[0]
    n = len(seq)
    # Pattern i is drawn before flip i * 3; black after the last one has waited out its latency.
    assert screen.shown[: n + 1] == [(i * 3, i) for i in range(n)] + [(n * 3, -1)]
    assert screen.flips == cfg.frames_per_pattern * n + cfg.latency_frames + 1 + 1  # + black + stop()
    assert screen.thread is not threading.main_thread() and screen.closed
    np.testing.assert_array_equal(screen.images[3], render_frame(seq.frames[3], 32, 8))
    # One trigger per pattern, in order, each no earlier than its flip + the centred offset.
    assert [i for i, _ in fired] == list(range(n))
    offset_ns = proj.timing.trigger_offset_us(4000.0) * 1e3
    for i, t_ns in fired:
        assert t_ns >= proj.flip_times_ns[i * 3] + offset_ns - 1
    assert proj.trigger_times_ns == [t for _, t in fired]


def test_size_mismatch_and_banding_exposure_are_refused() -> None:
    cfg = DisplayProjectorConfig(refresh_hz=60.0, frames_per_pattern=2)
    with pytest.raises(ProjectorError, match="whole multiple"):
        DisplayProjector(cfg, exposure_us=10000.0, screen_factory=FakeScreen)
    proj = DisplayProjector(cfg, screen_factory=FakeScreen)

    async def go() -> None:
        await proj.open()
        with pytest.raises(ProjectorError, match="sequence is 64x8 but the display is 32x8"):
            await proj.load(gray_code_sequence(64, 8, "x"))
        with pytest.raises(ProjectorError, match=r"start\(\) before load\(\)"):
            await proj.start()
        await proj.close()

    asyncio.run(go())


def test_missing_pygame_disables_only_this_backend_with_advice(without_pygame: None) -> None:
    with pytest.raises(BackendUnavailableError, match="pip install pygame"):
        DisplayProjector(DisplayProjectorConfig())
    assert dm.DisplayTiming(60.0, 1, 1).frame_period_us > 0  # the timing logic still imports
