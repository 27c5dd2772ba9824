"""The hardware protocols every backend implements.

A backend is one module named after its configuration ``type:``. Backends know nothing about scans;
``scan.py`` drives them only through these protocols. Blocking device work happens in the backend's own
thread(s) or an executor: the async methods never block the event loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, cast, runtime_checkable

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
    """A camera that captures one frame per trigger into preallocated buffers.

    Whether the scan fires each frame itself is part of the protocol (:attr:`needs_software_trigger`), not
    something callers probe for; :meth:`trigger` has one (async) signature in every backend.
    """

    name: str

    @property
    def needs_software_trigger(self) -> bool:
        """True when the scan must call :meth:`trigger` once per frame (no trigger line, no free run)."""
        ...

    async def open(self) -> CameraInfo:
        """Connect and configure; idempotent."""
        ...

    async def arm(self, n_frames: int, out: FrameArray, on_frame: FrameCallback | None = None) -> None:
        """Prepare to capture ``n_frames`` frames into ``out`` (shape (n_frames, H, W)) on triggers."""
        ...

    async def trigger(self, index: int) -> None:
        """Expose frame ``index`` of the armed sequence now (by software)."""
        ...

    async def wait_frames(self, timeout_s: float) -> None:
        """Wait until every armed frame has arrived; raise :class:`~appliance.errors.CameraError` if not."""
        ...

    async def close(self) -> None:
        """Stop acquisition and release the device; idempotent."""
        ...


class ExposureControl(Protocol):
    """A camera whose exposure a scan sets between the passes of a multi-exposure (HDR) capture.

    Optional: a :class:`Camera` has it when it implements :meth:`set_exposure` (see :func:`exposure_control`).
    """

    name: str

    async def set_exposure(self, exposure_us: float) -> None:
        """Expose the frames of the next acquisition for ``exposure_us`` (µs); call between acquisitions.

        Raises
        ------
        CameraError
            When the camera refuses the value (naming the camera, the value and what it accepts).
        """
        ...


def exposure_control(camera: Camera) -> ExposureControl | None:
    """``camera`` as an :class:`ExposureControl` when it can set its exposure between passes, else None.

    Read from the object each time, as :func:`intensity_control` does.
    """
    if callable(getattr(camera, "set_exposure", None)):
        return cast(ExposureControl, camera)
    return None


class IntensityControl(Protocol):
    """A projector whose brightness a scan sets between the passes of a multi-pass (HDR) capture.

    Optional: a :class:`Projector` has it when it implements :meth:`set_intensity` (see
    :func:`intensity_control`).
    """

    async def set_intensity(self, intensity: float) -> None:
        """Show the frames of the next pass at ``intensity`` (0-1] of the projector's configured full scale.

        Raises
        ------
        ProjectorError
            When the device refuses the value or does not answer.
        """
        ...


def intensity_control(projector: object) -> IntensityControl | None:
    """``projector`` as an :class:`IntensityControl` when it can set its brightness between passes, else None.

    Read from the object each time (not ``isinstance``, whose answer the ABC machinery caches per class: so
    neither this protocol nor :class:`ExposureControl` is runtime-checkable).
    """
    if callable(getattr(projector, "set_intensity", None)):
        return cast(IntensityControl, projector)
    return None


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
    """Where scan requests come from (and, for a controller, who fires the camera/projector pulses).

    The optional capabilities are part of the protocol: :attr:`emits_sequence_pulses` says whether the source
    is a :class:`PulseSource` (see :func:`pulse_source`), :attr:`has_lamps` whether :meth:`set_leds` shows
    anything. :class:`ButtonOnly` gives a backend without either the defaults.
    """

    name: str

    @property
    def emits_sequence_pulses(self) -> bool:
        """True when the source is a :class:`PulseSource`: it fires the camera (and projector) pulses itself."""
        ...

    @property
    def has_lamps(self) -> bool:
        """True when :meth:`set_leds` shows ready/busy/fault on the device."""
        ...

    async def open(self) -> None:
        """Connect; idempotent."""
        ...

    async def next_event(self) -> TriggerEvent:
        """Wait for the next button press (or equivalent)."""
        ...

    async def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        """Show the appliance's state on the device's lamps."""
        ...

    def status(self) -> str:
        """One line about the device (shown by ``scan3d status``)."""
        ...

    async def close(self) -> None:
        """Release the device; idempotent."""
        ...


@runtime_checkable
class PulseSource(TriggerSource, Protocol):
    """A trigger source that also fires the camera (and projector) pulses of a sequence (the controller)."""

    async def run_sequence(self, n: int) -> list[int]:
        """Fire ``n`` pulses and wait until done; the pulses' timestamps (µs, the source's own clock)."""
        ...


def pulse_source(trigger: TriggerSource) -> PulseSource | None:
    """``trigger`` as a :class:`PulseSource` when it emits the pulses of a sequence, else None."""
    if trigger.emits_sequence_pulses and isinstance(trigger, PulseSource):
        return trigger
    return None


class ButtonOnly:
    """Defaults for a :class:`TriggerSource` that only reports presses: no pulse outputs, no lamps."""

    name: str
    emits_sequence_pulses = False
    has_lamps = False

    async def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        """No lamps: nothing to show."""
        return None

    def status(self) -> str:
        """``open``: a button has nothing more to say."""
        return "open"
