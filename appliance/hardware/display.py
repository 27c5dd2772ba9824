"""The ``display`` projector backend: an HDMI/DP projector driven as a second display.

Output goes through pygame (SDL2; the ``kmsdrm`` video driver works without a desktop), an optional
dependency: without it the backend raises :class:`~appliance.errors.BackendUnavailableError` saying
``pip install pygame``. A vsync'd flip returns when the new image starts to scan out, but SDL gives no
flip timestamp, so synchronisation is by counting frames: the light of a flipped image reaches the object
``latency_frames`` frames later (calibrated once per projector), each pattern stays up for
``frames_per_pattern`` frames, and camera exposures are whole multiples of the frame period (a DLP
projector shows an image as a sequence of bit planes within each frame: partial frames band).

:class:`DisplayTiming` holds that logic as pure arithmetic, testable without a display. The camera
trigger for a pattern is centred in the window during which the pattern's light is on the object::

    light of pattern i:  [flip_i + L*T,  flip_i + (L + F)*T)       L = latency_frames, F = frames_per_pattern
    trigger of pattern i: flip_i + L*T + (F - k)*T/2                k = exposure / T (whole number, k <= F)

so up to ``(F - k) T / 2`` of latency error on either side cannot mix two patterns in one exposure.
"""

from __future__ import annotations

import asyncio
import heapq
import importlib.util
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from appliance.config.backends import DisplayProjectorConfig
from appliance.errors import BackendUnavailableError, ProjectorError
from appliance.patterns.render import render_frame
from appliance.patterns.sequence import Sequence

# Module-level so tests can change them.
EXPOSURE_TOLERANCE_US = 20.0
"""How far an exposure may be from a whole number of frame periods (µs)."""
DROPPED_FLIP_FACTOR = 1.5
"""A flip interval longer than this many frame periods means a missed vsync."""

TriggerCallback = Callable[[int, int], None]
"""Called (from the display's trigger thread) with the pattern index and the CLOCK_MONOTONIC time (ns)."""


@dataclass(frozen=True)
class PatternSlot:
    """When pattern ``index`` is flipped and when its camera trigger fires (relative to the first flip).

    ``flip_frame`` counts display frames; times are in µs.
    """

    index: int
    flip_frame: int
    light_start_us: float
    light_end_us: float
    trigger_us: float


class DisplayTiming:
    """Frame-counting synchronisation between a display and cameras.

    Parameters
    ----------
    refresh_hz : float
        Display refresh rate (Hz).
    latency_frames : int
        Frames between a flip and the image's light on the object (calibrated).
    frames_per_pattern : int
        Display frames each pattern stays up.
    """

    def __init__(self, refresh_hz: float, latency_frames: int, frames_per_pattern: int) -> None:
        if not refresh_hz > 0:
            raise ProjectorError(f"display: refresh_hz = {refresh_hz}: must be > 0")
        if latency_frames < 0 or frames_per_pattern < 1:
            raise ProjectorError(
                f"display: latency_frames = {latency_frames}, frames_per_pattern = {frames_per_pattern}: "
                "need latency_frames >= 0 and frames_per_pattern >= 1"
            )
        self.refresh_hz = refresh_hz
        self.latency_frames = latency_frames
        self.frames_per_pattern = frames_per_pattern

    @classmethod
    def from_config(cls, cfg: DisplayProjectorConfig) -> DisplayTiming:
        """Timing of a ``display`` projector configuration."""
        return cls(cfg.refresh_hz, cfg.latency_frames, cfg.frames_per_pattern)

    @property
    def frame_period_us(self) -> float:
        """One display frame (µs)."""
        return 1e6 / self.refresh_hz

    @property
    def pattern_period_us(self) -> float:
        """Time each pattern is shown (µs)."""
        return self.frames_per_pattern * self.frame_period_us

    def exposure_frames(self, exposure_us: float) -> int:
        """Frames one exposure of ``exposure_us`` spans; raise if it is not a usable whole multiple.

        Raises
        ------
        ProjectorError
            If the exposure is not within :data:`EXPOSURE_TOLERANCE_US` of a whole number ``k >= 1`` of
            frame periods, or ``k > frames_per_pattern``. The message names the nearest valid exposures.
        """
        t = self.frame_period_us
        k = round(exposure_us / t)
        if k < 1 or abs(exposure_us - k * t) > EXPOSURE_TOLERANCE_US:
            lo, hi = max(1, int(exposure_us // t)), max(1, int(exposure_us // t)) + 1
            raise ProjectorError(
                f"display: exposure_us = {exposure_us:g} at {self.refresh_hz:g} Hz: must be a whole "
                f"multiple of the frame period {t:.1f} µs (DLP projectors band otherwise); "
                f"use {lo * t:.0f} or {hi * t:.0f}"
            )
        if k > self.frames_per_pattern:
            raise ProjectorError(
                f"display: exposure_us = {exposure_us:g} spans {k} frames but each pattern is up for only "
                f"frames_per_pattern = {self.frames_per_pattern}; raise frames_per_pattern to >= {k} or "
                f"shorten the exposure"
            )
        return k

    def trigger_offset_us(self, exposure_us: float) -> float:
        """Delay from the flip of a pattern to its camera trigger (µs): exposure centred in the light."""
        k = self.exposure_frames(exposure_us)
        return (self.latency_frames + (self.frames_per_pattern - k) / 2) * self.frame_period_us

    def margin_us(self, exposure_us: float) -> float:
        """Latency error tolerated on each side before two patterns mix in one exposure (µs)."""
        k = self.exposure_frames(exposure_us)
        return (self.frames_per_pattern - k) * self.frame_period_us / 2

    def schedule(self, n_patterns: int, exposure_us: float) -> list[PatternSlot]:
        """Flip frame, light window and trigger time of each pattern (µs from the first flip)."""
        t, f, lat = self.frame_period_us, self.frames_per_pattern, self.latency_frames
        offset = self.trigger_offset_us(exposure_us)
        return [
            PatternSlot(i, i * f, (i * f + lat) * t, (i * f + lat + f) * t, i * f * t + offset)
            for i in range(n_patterns)
        ]

    def total_frames(self, n_patterns: int) -> int:
        """Display frames of a whole sequence, including the latency the last pattern must wait out."""
        return n_patterns * self.frames_per_pattern + self.latency_frames

    def dropped_flips(self, flip_times_ns: list[int] | npt.NDArray[np.int64]) -> list[int]:
        """Indices ``i`` where the interval from flip ``i-1`` to flip ``i`` shows a missed vsync.

        Parameters
        ----------
        flip_times_ns : sequence of int
            CLOCK_MONOTONIC time at which each consecutive flip returned (ns).
        """
        times = np.asarray(flip_times_ns, dtype=np.int64)
        limit = DROPPED_FLIP_FACTOR * self.frame_period_us * 1e3
        return [int(i) + 1 for i in np.nonzero(np.diff(times) > limit)[0]]


# --- the backend ----------------------------------------------------------------------------------------


class Screen(Protocol):
    """What the flip loop needs from a display (pygame implements it; tests pass a fake)."""

    size: tuple[int, int]

    def prepare(self, images: list[npt.NDArray[np.uint8]]) -> None:
        """Convert (H, W) grey or (H, W, 3) RGB uint8 images into display surfaces once, before a sequence."""
        ...

    def show(self, index: int) -> None:
        """Draw prepared image ``index`` (-1 = black) into the back buffer."""
        ...

    def flip(self) -> None:
        """Present the back buffer; block until the next vsync."""
        ...

    def close(self) -> None:
        """Release the display."""
        ...


class PygameScreen:
    """A full-screen, vsync'd pygame window on one display.

    ``pygame.SCALED`` is in the flags because it is pygame's only vsync'd path without OpenGL: it draws
    into a surface of the requested size that each flip uploads to a texture and presents with an
    ``SDL_Renderer`` (without SCALED or OPENGL, pygame ignores ``vsync``). The requested size is the
    display's current mode and the window is checked to have it, so that renderer scales by exactly 1:
    pixel values reach the output unchanged, which :meth:`prepare` relies on for bit-plane images.

    Parameters
    ----------
    output : str
        SDL video driver (``SDL_VIDEODRIVER``), unless the environment already names one.
    display_index : int
        Which display.
    flip_at_scanout : bool
        Make :meth:`flip` return when the presented frame starts to scan out, not one frame earlier:
        with the ``kmsdrm`` driver SDL queues the page flip and returns unless ``SDL_VIDEO_DOUBLE_BUFFER``
        is set (SDL 2 ``KMSDRM_GLES_SwapWindow``), so this sets it in the process environment.
        Frame-accurate users (a DLPC350 video port) need it.
    """

    def __init__(self, output: str, display_index: int, *, flip_at_scanout: bool = False) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # no greeting on the service's stdout
        import pygame

        self._pg = pygame
        if output and "SDL_VIDEODRIVER" not in os.environ:
            os.environ["SDL_VIDEODRIVER"] = output
        if flip_at_scanout:
            os.environ["SDL_VIDEO_DOUBLE_BUFFER"] = "1"
        try:
            pygame.display.init()
            sizes = pygame.display.get_desktop_sizes()
            if display_index >= len(sizes):
                raise ProjectorError(
                    f"display: display_index = {display_index}: only {len(sizes)} display(s) found "
                    f"with SDL driver {os.environ.get('SDL_VIDEODRIVER')!r}; check the projector's cable"
                )
            width, height = sizes[display_index]
            self.size = (int(width), int(height))
            flags = pygame.FULLSCREEN | pygame.SCALED | pygame.NOFRAME
            self._screen = pygame.display.set_mode(self.size, flags, display=display_index, vsync=1)
            window = tuple(int(v) for v in pygame.display.get_window_size())
            if window != self.size or self._screen.get_size() != self.size:
                raise ProjectorError(
                    f"display: the window on display {display_index} is {window[0]}x{window[1]} but the display "
                    f"mode is {width}x{height}: SDL would rescale every image; check the display's mode"
                )
            pygame.mouse.set_visible(False)
        except pygame.error as exc:
            pygame.display.quit()
            raise ProjectorError(
                f"display: cannot open display {display_index} with SDL driver {output!r}: {exc}; "
                "check that no desktop holds the DRM device and the user is in the 'video' group"
            ) from exc
        except ProjectorError:
            pygame.display.quit()
            raise
        self._surfaces: list[Any] = []

    def prepare(self, images: list[npt.NDArray[np.uint8]]) -> None:
        """Convert the images to display surfaces; pixel values are copied unchanged (no scaling).

        Raises
        ------
        ProjectorError
            If an image is not (H, W) or (H, W, 3) uint8, or its size differs from the display's.
        """
        surfaces = []
        for i, img in enumerate(images):
            if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
                raise ProjectorError(
                    f"display: image {i} is {img.dtype} {img.shape}: must be (H, W) or (H, W, 3) uint8"
                )
            if (img.shape[1], img.shape[0]) != tuple(self.size):
                raise ProjectorError(
                    f"display: image {i} is {img.shape[1]}x{img.shape[0]} but the display is "
                    f"{self.size[0]}x{self.size[1]}; images must match the display mode exactly (no scaling)"
                )
            rgb = np.repeat(img.T[:, :, None], 3, axis=2) if img.ndim == 2 else img.transpose(1, 0, 2)
            surfaces.append(self._pg.surfarray.make_surface(np.ascontiguousarray(rgb)).convert())
        self._surfaces = surfaces

    def show(self, index: int) -> None:
        """Draw prepared image ``index`` (-1 = black) into the back buffer."""
        if index < 0:
            self._screen.fill((0, 0, 0))
        else:
            self._screen.blit(self._surfaces[index], (0, 0))

    def flip(self) -> None:
        """Present the back buffer; block until the next vsync."""
        self._pg.display.flip()
        self._pg.event.pump()

    def close(self) -> None:
        """Release the display."""
        self._pg.display.quit()


def _pygame_screen(cfg: DisplayProjectorConfig) -> Screen:
    return PygameScreen(cfg.output, cfg.display_index)


class DisplayProjector:
    """The ``display`` :class:`~appliance.hardware.base.Projector`: patterns on an HDMI/DP output.

    ``start()`` shows the loaded sequence once (each pattern for ``frames_per_pattern`` frames, then
    black) and returns when it has been shown; ``on_trigger`` is called once per pattern at the time
    the camera exposure should start (:class:`DisplayTiming`).

    Parameters
    ----------
    config : DisplayProjectorConfig
        Backend options.
    exposure_us : float, optional
        Camera exposure (µs), a whole multiple of the frame period; default one frame.
    on_trigger : callable, optional
        ``on_trigger(pattern_index, t_monotonic_ns)``, e.g. a camera's software trigger.
    screen_factory : callable, optional
        Makes the :class:`Screen` (default: pygame); tests pass a fake.
    """

    def __init__(
        self,
        config: DisplayProjectorConfig,
        *,
        name: str = "projector",
        exposure_us: float | None = None,
        on_trigger: TriggerCallback | None = None,
        screen_factory: Callable[[DisplayProjectorConfig], Screen] | None = None,
    ) -> None:
        if screen_factory is None and importlib.util.find_spec("pygame") is None:
            raise BackendUnavailableError(
                "projector backend 'display' needs pygame (SDL2): install it with: pip install pygame"
            )
        self.name = name
        self.config = config
        self.timing = DisplayTiming.from_config(config)
        self.exposure_us = self.timing.frame_period_us if exposure_us is None else exposure_us
        self.timing.exposure_frames(self.exposure_us)  # refuse a banding exposure at construction
        self.on_trigger = on_trigger
        self._factory: Callable[[DisplayProjectorConfig], Screen] = screen_factory or _pygame_screen
        self._screen: Screen | None = None
        self._n_patterns = 0
        self._stop = threading.Event()
        self._lock = asyncio.Lock()
        self.flip_times_ns: list[int] = []
        self.trigger_times_ns: list[int] = []

    async def open(self) -> None:
        """Open the display full-screen (in a thread: SDL initialisation can take a while)."""
        if self._screen is None:
            self._screen = await asyncio.to_thread(self._factory, self.config)

    async def load(self, sequence: Sequence) -> None:
        """Render the sequence's images and convert them to display surfaces."""
        screen = self._require_screen()
        if (sequence.width, sequence.height) != tuple(screen.size):
            raise ProjectorError(
                f"projector {self.name!r} (display): sequence is {sequence.width}x{sequence.height} but the "
                f"display is {screen.size[0]}x{screen.size[1]}; generate the sequence for the display's size"
            )
        images = [render_frame(f, sequence.width, sequence.height) for f in sequence]
        await asyncio.to_thread(screen.prepare, images)
        self._n_patterns = len(images)

    async def start(self) -> None:
        """Show the loaded sequence once; return when its last pattern has been exposed."""
        screen = self._require_screen()
        if not self._n_patterns:
            raise ProjectorError(f"projector {self.name!r} (display): start() before load(); load a sequence")
        async with self._lock:
            self._stop.clear()
            await asyncio.to_thread(self._run_sequence, screen)
        dropped = self.timing.dropped_flips(self.flip_times_ns)
        if dropped:
            raise ProjectorError(
                f"projector {self.name!r} (display): {len(dropped)} missed vsync(s) at flips {dropped[:5]}; "
                "patterns and exposures went out of step: reduce system load or raise frames_per_pattern"
            )

    def _run_sequence(self, screen: Screen) -> None:
        per = self.timing.frames_per_pattern
        offset_ns = round(self.timing.trigger_offset_us(self.exposure_us) * 1e3)
        triggers = _TriggerThread(self.on_trigger)
        self.flip_times_ns = []
        try:
            for frame in range(self.timing.total_frames(self._n_patterns) + 1):
                if self._stop.is_set():
                    break
                pattern, within = divmod(frame, per)
                if within == 0:
                    screen.show(pattern if pattern < self._n_patterns else -1)
                screen.flip()
                now = time.monotonic_ns()
                self.flip_times_ns.append(now)
                if within == 0 and pattern < self._n_patterns:
                    triggers.add(now + offset_ns, pattern)
        finally:
            self.trigger_times_ns = triggers.finish()

    async def stop(self) -> None:
        """Stop a running sequence and show black."""
        self._stop.set()
        async with self._lock:
            if self._screen is not None:
                screen = self._screen
                await asyncio.to_thread(show_black, screen)

    async def close(self) -> None:
        """Release the display; idempotent."""
        self._stop.set()
        if self._screen is not None:
            screen, self._screen = self._screen, None
            await asyncio.to_thread(screen.close)

    def _require_screen(self) -> Screen:
        if self._screen is None:
            raise ProjectorError(f"projector {self.name!r} (display): not open; call open() first")
        return self._screen


def show_black(screen: Screen) -> None:
    """Draw black and flip."""
    screen.show(-1)
    screen.flip()


class _TriggerThread:
    """Fires trigger callbacks at CLOCK_MONOTONIC deadlines, independent of the blocking flips."""

    def __init__(self, callback: TriggerCallback | None) -> None:
        self._callback = callback
        self._heap: list[tuple[int, int]] = []
        self._cond = threading.Condition()
        self._closing = False
        self._fired: list[int] = []
        self._thread = threading.Thread(target=self._loop, name="display-trigger", daemon=True)
        self._thread.start()

    def add(self, deadline_ns: int, index: int) -> None:
        with self._cond:
            heapq.heappush(self._heap, (deadline_ns, index))
            self._cond.notify()

    def finish(self) -> list[int]:
        """Fire what is pending, stop the thread, return the fire times (ns) in pattern order."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()
        return self._fired

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._heap and not self._closing:
                    self._cond.wait()
                if not self._heap:
                    return
                deadline, index = self._heap[0]
                wait_s = (deadline - time.monotonic_ns()) / 1e9
                if wait_s > 0:
                    self._cond.wait(wait_s)
                    continue
                heapq.heappop(self._heap)
            now = time.monotonic_ns()
            self._fired.append(now)
            if self._callback is not None:
                self._callback(index, now)
