"""The OPC UA face (asyncua): a ``Scanner`` object a PLC or cell controller reads, and a ``Trigger`` method.

Namespace ``urn:scan3d:appliance``; under Objects, ``Scanner`` with the variables ``State`` (the service's
state), ``VisionState`` (the OPC 40100 top-level state it maps to), ``ScansDone``, ``LastScanId`` (the
40100 result id), ``LastResultFile``, ``LastPointCount``, ``LastError``, ``CalibrationHealth`` and the
method ``Trigger() -> ScanId`` (waits for the scan under the busy policy; a refused trigger answers
``BadInvalidState``, a failed scan ``BadInternalError``; ``LastError`` says why). See docs/line-integration.md.

Security: anonymous sessions read and subscribe only; ``Trigger`` needs the user ``service.opcua.username``
with the password in ``password_file`` (no user configured: no one can call it). The offered security
policies are ``security_policies``.

asyncua builds its standard address space in pure Python (seconds of CPU), so the server runs on its own
event loop in its own thread; it reaches the service only through :class:`ServiceView` on the service's
loop, and the service's loop never waits for it.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import hmac
import logging
import threading
from typing import Any
from urllib.parse import urlparse

from asyncua import Server, ua
from asyncua.crypto.permission_rules import PermissionRuleset, User, UserRole
from asyncua.server import standard_address_space

from appliance.config.schema import OpcUaConfig
from appliance.errors import ApplianceError, ConfigError
from appliance.service.control import dumps_json
from appliance.service.faces import Event, ServiceView
from appliance.service.http import read_secret

log = logging.getLogger(__name__)

NAMESPACE = "urn:scan3d:appliance"
START_TIMEOUT_S = 60.0
# OPC 40100-1 top-level states of a vision system, by our state (tuning: set-up, no job is accepted).
VISION_STATE = {"starting": "Preoperational", "idle": "Operational", "scanning": "Operational",
                "processing": "Operational", "writing": "Operational", "tuning": "Preoperational", "fault": "Error",
                "stopping": "Halted"}
_POLICY = {"None": ua.SecurityPolicyType.NoSecurity,
           "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
           "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt}
_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
_ADMIN_ONLY = {ua.NodeId(i) for i in (
    ua.ObjectIds.AddNodesRequest_Encoding_DefaultBinary, ua.ObjectIds.DeleteNodesRequest_Encoding_DefaultBinary,
    ua.ObjectIds.AddReferencesRequest_Encoding_DefaultBinary,
    ua.ObjectIds.DeleteReferencesRequest_Encoding_DefaultBinary,
    ua.ObjectIds.RegisterServerRequest_Encoding_DefaultBinary,
    ua.ObjectIds.RegisterServer2Request_Encoding_DefaultBinary)}


class _Rules(PermissionRuleset):  # type: ignore[misc]
    """Anonymous: everything but Write, Call and address-space edits; the configured user: Call too."""

    def check_validity(self, user: User | None, action_type_id: ua.NodeId, body: Any) -> bool:
        if action_type_id in _ADMIN_ONLY:
            return False
        if user is None or user.role == UserRole.Anonymous:
            return action_type_id not in (_CALL, _WRITE)
        return bool(user.role == UserRole.User)


class _Users:
    """Anonymous sessions, and the one configured user (password compared in constant time)."""

    def __init__(self, username: str | None, password: str | None) -> None:
        self.username = username
        self.password = password
        self.rejected = 0

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None and password is None:  # anonymous token (a certificate here is the channel's)
            return User(role=UserRole.Anonymous)
        if (self.username is not None and self.password is not None and username == self.username
                and hmac.compare_digest(str(password or "").encode(), self.password.encode())):
            return User(role=UserRole.User, name=username)
        self.rejected += 1
        log.warning("OPC UA: login as %r refused (unknown user or wrong password)", username)
        return None


def _health_text(health: Any) -> str:
    """``ok`` / ``drifting`` / ``bad`` / ``not measured`` (the sidecar's ``calibration_health.status``)."""
    if not health:
        return "not measured"
    if isinstance(health, dict) and isinstance(health.get("status"), str):
        return str(health["status"])
    return health if isinstance(health, str) else dumps_json(health, separators=(",", ":"))


class OpcUaFace:
    """Serves the Scanner object on ``service.opcua.endpoint`` from a thread of its own.

    Parameters
    ----------
    cfg : OpcUaConfig
        Endpoint, Trigger user, security policies, certificate.
    view : ServiceView
        The service as the faces see it.
    """

    def __init__(self, cfg: OpcUaConfig, view: ServiceView) -> None:
        self.cfg = cfg
        self.view = view
        url = urlparse(cfg.endpoint)
        if url.port is None or not 0 < url.port < 65536:
            raise ConfigError(f"service.opcua.endpoint = {cfg.endpoint!r}: no valid port; use e.g. "
                              "opc.tcp://0.0.0.0:4840/scan3d")
        self._service_loop: asyncio.AbstractEventLoop | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: Server | None = None
        self._vars: dict[str, Any] = {}
        self._ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._stop: asyncio.Event | None = None
        self._queue: asyncio.Queue[Event] | None = None
        self._follow: asyncio.Task[None] | None = None
        self._users: _Users | None = None

    # --- the service's loop ------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the server thread and wait (without blocking the loop) until it listens.

        Raises
        ------
        ApplianceError
            When the server cannot start (address in use, bad certificate, ...).
        """
        password = await asyncio.to_thread(read_secret, self.cfg.password_file, "service.opcua.password_file")
        self._users = _Users(self.cfg.username, password)
        self._service_loop = asyncio.get_running_loop()
        self._thread = threading.Thread(target=self._thread_main, name="scan3d-opcua", daemon=True)
        self._thread.start()
        try:
            await asyncio.wait_for(asyncio.wrap_future(self._ready), START_TIMEOUT_S)
        except BaseException:
            await self.close()
            raise
        self._queue = self.view.subscribe()
        self._follow = asyncio.get_running_loop().create_task(self._forward(), name="scan3d-opcua-follow")
        self._send(self.view.state_event())
        for scan in (await self.view.scans(1))[:1]:
            if scan.get("ok"):
                self._send({**scan, "type": "scan"})
        log.info("OPC UA: serving %s (namespace %s; Trigger %s)", self.cfg.endpoint, NAMESPACE,
                 f"for user {self.cfg.username!r}" if self.cfg.username else "disabled: no user configured")

    async def close(self) -> None:
        """Stop the server and its thread."""
        if self._follow is not None:
            self._follow.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._follow
            self._follow = None
        if self._queue is not None:
            self.view.unsubscribe(self._queue)
            self._queue = None
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 10.0)
            self._thread = None

    async def _forward(self) -> None:
        assert self._queue is not None
        while True:
            self._send(await self._queue.get())

    def _send(self, event: Event) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                asyncio.run_coroutine_threadsafe(self._apply(event), loop)

    # --- the server's own thread and loop ------------------------------------------------------------

    def _thread_main(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # reported to start(); the thread ends
            if not self._ready.done():
                self._ready.set_exception(exc if isinstance(exc, ApplianceError) else ApplianceError(
                    f"OPC UA server on {self.cfg.endpoint} did not start: {exc!r}"))
            else:
                log.error("OPC UA server stopped: %r", exc)

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        cfg = self.cfg
        server = Server(user_manager=self._users)
        iserver = server.iserver

        async def fill_in_a_thread(shelf_file: Any = None) -> None:
            # ~1 s of CPU building the standard address space: not on the event loop. Nothing else touches
            # this server until it starts.
            await asyncio.to_thread(standard_address_space.fill_address_space, iserver.node_mgt_service)

        iserver.load_standard_address_space = fill_in_a_thread
        await server.init()
        server.set_endpoint(cfg.endpoint)
        server.set_server_name(f"scan3d {self.view.serial}")
        await server.set_application_uri(f"{NAMESPACE}:{self.view.serial}")
        if cfg.certificate_file is not None and cfg.private_key_file is not None:
            await server.load_certificate(str(cfg.certificate_file))
            await server.load_private_key(str(cfg.private_key_file))
        server.set_security_policy([_POLICY[p] for p in cfg.security_policies], permission_ruleset=_Rules())
        tokens: list[Any] = [ua.AnonymousIdentityToken]
        if cfg.username is not None:
            tokens.append(ua.UserNameIdentityToken)
        server.set_identity_tokens(tokens)
        idx = await server.register_namespace(NAMESPACE)
        scanner = await server.nodes.objects.add_object(idx, "Scanner")
        specs: list[tuple[str, Any, ua.VariantType]] = [
            ("State", "starting", ua.VariantType.String), ("VisionState", "Preoperational", ua.VariantType.String),
            ("ScansDone", 0, ua.VariantType.UInt32), ("LastScanId", "", ua.VariantType.String),
            ("LastResultFile", "", ua.VariantType.String), ("LastPointCount", 0, ua.VariantType.UInt32),
            ("LastError", "", ua.VariantType.String), ("CalibrationHealth", "not measured", ua.VariantType.String),
        ]
        for name, value, vtype in specs:
            self._vars[name] = await scanner.add_variable(idx, name, ua.Variant(value, vtype))
        await scanner.add_method(idx, "Trigger", self._trigger, [], [ua.VariantType.String])
        self._server = server
        try:
            await server.start()
        except OSError as exc:
            raise ApplianceError(f"OPC UA: cannot listen on {cfg.endpoint} ({exc.strerror or exc}); is another "
                                 "server on that port? change service.opcua.endpoint (under systemd, a port must "
                                 "also be in scan3d.service's SocketBindAllow=)") from exc
        self._ready.set_result(None)
        try:
            await self._stop.wait()
        finally:
            with contextlib.suppress(Exception):
                await server.stop()

    async def _set(self, name: str, value: Any, vtype: ua.VariantType) -> None:
        await self._vars[name].write_value(ua.DataValue(ua.Variant(value, vtype)))

    async def _apply(self, event: Event) -> None:
        if not self._vars:
            return
        if event.get("type") == "state":
            state = str(event.get("state", ""))
            await self._set("State", state, ua.VariantType.String)
            await self._set("VisionState", VISION_STATE.get(state, "Error"), ua.VariantType.String)
            await self._set("ScansDone", int(event.get("scans_done", 0)), ua.VariantType.UInt32)
            err = event.get("last_error") or {}
            await self._set("LastError", str(err.get("message", "")), ua.VariantType.String)
        elif event.get("type") == "scan" and event.get("ok"):
            files = [str(f) for f in event.get("files", [])]
            cloud = next((f for f in files if f.endswith(".ply")), files[0] if files else "")
            await self._set("LastResultFile", cloud, ua.VariantType.String)
            await self._set("LastPointCount", int(event.get("points", 0)), ua.VariantType.UInt32)
            if "calibration_health" in event:
                await self._set("CalibrationHealth", _health_text(event["calibration_health"]),
                                ua.VariantType.String)
            await self._set("LastScanId", str(event.get("scan_id", "")), ua.VariantType.String)

    async def _trigger(self, parent: ua.NodeId) -> Any:
        loop = self._service_loop
        if loop is None:
            return ua.StatusCode(ua.StatusCodes.BadInvalidState)
        log.info("OPC UA: Trigger called")
        fut = asyncio.run_coroutine_threadsafe(self.view.trigger(True, "opcua"), loop)
        reply: dict[str, Any] = await asyncio.wrap_future(fut)
        scan = reply.get("scan") or {}
        if reply.get("ok") and scan.get("scan_id"):
            # the scan event may still be on its way: LastScanId is current when Trigger returns
            await self._apply({**scan, "type": "scan"})
            return [ua.Variant(str(scan["scan_id"]), ua.VariantType.String)]
        log.warning("OPC UA: Trigger: %s", reply.get("error") or reply.get("result"))
        if str(reply.get("result", "")).startswith("refused"):
            return ua.StatusCode(ua.StatusCodes.BadInvalidState)
        return ua.StatusCode(ua.StatusCodes.BadInternalError)
