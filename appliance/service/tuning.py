"""``scan3d tune`` in the service: the capture assistant's probe on the service's own rig.

A tune takes the scan lock (so no scan runs beside it), shows ``tuning`` on the status board (a trigger meanwhile
is refused with one line: a scan queued behind a tune would use the settings it is about to replace), probes the
rig (:func:`appliance.procedures.tune.tune_rig`: white and black at a few exposures, the choice in a thread) and
then has the rig rebuilt, since the probe left the projector and the cameras' exposure changed. Applying a
choice writes ``sequence.exposures_us`` into the service's configuration file (validated, atomic) and reloads it
as an edit over SSH would be reloaded.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from typing import Any

from appliance.errors import ApplianceError, ScanError
from appliance.service.parts import RigView, TuneHost, Worker
from appliance.service.state import Phase, State, StatusBoard

log = logging.getLogger(__name__)

TUNE_TIMEOUT_S = 120.0
"""A probe that takes longer than this fails (a camera that never delivers)."""


class TuneRefused(ApplianceError):
    """A tune (or applying one) cannot run now: busy, not ready, or nothing to apply."""


class Tuner:
    """Runs ``scan3d tune`` on the service's rig and applies its choice.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (this part writes the ``tuning`` state).
    host : TuneHost
        The running configuration, its file and the reload.
    rig : RigView
        The rig part: ready or not, its scanner (and through it the open devices), the rebuild.
    worker : Worker
        The scan worker: whether a scan is queued or running.
    scan_lock : asyncio.Lock
        Held by a scan, a tune and every change of the rig.
    """

    def __init__(self, board: StatusBoard, host: TuneHost, rig: RigView, worker: Worker,
                 scan_lock: asyncio.Lock) -> None:
        self.board = board
        self.host = host
        self.rig = rig
        self.worker = worker
        self.scan_lock = scan_lock
        self.last: dict[str, Any] = {}  # the last tune's reply (its choice is what "apply" writes)

    @property
    def tuning(self) -> bool:
        """True while a tune probes the rig."""
        return self.board.state == State.TUNING

    async def tune(self, time_budget_ms: float, apply: bool = False) -> dict[str, Any]:
        """Probe the rig, choose the exposures for ``time_budget_ms`` and, with ``apply``, write them.

        Returns
        -------
        dict
            ``choice`` (the :class:`~appliance.procedures.tune.TuneChoice` fields), ``lines`` (the plain-words
            report of ``scan3d tune``), ``time_budget_ms``, ``probe_ms`` and, with ``apply``, ``applied``.

        Raises
        ------
        TuneRefused
            When a scan or another tune runs, or the rig is not ready.
        ConfigError
            When the time budget is not a positive number.
        """
        from appliance.procedures.tune import check_time_budget, tune_rig

        check_time_budget(time_budget_ms)
        b = self.board
        scanner = self.rig.scanner
        if self.tuning:
            raise TuneRefused("scan3d tune: a tune is already running; wait for its result")
        if b.busy or self.worker.busy or self.scan_lock.locked():  # a scan queued, starting or running
            raise TuneRefused(f"scan3d tune: the service is busy ({b.state}: {b.detail}); tune when it is idle")
        if not self.rig.ready or scanner is None:
            raise TuneRefused(f"scan3d tune: the rig is not ready ({b.state}: {b.detail}); tune when it is idle")
        cfg = self.host.cfg
        async with self.scan_lock:  # free a moment ago: taken at once, before any trigger can start a scan
            b.set_state(State.TUNING, f"scan3d tune: probing the scene (budget {time_budget_ms:g} ms)")
            t0 = time.perf_counter()
            try:
                proj = scanner.calibration.devices["projector"]
                async with asyncio.timeout(TUNE_TIMEOUT_S):
                    choice = await tune_rig(cfg, scanner.rig, (proj.width, proj.height), time_budget_ms)
            except TimeoutError as exc:
                raise ScanError(f"scan3d tune: the probe took longer than {TUNE_TIMEOUT_S:g} s; check the "
                                "cameras (scan3d status)") from exc
            finally:
                # the probe left its own frames in the projector and the cameras at its last exposure
                if self.tuning:  # not when the service is stopping meanwhile
                    b.set_state(State.STARTING, "reconnecting after scan3d tune", Phase.CONNECT)
                self.rig.reconnect()
        reply: dict[str, Any] = {"choice": dataclasses.asdict(choice), "lines": choice.lines(time_budget_ms),
                                 "time_budget_ms": time_budget_ms,
                                 "probe_ms": round((time.perf_counter() - t0) * 1e3, 1)}
        log.info("scan3d tune: %s", reply["lines"][1])
        self.last = reply
        if apply:
            reply["applied"] = await self.apply(list(choice.exposures_us))
        return reply

    async def apply(self, exposures_us: list[int] | None = None) -> dict[str, Any]:
        """Write the last tune's exposures into the configuration file and reload it.

        Parameters
        ----------
        exposures_us : list of int, optional
            What the caller saw and approves; must equal the last tune's choice (another tune may have run
            since). None: the last choice.

        Returns
        -------
        dict
            ``path``, ``exposures_us``, ``intensities`` (empty: every pass at full intensity), ``edge_blur_px``
            (the cameras' blur written, None: left as it was) and the reload's ``reloaded`` (bool) and ``error``.

        Raises
        ------
        TuneRefused
            When no tune has run, or ``exposures_us`` is not its choice.
        ConfigError
            When the file with the new exposures does not validate (it is left as it was).
        """
        from appliance.procedures.tune import apply_choice

        chosen = [int(e) for e in self.last.get("choice", {}).get("exposures_us", [])]
        if not chosen:
            raise TuneRefused("scan3d tune: nothing to apply; run a tune first")
        if exposures_us is not None and [int(e) for e in exposures_us] != chosen:
            raise TuneRefused(f"scan3d tune: {list(exposures_us)} is not the last tune's choice ({chosen}); "
                              "look at its result again and apply that")
        levels = [float(i) for i in self.last["choice"].get("intensities", [])]
        blur = self.last["choice"].get("edge_blur_px")
        edge = float(blur) if isinstance(blur, (int, float)) else None
        path = self.host.config_path
        # validated, then written atomically
        await asyncio.to_thread(apply_choice, path, tuple(chosen), tuple(levels), edge)
        log.info("scan3d tune: sequence.exposures_us = %s%s%s written to %s", chosen,
                 f", sequence.intensities = {levels}" if levels else "",
                 f", reconstruction.edge_blur_px = {edge:g}" if edge is not None else "", path)
        ok, error = await self.host.reload("scan3d tune --apply")
        return {"path": str(path), "exposures_us": chosen, "intensities": levels, "edge_blur_px": edge,
                "reloaded": ok, "error": error}

