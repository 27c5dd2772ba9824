"""The rig as the service sees it: connect (build, open, warm the kernels), retry with backoff while it is
absent or failing, rebuild it when the configuration changes it, and turn the trigger device's presses into
scan requests.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from appliance.config import AppConfig
from appliance.errors import ApplianceError
from appliance.hardware.base import TriggerSource
from appliance.service import memory
from appliance.service.parts import RigHost
from appliance.service.state import DeviceStatus, Phase, State, StatusBoard

if TYPE_CHECKING:
    from appliance.hardware.registry import Rig
    from appliance.scan import Scanner, ScanPhase
    from appliance.service.parts import ScannerFactory
    from appliance.sim.rig import VirtualRig

log = logging.getLogger(__name__)

# Module-level so tests can shorten it.
RETRY_FIRST_S = 1.0  # first wait before reconnecting hardware; doubles up to service.retry_max_s


SAFE_LAYERS = ("omp", "tbb")  # numba threading layers safe for parallel kernels launched from several threads


class FatalError(ApplianceError):
    """A problem no retry can fix: the service stops with exit status 1."""


def select_threading_layer() -> None:
    """Ask numba for a thread-safe threading layer (tbb, else omp) unless the operator chose one.

    Kernels run concurrently (one decode thread per camera, the reconstruction): numba's ``workqueue`` layer
    is not safe for that. Must run before the first parallel kernel of the process.
    """
    from numba.core import config

    if str(getattr(config, "THREADING_LAYER", "default")) == "default":
        setattr(config, "THREADING_LAYER", "threadsafe")  # noqa: B010 (numba's config has no stubs)


def current_threading_layer() -> str | None:
    """The numba threading layer in use (None before the first parallel kernel has run)."""
    from numba.np.ufunc.parallel import threading_layer

    layer: Callable[[], str] = threading_layer
    try:
        return layer()
    except ValueError:
        return None


def threading_layer_problem() -> str:
    """'' when the numba threading layer in use is thread-safe; else what is wrong and what to do.

    Only meaningful once a parallel kernel has run (after the warm-up).
    """
    layer = current_threading_layer()
    if layer is None or layer in SAFE_LAYERS:  # None: no parallel kernel has run, nothing is unsafe yet
        return ""
    return (f"numba threading layer is {layer!r}, which is not safe with kernels running in several threads; "
            "unset NUMBA_THREADING_LAYER (or set it to omp or tbb) and install libgomp1 (apt) or tbb (pip)")


def build_scanner(cfg: AppConfig, on_phase: Callable[[ScanPhase], None]) -> tuple[Rig, Scanner]:
    """Build (not open) the configured rig and its scanner; blocking (renders the virtual rig, builds ray
    tables), run in a thread. The service's :data:`~appliance.service.parts.ScannerFactory`.

    Parameters
    ----------
    cfg : AppConfig
        The configuration (devices, calibration file, sequence, reconstruction).
    on_phase : callable
        The scanner's phase callback (see :class:`~appliance.scan.Scanner`).
    """
    from appliance.hardware.registry import build_rig
    from appliance.scan import Scanner, load_calibration_for

    rig = build_rig(cfg)
    calibration = load_calibration_for(cfg, rig)
    return rig, Scanner(cfg, rig, calibration, keep_frames=False, on_phase=on_phase)


class RigManager:
    """Connects the rig of one service and keeps it connected; the one owner of the rig and its scanner.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (this part writes its ``devices`` and ``sequence``).
    host : RigHost
        The configuration, the service's tasks, and where presses, "ready" and "lost" go.
    make_scanner : ScannerFactory
        Builds the rig and its scanner for a configuration (in a thread); tests hand in fakes.
    scan_lock : asyncio.Lock
        Held by a scan and by every change of the rig.
    """

    def __init__(self, board: StatusBoard, host: RigHost, make_scanner: ScannerFactory,
                 scan_lock: asyncio.Lock) -> None:
        self.board = board
        self.host = host
        self.make_scanner = make_scanner
        self.scan_lock = scan_lock
        self.rig: Rig | None = None  # the rig built last (kept after close: its trigger shows the lamps)
        self.scanner: Scanner | None = None  # the open rig's scanner (None while not connected)
        self.changed = asyncio.Event()  # set: close and rebuild the rig (new configuration, lost devices)
        self.connected = False  # connected and warm
        self._trigger_task: asyncio.Task[None] | None = None

    def devices_from_config(self) -> None:
        """Every configured device, not connected yet."""
        cfg = self.host.cfg
        devs = {f"camera:{n}": DeviceStatus("camera", n, c.type) for n, c in cfg.cameras.items()}
        devs["projector"] = DeviceStatus("projector", "projector", cfg.projector.type)
        devs["trigger"] = DeviceStatus("trigger", "trigger", cfg.trigger.type)
        self.board.devices = devs

    @property
    def ready(self) -> bool:
        """True when the rig is connected and current (no rebuild pending)."""
        return self.connected and self.scanner is not None and not self.changed.is_set()

    @property
    def virtual(self) -> VirtualRig | None:
        """The virtual rig of the rig built last (None: no simulated device, or no rig yet)."""
        return self.rig.virtual if self.rig is not None else None

    @property
    def trigger(self) -> TriggerSource | None:
        """The trigger device of the rig built last (None before the first)."""
        return self.rig.trigger if self.rig is not None else None

    def reconnect(self) -> None:
        """Close and rebuild the rig (a new configuration, devices in an unknown state); not ready from now."""
        self.changed.set()

    def idle_state(self) -> State:
        """``idle`` when every device is fine, else ``fault``."""
        return State.IDLE if all(d.ok for d in self.board.devices.values()) else State.FAULT

    def on_scan_phase(self, phase: ScanPhase) -> None:
        """The scanner's phases (on the event loop): once every camera has its frames, the scan is
        ``processing``."""
        b = self.board
        if phase.value == "captured" and b.state == State.SCANNING:
            b.set_state(State.PROCESSING, b.detail)

    async def connect(self) -> None:
        """Build and open the rig, open the trigger, warm the kernels (under the scan lock)."""
        loop = asyncio.get_running_loop()
        cfg = self.host.cfg
        b = self.board
        b.set_state(State.STARTING, "connecting hardware", Phase.CONNECT)
        rig, scanner = await loop.run_in_executor(None, self.make_scanner, cfg, self.on_scan_phase)
        self.rig = rig
        b.sequence = scanner.sequence.describe()
        try:
            await scanner.open()
        except BaseException:
            with contextlib.suppress(Exception):
                await scanner.close()
            raise
        for n in cfg.cameras:
            info = scanner.camera_info.get(n)
            detail = (f"{info.model} {info.serial}, {info.width}x{info.height} {info.pixel_format}"
                      if info is not None else "open")
            b.devices[f"camera:{n}"] = DeviceStatus("camera", n, cfg.cameras[n].type, True, detail)
        b.devices["projector"] = DeviceStatus("projector", "projector", cfg.projector.type, True,
                                              f"sequence loaded: {scanner.sequence.describe()}")
        self.scanner = scanner
        await self._open_trigger()
        b.set_state(State.STARTING, "warming kernels", Phase.WARM)
        t = time.perf_counter()
        try:
            await scanner.warm_up()  # a discarded scan on the virtual rig, else a decode of blank frames
        except ValueError as exc:
            if "threading layer" in str(exc):
                raise FatalError(f"numba: {exc}; install libgomp1 (apt) or tbb (pip install tbb)") from exc
            raise
        problem = threading_layer_problem()
        if problem:
            raise FatalError(problem)
        await asyncio.to_thread(memory.trim)  # the warm-up's temporaries
        log.info("kernels warm in %.1f s", time.perf_counter() - t)

    def _trigger_link(self, state: Any, reason: str) -> None:
        """The trigger backend's link state changed (backends that reconnect by themselves report here)."""
        b = self.board
        dev = b.devices.get("trigger")
        if dev is None:
            return
        ok = getattr(state, "value", str(state)) == "ready"
        if ok != dev.ok:
            if not ok:
                b.error("hardware", f"trigger {dev.backend}: {reason}")
            dev.ok, dev.detail = ok, f"{getattr(state, 'value', state)}: {reason}"
            if not b.busy and b.state in (State.IDLE, State.FAULT) and self.scanner:
                b.set_state(self.idle_state(), "ready" if ok else f"trigger: {reason}")

    async def _open_trigger(self) -> None:
        if self.rig is None:
            return
        trig = self.rig.trigger
        kind = self.host.cfg.trigger.type
        if hasattr(trig, "on_state"):
            trig.on_state = self._trigger_link
        self.host.trigger_opening()
        try:
            await trig.open()
        except (ApplianceError, OSError) as exc:
            self.board.devices["trigger"] = DeviceStatus("trigger", trig.name, kind, False, str(exc))
            self.board.error("hardware", f"trigger {kind}: {exc}")
        else:
            detail = trig.status() or "open"
            self.board.devices["trigger"] = DeviceStatus("trigger", trig.name, kind, True, detail)
        self._trigger_task = self.host.spawn(self._trigger_loop(trig), "trigger")

    async def close(self) -> None:
        """Stop the trigger loop, close the trigger and the rig."""
        self.connected = False
        task = self._trigger_task
        if task is not None:
            task.cancel()
            # wait for it to end without swallowing a cancellation of this caller: the rig loop, cancelled by a
            # stop while it rebuilds the rig (after a reload or a tune), must end, not build a new rig
            await asyncio.wait({task})
            self._trigger_task = None
        if self.rig is not None:
            with contextlib.suppress(Exception):
                await self.rig.trigger.close()
        if self.scanner is not None:
            try:
                await self.scanner.close()
            except Exception as exc:
                log.warning("closing the rig: %s", exc)
        self.scanner = None

    async def loop(self) -> None:
        """Connect, retry with backoff on failure, rebuild on :attr:`changed` (runs until cancelled)."""
        host, b = self.host, self.board
        delay = RETRY_FIRST_S
        failures = 0
        while True:
            self.devices_from_config()
            try:
                async with self.scan_lock:
                    await self.connect()
            except FatalError as exc:
                await self.close()
                host.fail(str(exc))
                return
            except Exception as exc:  # any failure to connect is a fault to retry, never the end
                await self.close()
                failures += 1
                if not isinstance(exc, (ApplianceError, OSError)):
                    log.exception("hardware: unexpected error")
                for d in b.devices.values():
                    if not d.ok and d.detail == "not connected":
                        d.detail = "not connected (see last error)"
                if failures == 1:
                    log.error("hardware: %s; retrying with backoff", exc)
                b.error("hardware", str(exc))
                host.rig_lost(str(exc))
                b.set_state(State.FAULT, f"hardware: {exc}; retry in {delay:.0f} s", Phase.CONNECT)
                host.send_ready()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self.changed.wait(), delay)
                self.changed.clear()
                delay = min(delay * 2, host.cfg.service.retry_max_s)
                continue
            if failures:
                log.info("hardware recovered after %d failed attempt(s)", failures)
            failures, delay = 0, RETRY_FIRST_S
            self.connected = True
            b.set_state(self.idle_state(), "ready", Phase.READY)
            host.send_ready()
            host.rig_ready()
            await self.changed.wait()
            self.connected = False  # not ready from here on, before the lock is taken
            self.changed.clear()
            async with self.scan_lock:
                await self.close()

    async def _trigger_loop(self, trig: Any) -> None:
        b = self.board
        delay = RETRY_FIRST_S
        key = "trigger"
        while True:
            try:
                event = await trig.next_event()
            except (ApplianceError, OSError) as exc:
                dev = b.devices[key]
                if dev.ok:
                    log.error("trigger %s failed: %s; retrying with backoff", trig.name, exc)
                    b.error("hardware", f"trigger {trig.name}: {exc}")
                dev.ok, dev.detail = False, str(exc)
                if not b.busy:
                    b.set_state(State.FAULT, f"trigger: {exc}")
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.host.cfg.service.retry_max_s)
                with contextlib.suppress(ApplianceError, OSError):
                    await trig.close()
                try:
                    await trig.open()
                except (ApplianceError, OSError) as exc2:
                    dev.detail = str(exc2)
                    continue
                log.info("trigger %s recovered", trig.name)
                dev.ok, dev.detail, delay = True, "open", RETRY_FIRST_S
                if not b.busy:
                    b.set_state(self.idle_state(), "ready")
                continue
            self.host.request_scan(event)
