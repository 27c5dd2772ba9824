"""The HTTP face (aiohttp): a small JSON API, server-sent events and the status page.

``service.http.listen`` (``HOST:PORT``; unset = off). Routes:

- ``GET /`` the status page (``appliance/service/static``: our own HTML, JS and CSS, nothing from a CDN);
- ``GET /api/status`` the same JSON as ``scan3d status --json``;
- ``POST /api/trigger[?wait=1]`` a scan under the busy policy; needs ``Authorization: Bearer <token>``
  (the content of ``service.http.token_file``); 401 otherwise (logged, the token never is);
- ``POST /api/tune[?time_budget_ms=MS]`` ``scan3d tune`` on the rig (busy meanwhile: triggers are refused);
  ``POST /api/tune/apply`` (body ``{"exposures_us": [...]}``, the last tune's choice) writes it into the
  configuration file and reloads it; both need the token, 409 when refused (busy, nothing to apply);
- ``GET /api/scans?limit=N`` the last scans; ``GET /api/scans/<id>/{preview.png,cloud.ply,sidecar.json}`` the
  files of a known scan id only, ``.../cloud.bin`` a downsampled cloud (float32 x y z, mm) for the page;
- ``GET /api/events`` server-sent events (``state`` and ``scan``);
- ``GET /api/config`` the running configuration and the last rejected edit.

The status, the ``state`` events and the configuration carry the board's ``revision`` (one more at every
change): a client holding copies that came by different connections keeps the newest.

Requests are bounded in size (``max_request_kb``) and rate (``rate_per_s`` per client address).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import time
from collections.abc import Awaitable, Callable
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import web

from appliance.config.schema import HttpConfig
from appliance.errors import ApplianceError, ConfigError
from appliance.service.control import dumps_json
from appliance.service.faces import ServiceView

log = logging.getLogger(__name__)

# Module-level so tests can shorten them.
SSE_HEARTBEAT_S = 15.0
SCANS_LIMIT_MAX = 100
STATIC_FILES = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css"}
FILE_ROUTES = {"preview.png": ("preview", "image/png"), "cloud.ply": ("cloud", "application/octet-stream"),
               "sidecar.json": ("sidecar", "application/json")}
CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; connect-src 'self'; "
       "frame-ancestors 'none'; base-uri 'none'; form-action 'none'")

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def _json_response(data: Any, **kwargs: Any) -> web.Response:
    """A JSON response that any client parses (non-finite numbers as null: :func:`dumps_json`)."""
    return web.json_response(data, dumps=dumps_json, **kwargs)


def parse_listen(listen: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` too) as (host, port).

    Raises
    ------
    ConfigError
        When the port is out of range.
    """
    host, _, port_text = listen.rpartition(":")
    port = int(port_text)
    if not 0 <= port < 65536:  # 0: any free port (tests)
        raise ConfigError(f"service.http.listen = {listen!r}: port {port} is out of range; use 1..65535 "
                          "(0: any free port)")
    return host.strip("[]"), port


def read_secret(path: Path | None, what: str) -> str | None:
    """The stripped content of a secret file (None when unset).

    Raises
    ------
    ConfigError
        When the file cannot be read or is empty.
    """
    if path is None:
        return None
    try:
        text = Path(path).read_text().strip()
    except OSError as exc:
        raise ConfigError(f"{what} = {str(path)!r}: cannot read it ({exc.strerror}); create it (chmod 600) or "
                          "unset the key") from exc
    if not text:
        raise ConfigError(f"{what} = {str(path)!r}: the file is empty; put the secret in it")
    return text


class _RateLimiter:
    """A token bucket per client address (``rate`` per second, bursts of ``2 * rate``)."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.burst = 2.0 * rate
        self._buckets: dict[str, tuple[float, float]] = {}

    def allow(self, key: str) -> bool:
        now = time.monotonic()
        tokens, last = self._buckets.get(key, (self.burst, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate)
        if len(self._buckets) > 4096:  # many addresses: forget the idle ones
            self._buckets = {k: v for k, v in self._buckets.items() if now - v[1] < 60}
        if tokens < 1.0:
            self._buckets[key] = (tokens, now)
            return False
        self._buckets[key] = (tokens - 1.0, now)
        return True


class HttpFace:
    """Serves the API and the status page.

    Parameters
    ----------
    cfg : HttpConfig
        ``listen``, ``token_file`` and the request bounds.
    view : ServiceView
        The service as the faces see it.
    """

    def __init__(self, cfg: HttpConfig, view: ServiceView) -> None:
        if cfg.listen is None:
            raise ConfigError("service.http.listen is not set; the HTTP face is off")
        self.cfg = cfg
        self.view = view
        self.host, self.port = parse_listen(cfg.listen)
        self._token: bytes | None = None
        self._static: dict[str, bytes] = {}
        self._limiter = _RateLimiter(cfg.rate_per_s)
        self._runner: web.AppRunner | None = None
        self._sse: set[asyncio.Queue[dict[str, Any]]] = set()
        self._closing = asyncio.Event()
        self.unauthorized = 0

    @property
    def url(self) -> str:
        """The base URL (with the bound port)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    def _load_files(self) -> None:  # blocking: in a thread
        token = read_secret(self.cfg.token_file, "service.http.token_file")
        self._token = token.encode() if token is not None else None
        pkg = resources.files("appliance.service") / "static"
        self._static = {name: (pkg / name).read_bytes() for name in STATIC_FILES}

    async def start(self) -> None:
        """Bind ``listen`` and serve.

        Raises
        ------
        ConfigError
            When the token file is unreadable.
        OSError
            When the address cannot be bound.
        """
        await asyncio.to_thread(self._load_files)
        if self._token is None:
            log.warning("HTTP: service.http.token_file is unset: every write (POST /api/trigger) is refused")
        app = web.Application(client_max_size=self.cfg.max_request_kb * 1024,
                              middlewares=[self._guard])
        app.router.add_get("/", self._page)
        app.router.add_get("/static/{name}", self._static_file)
        app.router.add_get("/api/status", self._status)
        app.router.add_post("/api/trigger", self._trigger)
        app.router.add_post("/api/tune", self._tune)
        app.router.add_post("/api/tune/apply", self._tune_apply)
        app.router.add_get("/api/scans", self._scans)
        app.router.add_get("/api/scans/{scan_id}/{file}", self._scan_file)
        app.router.add_get("/api/events", self._events)
        app.router.add_get("/api/config", self._config)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=1.0)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port, reuse_address=True)
        try:
            await site.start()
        except OSError as exc:
            await self._runner.cleanup()
            self._runner = None
            raise OSError(exc.errno, f"HTTP: cannot listen on {self.cfg.listen} ({exc.strerror}); is another "
                          "service on that port? change service.http.listen (under systemd, a port must also be "
                          "in scan3d.service's SocketBindAllow=)") from exc
        server = getattr(site, "_server", None)
        sockets = getattr(server, "sockets", None) or []
        if sockets:
            self.port = int(sockets[0].getsockname()[1])
        log.info("HTTP: API and status page on %s", self.url)

    async def close(self) -> None:
        """Stop serving (open event streams are ended)."""
        self._closing.set()
        for q in list(self._sse):  # wake the event streams so they end now
            with contextlib.suppress(asyncio.QueueEmpty):
                q.get_nowait()
            q.put_nowait({"type": "closing"})
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    # --- middleware --------------------------------------------------------------------------------

    @web.middleware
    async def _guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        peer = request.remote or "?"
        if not self._limiter.allow(peer):
            log.warning("HTTP: %s %s from %s: 429 (over service.http.rate_per_s = %g)", request.method,
                        request.path, peer, self.cfg.rate_per_s)
            return _json_response({"ok": False, "error": "too many requests; slow down"}, status=429)
        limit = self.cfg.max_request_kb * 1024
        if request.body_exists and (request.content_length or 0) > limit:
            log.warning("HTTP: %s %s from %s: 413 (body of %d bytes, over service.http.max_request_kb = %d)",
                        request.method, request.path, peer, request.content_length, self.cfg.max_request_kb)
            return _json_response({"ok": False, "error": f"request body over {self.cfg.max_request_kb} KiB"},
                                 status=413)
        try:
            if request.body_exists:
                await request.read()  # bounded by client_max_size (a chunked body too)
            resp = await handler(request)
        except web.HTTPException as exc:
            if exc.status == 413:
                log.warning("HTTP: %s %s from %s: 413 (body over %d KiB)", request.method, request.path, peer,
                            self.cfg.max_request_kb)
            raise
        if not resp.prepared:
            resp.headers["Content-Security-Policy"] = CSP
            resp.headers["X-Content-Type-Options"] = "nosniff"
            resp.headers["Referrer-Policy"] = "no-referrer"
            resp.headers.setdefault("Cache-Control", "no-store")
        return resp

    def _authorized(self, request: web.Request) -> bool:
        if self._token is None:
            return False
        given = request.headers.get("Authorization", "")
        scheme, _, value = given.partition(" ")
        if scheme.lower() != "bearer":
            return False
        return hmac.compare_digest(value.strip().encode(), self._token)

    # --- routes ------------------------------------------------------------------------------------

    async def _page(self, request: web.Request) -> web.StreamResponse:
        return web.Response(body=self._static["index.html"], content_type="text/html", charset="utf-8")

    async def _static_file(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        if name not in STATIC_FILES or name == "index.html":
            raise web.HTTPNotFound()
        return web.Response(body=self._static[name], content_type=STATIC_FILES[name], charset="utf-8")

    async def _status(self, request: web.Request) -> web.StreamResponse:
        st = await self.view.status()
        return _json_response(st)

    def _unauthorized(self, request: web.Request) -> web.Response | None:
        """The 401 reply for a write without the right token (logged; the token never is); None when allowed."""
        if self._authorized(request):
            return None
        self.unauthorized += 1
        why = ("no token is configured (service.http.token_file)" if self._token is None
               else "missing or wrong bearer token")
        log.warning("HTTP: POST %s from %s refused: 401 (%s)", request.path, request.remote or "?", why)
        return _json_response({"ok": False, "error": f"unauthorized: {why}"}, status=401,
                             headers={"WWW-Authenticate": 'Bearer realm="scan3d"'})

    async def _tune(self, request: web.Request) -> web.StreamResponse:
        refused = self._unauthorized(request)
        if refused is not None:
            return refused
        text = request.query.get("time_budget_ms", "2000")
        try:
            budget = float(text)
        except ValueError:
            return _json_response({"ok": False, "error": f"time_budget_ms = {text!r}: must be a number of ms"},
                                 status=400)
        log.info("HTTP: tune from %s (budget %g ms)", request.remote or "?", budget)
        reply = await self.view.tune(budget)
        return _json_response(reply, status=_status_of(reply))

    async def _tune_apply(self, request: web.Request) -> web.StreamResponse:
        refused = self._unauthorized(request)
        if refused is not None:
            return refused
        exposures: list[int] | None = None
        if request.body_exists:
            try:
                body = json.loads(await request.read() or b"{}")
                given = body.get("exposures_us") if isinstance(body, dict) else None
                if given is not None:
                    exposures = [int(e) for e in given]
            except (ValueError, TypeError):
                return _json_response({"ok": False, "error": 'the body is {"exposures_us": [whole numbers of '
                                      'µs]}, the last tune\'s choice'}, status=400)
        log.info("HTTP: apply the tune's choice from %s", request.remote or "?")
        reply = await self.view.tune_apply(exposures)
        return _json_response(reply, status=_status_of(reply))

    async def _trigger(self, request: web.Request) -> web.StreamResponse:
        peer = request.remote or "?"
        refused = self._unauthorized(request)
        if refused is not None:
            return refused
        wait = request.query.get("wait", "") in ("1", "true", "yes")
        log.info("HTTP: trigger from %s%s", peer, " (waiting)" if wait else "")
        reply = await self.view.trigger(wait, "http")
        status = 200 if reply.get("ok") else 409 if str(reply.get("result", "")).startswith("refused") else 500
        return _json_response(reply, status=status)

    async def _scans(self, request: web.Request) -> web.StreamResponse:
        try:
            limit = int(request.query.get("limit", "10"))
        except ValueError:
            return _json_response({"ok": False, "error": "limit must be a whole number"}, status=400)
        limit = max(1, min(limit, SCANS_LIMIT_MAX))
        return _json_response({"ok": True, "scans": await self.view.scans(limit)})

    async def _scan_file(self, request: web.Request) -> web.StreamResponse:
        scan_id, name = request.match_info["scan_id"], request.match_info["file"]
        if name == "cloud.bin":
            data = await self.view.cloud_sample(scan_id)
            if data is None:
                raise web.HTTPNotFound(text=f"no cloud for scan {scan_id!r}")
            return web.Response(body=data, content_type="application/octet-stream",
                                headers={"X-Points": str(len(data) // 12)})
        if name not in FILE_ROUTES:
            raise web.HTTPNotFound(text=f"no file {name!r}; use one of {', '.join([*FILE_ROUTES, 'cloud.bin'])}")
        kind, ctype = FILE_ROUTES[name]
        path = await self.view.scan_file(scan_id, kind)
        if path is None:
            raise web.HTTPNotFound(text=f"no {name} for scan {scan_id!r} (only the last scans are served)")
        return web.FileResponse(path, headers={"Content-Type": ctype, "Cache-Control": "max-age=3600"})

    async def _config(self, request: web.Request) -> web.StreamResponse:
        return _json_response(self.view.configuration())

    async def _events(self, request: web.Request) -> web.StreamResponse:
        if len(self._sse) >= self.cfg.max_event_clients:
            return _json_response({"ok": False, "error": "too many event streams open "
                                  f"(service.http.max_event_clients = {self.cfg.max_event_clients})"},
                                 status=503)
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store",
                                           "X-Accel-Buffering": "no"})
        resp.headers["Content-Security-Policy"] = CSP
        await resp.prepare(request)
        queue = self.view.subscribe()
        self._sse.add(queue)
        try:
            await resp.write(_sse(self.view.state_event()))
            while not self._closing.is_set():
                try:
                    event = await asyncio.wait_for(queue.get(), SSE_HEARTBEAT_S)
                except TimeoutError:
                    await resp.write(b": keep-alive\n\n")
                    continue
                if event.get("type") == "closing":
                    break
                await resp.write(_sse(event))
        except (ConnectionResetError, ApplianceError, RuntimeError):
            pass  # the client went away
        finally:
            self.view.unsubscribe(queue)
            self._sse.discard(queue)
        with contextlib.suppress(ConnectionResetError, RuntimeError):
            await resp.write_eof()
        return resp


def _status_of(reply: dict[str, Any]) -> int:
    """200 when done; 409 refused (busy, nothing to apply), 400 an invalid value or file, 500 failed."""
    if reply.get("ok"):
        return 200
    return {"refused": 409, "invalid": 400}.get(str(reply.get("result", "")), 500)


def _sse(event: dict[str, Any]) -> bytes:
    data = dumps_json(event, separators=(",", ":"), default=str)
    return f"event: {event.get('type', 'message')}\ndata: {data}\n\n".encode()
