"""The ``gpio`` trigger source: a button on a GPIO line through libgpiod v2 (PyPI ``gpiod`` 2.x).

The line request's file descriptor is watched with ``loop.add_reader``; edge events carry kernel
timestamps on CLOCK_MONOTONIC. Presses closer together than the debounce period are merged (the kernel
debounces too, where the chip supports it).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from datetime import timedelta
from typing import Any, Protocol

from appliance.config.backends import GpioTriggerConfig
from appliance.errors import BackendUnavailableError, TriggerError
from appliance.hardware.base import ButtonOnly, TriggerEvent

log = logging.getLogger(__name__)


class LineRequest(Protocol):
    """The part of ``gpiod.LineRequest`` this backend uses."""

    @property
    def fd(self) -> int: ...

    def read_edge_events(self) -> list[Any]: ...

    def release(self) -> None: ...


def request_line_gpiod(cfg: GpioTriggerConfig) -> LineRequest:
    """Request the button line from the kernel with libgpiod v2."""
    try:
        import gpiod
        from gpiod.line import Bias, Edge
    except ImportError as exc:
        raise BackendUnavailableError(
            f"trigger gpio: the gpiod module is missing ({exc}); install it with pip install 'gpiod>=2.1' "
            "(Debian's python3-libgpiod is the old v1 API and does not work)"
        ) from exc
    try:
        settings = gpiod.LineSettings(
            edge_detection=Edge.FALLING if cfg.active_low else Edge.RISING,
            bias=Bias.PULL_UP if cfg.active_low else Bias.PULL_DOWN,
            debounce_period=timedelta(milliseconds=cfg.debounce_ms),
        )
        return gpiod.request_lines(cfg.chip, consumer="scan3d", config={cfg.line: settings})  # type: ignore[no-any-return]
    except OSError as exc:
        raise TriggerError(
            f"trigger gpio: cannot request {cfg.chip} line {cfg.line} ({exc.strerror or exc}); check the chip "
            "path, that no other program holds the line, and that the service user is in the gpio group"
        ) from exc


class GpioTrigger(ButtonOnly):
    """A button on a GPIO line.

    Parameters
    ----------
    cfg : GpioTriggerConfig
        Chip, line, polarity, debounce.
    request_line : callable, optional
        Opens the line (default: libgpiod v2); tests pass a fake with the same ``fd`` +
        ``read_edge_events()`` interface.
    """

    def __init__(
        self, cfg: GpioTriggerConfig, request_line: Callable[[GpioTriggerConfig], LineRequest] | None = None
    ) -> None:
        self.name = f"gpio:{cfg.chip}:{cfg.line}"
        self.cfg = cfg
        self._request_line = request_line or request_line_gpiod
        self._req: LineRequest | None = None
        self._events: asyncio.Queue[TriggerEvent] = asyncio.Queue()
        self._last_ns: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.presses = 0
        self.bounces = 0

    async def open(self) -> None:
        if self._req is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._req = self._request_line(self.cfg)
        self._loop.add_reader(self._req.fd, self._readable)
        log.info("trigger %s: listening for presses", self.name)

    def _readable(self) -> None:
        assert self._req is not None
        try:
            events = self._req.read_edge_events()
        except OSError as exc:
            log.error("trigger %s: reading edge events failed: %s", self.name, exc)
            return
        debounce_ns = int(self.cfg.debounce_ms * 1e6)
        for ev in events:
            t = int(ev.timestamp_ns)
            if self._last_ns is not None and t - self._last_ns < debounce_ns:
                self.bounces += 1
                continue
            self._last_ns = t
            self.presses += 1
            self._events.put_nowait(TriggerEvent(self.name, t, "button"))

    async def next_event(self) -> TriggerEvent:
        return await self._events.get()

    async def close(self) -> None:
        if self._req is None:
            return
        if self._loop is not None:
            self._loop.remove_reader(self._req.fd)
        self._req.release()
        self._req = None
