"""What the control socket's commands do: ``status``, ``last_error``, ``reload``, ``trigger`` (``wait``)."""

from __future__ import annotations

import time
from dataclasses import asdict
from typing import Any

from appliance.errors import ApplianceError
from appliance.hardware.base import TriggerEvent
from appliance.service.parts import ControlHost
from appliance.service.state import StatusBoard

COMMANDS = ("status", "trigger", "reload", "ping", "last_error")


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
        return {"ok": False, "error": f"unknown command {cmd!r}; use {', '.join(COMMANDS[:-1])} or {COMMANDS[-1]}"}

    async def _reload(self) -> dict[str, Any]:
        ok, msg = await self.host.reload("control socket")
        return {"ok": ok, "error": msg} if not ok else {"ok": True}

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
