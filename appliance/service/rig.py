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

from appliance.errors import ApplianceError
from appliance.service import memory
from appliance.service.state import DeviceStatus, Phase, State

if TYPE_CHECKING:
    from appliance.scan import ScanPhase
    from appliance.service.daemon import Service

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


class RigManager:
    """Connects the rig of one service and keeps it connected."""

    def __init__(self, svc: Service) -> None:
        self.svc = svc
        self.changed = asyncio.Event()  # set: close and rebuild the rig (new configuration, lost devices)
        self.connected = False  # connected and warm
        self._trigger_task: asyncio.Task[None] | None = None

    def devices_from_config(self) -> None:
        """Every configured device, not connected yet."""
        cfg = self.svc.cfg
        devs = {f"camera:{n}": DeviceStatus("camera", n, c.type) for n, c in cfg.cameras.items()}
        devs["projector"] = DeviceStatus("projector", "projector", cfg.projector.type)
        devs["trigger"] = DeviceStatus("trigger", "trigger", cfg.trigger.type)
        self.svc.board.devices = devs

    @property
    def ready(self) -> bool:
        """True when the rig is connected and current (no rebuild pending)."""
        return self.connected and self.svc.scanner is not None and not self.changed.is_set()

    def idle_state(self) -> State:
        """``idle`` when every device is fine, else ``fault``."""
        return State.IDLE if all(d.ok for d in self.svc.board.devices.values()) else State.FAULT

    def on_scan_phase(self, phase: ScanPhase) -> None:
        """The scanner's phases (on the event loop): once every camera has its frames, the scan is
        ``processing``."""
        b = self.svc.board
        if phase.value == "captured" and b.state == State.SCANNING:
            b.set_state(State.PROCESSING, b.detail)

    async def connect(self) -> None:
        """Build and open the rig, open the trigger, warm the kernels (under the scan lock)."""
        svc = self.svc
        loop = asyncio.get_running_loop()
        cfg = svc.cfg
        svc.board.set_state(State.STARTING, "connecting hardware", Phase.CONNECT)
        rig, scanner = await loop.run_in_executor(None, svc._make_scanner, cfg)
        svc.rig = rig
        svc.board.sequence = scanner.sequence.describe()
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
            svc.board.devices[f"camera:{n}"] = DeviceStatus("camera", n, cfg.cameras[n].type, True, detail)
        svc.board.devices["projector"] = DeviceStatus("projector", "projector", cfg.projector.type, True,
                                                      f"sequence loaded: {scanner.sequence.describe()}")
        svc.scanner = scanner
        await self._open_trigger()
        svc.board.set_state(State.STARTING, "warming kernels", Phase.WARM)
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
        b = self.svc.board
        dev = b.devices.get("trigger")
        if dev is None:
            return
        ok = getattr(state, "value", str(state)) == "ready"
        if ok != dev.ok:
            if not ok:
                b.error("hardware", f"trigger {dev.backend}: {reason}")
            dev.ok, dev.detail = ok, f"{getattr(state, 'value', state)}: {reason}"
            if not b.busy and b.state in (State.IDLE, State.FAULT) and self.svc.scanner:
                b.set_state(self.idle_state(), "ready" if ok else f"trigger: {reason}")

    async def _open_trigger(self) -> None:
        svc = self.svc
        if svc.rig is None:
            return
        trig = svc.rig.trigger
        kind = svc.cfg.trigger.type
        if hasattr(trig, "on_state"):
            trig.on_state = self._trigger_link
        svc.publisher.reset_lamps()
        try:
            await trig.open()
        except (ApplianceError, OSError) as exc:
            svc.board.devices["trigger"] = DeviceStatus("trigger", trig.name, kind, False, str(exc))
            svc.board.error("hardware", f"trigger {kind}: {exc}")
        else:
            detail = trig.status() or "open"
            svc.board.devices["trigger"] = DeviceStatus("trigger", trig.name, kind, True, detail)
        self._trigger_task = svc.spawn(self._trigger_loop(trig), "trigger")

    async def close(self) -> None:
        """Stop the trigger loop, close the trigger and the rig."""
        svc = self.svc
        self.connected = False
        if self._trigger_task is not None:
            self._trigger_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._trigger_task
            self._trigger_task = None
        if svc.rig is not None:
            with contextlib.suppress(Exception):
                await svc.rig.trigger.close()
        if svc.scanner is not None:
            try:
                await svc.scanner.close()
            except Exception as exc:
                log.warning("closing the rig: %s", exc)
        svc.scanner = None

    async def loop(self) -> None:
        """Connect, retry with backoff on failure, rebuild on :attr:`changed` (runs until cancelled)."""
        svc = self.svc
        delay = RETRY_FIRST_S
        failures = 0
        while True:
            self.devices_from_config()
            try:
                async with svc.scan_lock:
                    await self.connect()
            except FatalError as exc:
                await self.close()
                svc.fail(str(exc))
                return
            except Exception as exc:  # any failure to connect is a fault to retry, never the end
                await self.close()
                failures += 1
                if not isinstance(exc, (ApplianceError, OSError)):
                    log.exception("hardware: unexpected error")
                for d in svc.board.devices.values():
                    if not d.ok and d.detail == "not connected":
                        d.detail = "not connected (see last error)"
                if failures == 1:
                    log.error("hardware: %s; retrying with backoff", exc)
                svc.board.error("hardware", str(exc))
                svc.jobs.drop_queued(f"scan not started: hardware: {exc}")
                svc.board.set_state(State.FAULT, f"hardware: {exc}; retry in {delay:.0f} s", Phase.CONNECT)
                svc.send_ready()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self.changed.wait(), delay)
                self.changed.clear()
                delay = min(delay * 2, svc.cfg.service.retry_max_s)
                continue
            if failures:
                log.info("hardware recovered after %d failed attempt(s)", failures)
            failures, delay = 0, RETRY_FIRST_S
            self.connected = True
            svc.board.set_state(self.idle_state(), "ready", Phase.READY)
            svc.send_ready()
            svc.jobs.ready.set()
            await self.changed.wait()
            self.connected = False  # not ready from here on, before the lock is taken
            self.changed.clear()
            async with svc.scan_lock:
                await self.close()

    async def _trigger_loop(self, trig: Any) -> None:
        svc = self.svc
        delay = RETRY_FIRST_S
        key = "trigger"
        while True:
            try:
                event = await trig.next_event()
            except (ApplianceError, OSError) as exc:
                dev = svc.board.devices[key]
                if dev.ok:
                    log.error("trigger %s failed: %s; retrying with backoff", trig.name, exc)
                    svc.board.error("hardware", f"trigger {trig.name}: {exc}")
                dev.ok, dev.detail = False, str(exc)
                if not svc.board.busy:
                    svc.board.set_state(State.FAULT, f"trigger: {exc}")
                await asyncio.sleep(delay)
                delay = min(delay * 2, svc.cfg.service.retry_max_s)
                with contextlib.suppress(ApplianceError, OSError):
                    await trig.close()
                try:
                    await trig.open()
                except (ApplianceError, OSError) as exc2:
                    dev.detail = str(exc2)
                    continue
                log.info("trigger %s recovered", trig.name)
                dev.ok, dev.detail, delay = True, "open", RETRY_FIRST_S
                if not svc.board.busy:
                    svc.board.set_state(self.idle_state(), "ready")
                continue
            svc.request_scan(event)
