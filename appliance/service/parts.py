"""What the parts of the service may ask of each other: one small protocol per need.

The daemon (:mod:`~appliance.service.daemon`) builds the parts and wires them; no part sees the daemon itself
(``tests/test_layering.py`` holds the rule). Each part gets the :class:`~appliance.service.state.StatusBoard`
and, for everything else, one of the protocols below. Every field has one owner: the rig part
(:mod:`~appliance.service.rig`) owns the rig and the scanner, the scan worker (:mod:`~appliance.service.jobs`)
the queue and the scan count, the writer (:mod:`~appliance.service.writing`) the share writer, its thread and
the persistent state, the publisher (:mod:`~appliance.service.publish`) the lamps and the mDNS announcement,
the health check (:mod:`~appliance.service.health`) its verdict. A part changes another only by calling it.

=====================  ==========================================================================
protocol               what it is (who implements it)
=====================  ==========================================================================
:class:`Configured`    the running configuration (the daemon)
:class:`Lifecycle`     that, tasks, stop and fault, READY=1 (the daemon)
:class:`RigHost`       what the rig part reports: a press, rig ready, rig lost (the daemon)
:class:`JobsHost`      where a finished scan goes (the daemon: its scan listeners)
:class:`HealthHost`    the control socket to probe (the daemon)
:class:`ControlHost`   what the control socket's commands do (the daemon)
:class:`TuneHost`      the configuration file and its reload, for ``scan3d tune`` (the daemon)
:class:`RigView`       the rig as the others see it: ready, idle state, scanner (the rig part)
:class:`Files`         the writer thread and what runs there (the writer)
:class:`Lamps`         the refused-trigger blink (the publisher)
:class:`Worker`        the scan worker's signs of life and whether it has work (the scan worker)
=====================  ==========================================================================
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from appliance.config import AppConfig
from appliance.hardware.base import TriggerEvent, TriggerSource
from appliance.output.share import ShareWriter
from appliance.service.state import ScanRecord, State

if TYPE_CHECKING:  # the scan machinery is imported when the rig is built, not at start-up
    from appliance.hardware.registry import Rig
    from appliance.scan import Scanner, ScanPhase
    from appliance.sim.rig import VirtualRig

    ScannerFactory = Callable[[AppConfig, Callable[[ScanPhase], None]], tuple[Rig, Scanner]]
    """Builds (does not open) the rig and its scanner for a configuration, with the scanner's phase callback;
    runs in a thread. The service's is :func:`appliance.service.rig.build_scanner`; tests hand in fakes."""

T = TypeVar("T")


class Configured(Protocol):
    """The running configuration (a reload replaces it: read it when needed, never keep it)."""

    @property
    def cfg(self) -> AppConfig:
        """The running configuration."""
        ...


class Lifecycle(Configured, Protocol):
    """The service's lifecycle, as a part may use it."""

    @property
    def stopping(self) -> bool:
        """True once a stop was requested."""
        ...

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str, *, critical: bool = True) -> asyncio.Task[Any]:
        """Run ``coro`` as a task of the service (a critical one ending is a fault)."""
        ...

    def fail(self, reason: str, exc: BaseException | None = None) -> None:
        """A part is gone for good: ``fault`` with ``reason``, stop, exit status 1."""
        ...

    def request_stop(self) -> None:
        """Begin a clean shutdown."""
        ...

    def send_ready(self) -> None:
        """``READY=1`` to systemd, once."""
        ...


class RigHost(Lifecycle, Protocol):
    """What the rig part reports to the service."""

    def request_scan(self, event: TriggerEvent) -> tuple[str, Any]:
        """A press of the trigger device: accept, queue or refuse it."""
        ...

    def rig_ready(self) -> None:
        """The rig is connected and warm: queued triggers may start."""
        ...

    def rig_lost(self, reason: str) -> None:
        """Connecting failed (``reason``): the queued triggers are dropped with it."""
        ...

    def trigger_opening(self) -> None:
        """A trigger device is about to open: what its lamps show is unknown."""
        ...


class JobsHost(Lifecycle, Protocol):
    """What the scan worker hands back to the service."""

    def scan_finished(self, record: ScanRecord) -> None:
        """A scan finished or failed: tell the scan listeners."""
        ...


class HealthHost(Lifecycle, Protocol):
    """What the health check looks at beside the parts it is given."""

    @property
    def control_path(self) -> Path | None:
        """The control socket being served (None while none is)."""
        ...


class ControlHost(Protocol):
    """What the control socket's commands may do."""

    async def status_async(self) -> dict[str, Any]:
        """What ``scan3d status --json`` shows."""
        ...

    def request_scan(self, event: TriggerEvent) -> tuple[str, Any]:
        """Accept, queue or refuse a trigger: (outcome, job with a ``done`` future, or None)."""
        ...

    async def reload(self, why: str) -> tuple[bool, str]:
        """Load the configuration file now: (applied, error message)."""
        ...

    async def tune(self, time_budget_ms: float, apply: bool) -> dict[str, Any]:
        """``scan3d tune`` on the service's rig (see :class:`~appliance.service.tuning.Tuner`)."""
        ...

    async def tune_apply(self, exposures_us: list[int] | None) -> dict[str, Any]:
        """Write the last tune's choice into the configuration file and reload it."""
        ...


class TuneHost(Configured, Protocol):
    """What the tuner needs beside the rig: the configuration file and its reload."""

    @property
    def config_path(self) -> Path:
        """The configuration file the service runs (and reloads)."""
        ...

    async def reload(self, why: str) -> tuple[bool, str]:
        """Load the configuration file now and apply it when valid: (applied, error message)."""
        ...


class RigView(Protocol):
    """The rig part, as the scan worker, the publisher and the health check see it."""

    @property
    def ready(self) -> bool:
        """Connected, warm and current (no rebuild pending)."""
        ...

    def idle_state(self) -> State:
        """``idle`` when every device is fine, else ``fault``."""
        ...

    @property
    def scanner(self) -> Scanner | None:
        """The connected rig's scanner (None while not connected)."""
        ...

    @property
    def virtual(self) -> VirtualRig | None:
        """The virtual rig (scene, models, ground truth) when a device is simulated."""
        ...

    @property
    def trigger(self) -> TriggerSource | None:
        """The trigger device of the rig built last (None before)."""
        ...

    def reconnect(self) -> None:
        """Close and rebuild the rig (devices in an unknown state, a new configuration)."""
        ...


class Files(Protocol):
    """The writer thread and what runs in it: the share writer, the scan counter, the state file."""

    @property
    def writer(self) -> ShareWriter:
        """The share writer in use."""
        ...

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` in the writer thread."""
        ...

    def submit(self, fn: Callable[[], T]) -> Future[T]:
        """Hand ``fn()`` to the writer thread without waiting."""
        ...

    async def next_number(self) -> int:
        """The next scan number (persisted before it is used)."""
        ...

    async def scan_written(self) -> None:
        """A scan's files are written: the share's status and the state file, the scan's memory back."""
        ...


class Lamps(Protocol):
    """The controller's lamps, as the scan worker uses them."""

    def blink_refused(self) -> None:
        """Blink the fault lamp (a refused trigger)."""
        ...


class Worker(Protocol):
    """The scan worker's signs of life, as the health check reads them."""

    @property
    def active(self) -> object | None:
        """The job in hand (None while idle)."""
        ...

    @property
    def deadline(self) -> float | None:
        """Monotonic time (s) by which the job in hand must be done."""
        ...

    @property
    def scan_id(self) -> str:
        """The running scan's id ('' before it has one)."""
        ...

    @property
    def heartbeat(self) -> float:
        """Monotonic time (s) of the worker's last sign of life."""
        ...

    @property
    def busy(self) -> bool:
        """True while a job is queued, waiting for the scan lock or running."""
        ...
