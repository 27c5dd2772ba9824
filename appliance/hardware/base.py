"""The hardware protocols every backend implements.

A backend is one module named after its configuration ``type:``. Backends know nothing about scans;
``scan.py`` drives them only through these protocols. Blocking device work happens in the backend's own
thread(s) or an executor: the async methods never block the event loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from appliance.patterns.sequence import Sequence

FrameArray = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]


@dataclass(frozen=True)
class CameraInfo:
    """What a camera says about itself."""

    name: str
    backend: str
    model: str
    serial: str
    width: int
    height: int
    pixel_format: str


@dataclass(frozen=True)
class TriggerEvent:
    """A request to scan: a button press, a control-socket command, ...

    ``t_monotonic_ns`` is on the host's CLOCK_MONOTONIC (converted by the source when it has its own clock).
    """

    source: str
    t_monotonic_ns: int
    detail: str = ""


FrameCallback = Callable[[int, FrameArray], None]
"""Called (from the camera's thread) with the frame index in the sequence and the frame data."""


@runtime_checkable
class Camera(Protocol):
    """A camera that captures one frame per trigger into preallocated buffers."""

    name: str

    async def open(self) -> CameraInfo:
        """Connect and configure; idempotent."""
        ...

    async def arm(self, n_frames: int, out: FrameArray, on_frame: FrameCallback | None = None) -> None:
        """Prepare to capture ``n_frames`` frames into ``out`` (shape (n_frames, H, W)) on triggers."""
        ...

    async def wait_frames(self, timeout_s: float) -> None:
        """Wait until every armed frame has arrived; raise :class:`~appliance.errors.CameraError` if not."""
        ...

    async def close(self) -> None:
        """Stop acquisition and release the device; idempotent."""
        ...


@runtime_checkable
class Projector(Protocol):
    """A projector that shows a :class:`Sequence`, frame by frame, on triggers or its own clock."""

    name: str

    async def open(self) -> None:
        """Connect and put the device in a known, idle state; idempotent."""
        ...

    async def load(self, sequence: Sequence) -> None:
        """Prepare ``sequence`` (upload or render its images, configure timing)."""
        ...

    async def start(self) -> None:
        """Start showing the loaded sequence."""
        ...

    async def stop(self) -> None:
        """Stop and return to idle (standby on shutdown)."""
        ...

    async def close(self) -> None:
        """Release the device; idempotent."""
        ...


@runtime_checkable
class TriggerSource(Protocol):
    """Where scan requests come from (and, for a controller, who fires the camera/projector pulses)."""

    name: str

    async def open(self) -> None:
        """Connect; idempotent."""
        ...

    async def next_event(self) -> TriggerEvent:
        """Wait for the next button press (or equivalent)."""
        ...

    async def close(self) -> None:
        """Release the device; idempotent."""
        ...
