"""The control socket: a unix stream socket speaking JSON lines.

Each request is one JSON object on one line, ``{"cmd": "status"}``; each reply is one JSON object on one line
with ``"ok": true|false``. Commands: ``status``, ``trigger`` (``"wait": true`` replies when the scan is done),
``tune`` (``"time_budget_ms"``, ``"apply"``: ``scan3d tune`` on the service's rig), ``reload``, ``ping``,
``last_error``. A connection may send several requests; a malformed line gets an error reply.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import socket
import stat
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from appliance.config.loader import MAX_SOCKET_PATH
from appliance.errors import ApplianceError

log = logging.getLogger(__name__)

Handler = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]
MAX_LINE = 64 * 1024
SOCKET_MODE = 0o660
REPLY_GRACE_S = 2.0  # at close, requests in progress get this long to send their reply
ALIVE_TIMEOUT_S = 0.5  # a socket file that accepts no connection within this is stale


def finite_json(value: Any) -> Any:
    """``value`` with every non-finite float (NaN: no measurement yet; inf) as None, through dicts, lists and
    tuples: what the service's faces print or send is JSON any parser reads (``NaN`` is Python's extension,
    which jq, browsers' ``JSON.parse`` and strict parsers refuse)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    return value


def dumps_json(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`finite_json` (``value``), refusing anything else that is not JSON."""
    return json.dumps(finite_json(value), allow_nan=False, **kwargs)


class ControlServer:
    """Serves the control socket at ``path`` with ``handler(request) -> reply``.

    Parameters
    ----------
    path : Path
        Socket path; a stale socket there is replaced, any other file is an error.
    handler : callable
        Coroutine function from a request dict to a reply dict (``ok`` is added when missing).
    """

    def __init__(self, path: Path, handler: Handler) -> None:
        self.path = Path(path)
        self.handler = handler
        self._server: asyncio.Server | None = None
        self._clients: set[asyncio.Task[Any]] = set()
        self._busy: set[asyncio.Task[Any]] = set()  # connections with a request in progress

    async def start(self) -> None:
        """Bind and listen.

        Raises
        ------
        ApplianceError
            When the path is taken by a non-socket file or by a live service.
        """
        p = self.path
        if len(os.fsencode(str(p))) > MAX_SOCKET_PATH:  # bind would fail with a bare OSError
            raise ApplianceError(f"control socket {p}: {len(os.fsencode(str(p)))} bytes is longer than a unix socket "
                                 f"path may be ({MAX_SOCKET_PATH}); set service.control_socket (or --control-socket) "
                                 "to a shorter path such as /run/scan3d/control.sock")
        p.parent.mkdir(parents=True, exist_ok=True)
        if p.exists() or p.is_symlink():
            if not stat.S_ISSOCK(p.lstat().st_mode):
                raise ApplianceError(f"control socket {p}: a file that is not a socket is there; remove it "
                                     "or set service.control_socket elsewhere")
            if await _socket_alive(p):
                raise ApplianceError(f"control socket {p}: another scan3d service answers there; stop it "
                                     "(systemctl stop scan3d) or use --control-socket")
            p.unlink()
        self._server = await asyncio.start_unix_server(self._client, path=str(p), limit=MAX_LINE)
        os.chmod(p, SOCKET_MODE)
        log.info("control socket at %s", p)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._clients.add(task)
        try:
            while True:
                try:
                    line = await reader.readline()
                except (ValueError, asyncio.LimitOverrunError):
                    await _reply(writer, {"ok": False, "error": f"request longer than {MAX_LINE} bytes"})
                    break
                if not line:
                    break
                if not line.strip():
                    continue
                if task is not None:
                    self._busy.add(task)
                reply = await self._dispatch(line)
                await _reply(writer, reply)
                if task is not None:
                    self._busy.discard(task)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:  # the service is stopping: a request in progress gets a reply
            if task is not None and task in self._busy:
                with contextlib.suppress(ConnectionError, OSError, RuntimeError):
                    writer.write(json.dumps({"ok": False, "error": "the service is stopping"}).encode() + b"\n")
            # and end normally: a cancelled connection task makes asyncio log a CancelledError traceback
        finally:
            if task is not None:
                self._clients.discard(task)
                self._busy.discard(task)
            writer.close()
            with contextlib.suppress(ConnectionError, OSError, asyncio.CancelledError):
                await writer.wait_closed()

    async def _dispatch(self, line: bytes) -> dict[str, Any]:
        try:
            request = json.loads(line)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            return {"ok": False, "error": f"not a JSON line: {exc}"}
        except RecursionError:
            return {"ok": False, "error": "not a JSON request: nested too deeply; send one flat JSON object"}
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            return {"ok": False, "error": 'a request is a JSON object with a "cmd" string'}
        try:
            reply = await self.handler(request)
        except ApplianceError as exc:
            return {"ok": False, "error": str(exc)}
        except Exception as exc:  # a handler bug must not kill the socket
            log.exception("control request %r failed", request)
            return {"ok": False, "error": f"internal error: {exc!r}"}
        reply.setdefault("ok", True)
        return reply

    async def close(self) -> None:
        """Stop listening, let requests in progress reply (up to :data:`REPLY_GRACE_S`), end the connections,
        remove the socket file."""
        if self._server is not None:
            self._server.close()
            busy = set(self._busy)
            if busy:
                await asyncio.wait(busy, timeout=REPLY_GRACE_S)
            for t in list(self._clients):
                t.cancel()
            if self._clients:
                await asyncio.gather(*self._clients, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None
            with contextlib.suppress(OSError):
                if stat.S_ISSOCK(self.path.lstat().st_mode):
                    self.path.unlink()


async def _reply(writer: asyncio.StreamWriter, reply: dict[str, Any]) -> None:
    writer.write(json.dumps(reply, default=str).encode() + b"\n")
    await writer.drain()


async def _socket_alive(path: Path) -> bool:
    try:
        async with asyncio.timeout(ALIVE_TIMEOUT_S):
            _, writer = await asyncio.open_unix_connection(str(path))
    except (OSError, TimeoutError):
        return False
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return True


MAX_REPLY = 8 * 1024 * 1024
"""Longest reply a client reads (bytes)."""


def request(path: Path, req: dict[str, Any], timeout_s: float = 10.0) -> dict[str, Any]:
    """Send one request to the control socket at ``path`` and return the reply (blocking; for clients).

    Raises
    ------
    ApplianceError
        When nothing listens there or the reply is not JSON.
    """
    deadline = time.monotonic() + timeout_s
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        try:
            s.connect(str(path))
        except OSError as exc:
            raise ApplianceError(
                f"control socket {path}: {exc.strerror or exc}; is the service running? "
                "(systemctl status scan3d, or scan3d run)"
            ) from exc
        try:
            s.sendall(json.dumps(req).encode() + b"\n")
        except OSError as exc:
            raise ApplianceError(f"control socket {path}: the request could not be sent ({exc.strerror or exc}); "
                                 "is the service running?") from exc
        buf = b""
        while not buf.endswith(b"\n"):
            left = deadline - time.monotonic()  # one deadline for the whole reply, however it trickles in
            if left <= 0:
                raise ApplianceError(f"control socket {path}: no complete reply within {timeout_s:g} s; is "
                                     "another program listening there?")
            s.settimeout(left)
            try:
                chunk = s.recv(65536)
            except TimeoutError as exc:
                raise ApplianceError(f"control socket {path}: no complete reply within {timeout_s:g} s"
                                     + ("" if not buf else "; is another program listening there?")) from exc
            except OSError as exc:
                raise ApplianceError(f"control socket {path}: the reply broke off ({exc.strerror or exc})") from exc
            if not chunk:
                break
            buf += chunk
            if len(buf) > MAX_REPLY:
                raise ApplianceError(f"control socket {path}: the reply is longer than {MAX_REPLY // 1024} KiB; "
                                     "is another program listening there?")
    finally:
        s.close()
    try:
        reply = json.loads(buf)
    except (ValueError, RecursionError) as exc:  # not JSON, not UTF-8, or nested beyond the parser's depth
        raise ApplianceError(f"control socket {path}: the reply is not JSON ({buf[:80]!r}); is another program "
                             "listening there?") from exc
    if not isinstance(reply, dict):
        raise ApplianceError(f"control socket {path}: unexpected reply {reply!r}")
    return reply
