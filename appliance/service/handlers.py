"""What the control socket's commands do: ``status``, ``last_error``, ``reload``, ``trigger`` (``wait``),
``tune`` (``time_budget_ms``, ``apply``: ``scan3d tune`` on the service's rig)."""

from __future__ import annotations

import time
from dataclasses import asdict
from typing import Any

from appliance.errors import ApplianceError
from appliance.hardware.base import TriggerEvent
from appliance.service.parts import ControlHost
from appliance.service.state import StatusBoard

COMMANDS = ("status", "trigger", "tune", "reload", "ping", "last_error")
DEFAULT_TIME_BUDGET_MS = 2000.0


class ControlHandlers:
    """The control socket's request handler for one service.

    Parameters
    ----------
    board : StatusBoard
        The service's status board (read only).
    host : ControlHost
        The status, the trigger and the reload the commands run.
    """

    def __init__(self, board: StatusBoard, host: ControlHost) -> None:
        self.board = board
        self.host = host

    async def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        """Answer one request (a dict with a ``cmd`` string)."""
        cmd = req["cmd"]
        if cmd == "status":
            return {"ok": True, "status": await self.host.status_async()}
        if cmd == "ping":  # the health check's probe: the socket and the loop answer
            return {"ok": True, "pong": True}
        if cmd == "last_error":
            err = self.board.last_error
            return {"ok": True, "last_error": asdict(err) if err is not None else None}
        if cmd == "reload":
            return await self._reload()
        if cmd == "trigger":
            return await self._trigger(req)
        if cmd == "tune":
            return await self._tune(req)
        return {"ok": False, "error": f"unknown command {cmd!r}; use {', '.join(COMMANDS[:-1])} or {COMMANDS[-1]}"}

    async def _reload(self) -> dict[str, Any]:
        ok, msg = await self.host.reload("control socket")
        return {"ok": ok, "error": msg} if not ok else {"ok": True}

    async def _tune(self, req: dict[str, Any]) -> dict[str, Any]:
        budget = req.get("time_budget_ms", DEFAULT_TIME_BUDGET_MS)
        if isinstance(budget, bool) or not isinstance(budget, (int, float)):
            return {"ok": False, "error": f"tune: time_budget_ms = {budget!r}: must be a number of ms (e.g. 2000)"}
        reply = await self.host.tune(float(budget), bool(req.get("apply", False)))
        applied = reply.get("applied")
        if isinstance(applied, dict) and not applied.get("reloaded"):
            return {"ok": False, "tune": reply, "error": f"tune: written to {applied.get('path')} but the reload "
                    f"failed: {applied.get('error')}"}
        return {"ok": True, "tune": reply}

    async def _trigger(self, req: dict[str, Any]) -> dict[str, Any]:
        ev = TriggerEvent("control", time.monotonic_ns(), str(req.get("detail", "")))
        outcome, job = self.host.request_scan(ev)
        if job is None:
            return {"ok": False, "result": outcome, "error": f"trigger {outcome}"}
        if not req.get("wait"):
            return {"ok": True, "result": outcome}
        try:
            rec = await job.done
        except ApplianceError as exc:
            return {"ok": False, "result": outcome, "error": str(exc)}
        return {"ok": rec.ok, "result": outcome, "scan": asdict(rec), **({"error": rec.error} if not rec.ok else {})}
