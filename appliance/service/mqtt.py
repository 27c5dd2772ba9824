"""The MQTT face (aiomqtt): the service's state and scans on a broker, and a trigger command.

Topics under ``service.mqtt.topic_prefix`` (``scan3d/{serial}`` by default):

- ``<prefix>/state`` retained JSON, republished on every change and on every (re)connect; the last will
  (and a clean stop) leaves ``{"state": "offline"}``;
- ``<prefix>/scans`` one JSON per finished scan (id, time, points, file paths, timings, calibration health);
- ``<prefix>/cmd/trigger`` subscribed: starts a scan under the busy policy (payload optional JSON
  ``{"wait": false, "id": ...}``); the reply goes to ``<prefix>/cmd/trigger/result``.

The client runs beside the service, never in its way: a broker that is away is retried with backoff (first
failure and recovery logged), scan messages wait in a bounded queue (the oldest dropped), and a scan never
waits for the broker.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import ssl
from collections import deque
from typing import Any

import aiomqtt

from appliance.config.schema import MqttConfig
from appliance.errors import ConfigError
from appliance.service.control import dumps_json
from appliance.service.faces import Event, ServiceView
from appliance.service.http import read_secret

log = logging.getLogger(__name__)

# Module-level so tests can shorten them.
RECONNECT_FIRST_S = 0.5
PUBLISH_TIMEOUT_S = 5.0
TRIGGER_PAYLOAD_MAX = 4096
OFFLINE = json.dumps({"state": "offline"})


def _dumps(obj: Any) -> str:
    return dumps_json(obj, separators=(",", ":"), default=str)


class MqttFace:
    """Publishes state and scans to a broker and takes trigger commands from it.

    Parameters
    ----------
    cfg : MqttConfig
        Broker, credentials, TLS, topic prefix, bounds.
    view : ServiceView
        The service as the faces see it.
    """

    def __init__(self, cfg: MqttConfig, view: ServiceView) -> None:
        self.cfg = cfg
        self.view = view
        self.prefix = cfg.topic_prefix.replace("{serial}", view.serial).rstrip("/")
        self._password: str | None = None
        self._tls: ssl.SSLContext | None = None
        self._state: str = ""
        self._state_dirty = True
        self._outbox: deque[tuple[str, str]] = deque(maxlen=cfg.queue_max)
        self._wake = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._triggers: set[asyncio.Task[None]] = set()
        self._queue: asyncio.Queue[Event] | None = None
        self._client: aiomqtt.Client | None = None
        self.connected = asyncio.Event()
        self.connects = 0
        self.dropped = 0
        self.sent = 0  # outbox messages the broker took

    @property
    def queued(self) -> int:
        """Messages waiting for the broker."""
        return len(self._outbox)

    def topic(self, name: str) -> str:
        """``<prefix>/<name>``."""
        return f"{self.prefix}/{name}"

    async def start(self) -> None:
        """Read the password and start the client (a broker that is away is retried; this never waits)."""
        self._password = await asyncio.to_thread(read_secret, self.cfg.password_file, "service.mqtt.password_file")
        if self.cfg.tls:  # loading the CA store is file work: once, in a thread
            cafile = str(self.cfg.ca_file) if self.cfg.ca_file else None
            try:
                self._tls = await asyncio.to_thread(ssl.create_default_context, cafile=cafile)
            except OSError as exc:
                raise ConfigError(f"service.mqtt.ca_file = {cafile!r}: cannot load it as a CA bundle ({exc}); "
                                  "give a PEM file or unset it for the system store") from exc
        self._state = _dumps(self.view.state_event())
        self._queue = self.view.subscribe()
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._follow(), name="scan3d-mqtt-follow"),
                       loop.create_task(self._run(), name="scan3d-mqtt")]
        log.info("MQTT: publishing to %s:%d under %s/", self.cfg.host, self.cfg.port, self.prefix)

    async def close(self) -> None:
        """Leave ``offline`` as the retained state and disconnect."""
        client = self._client
        if client is not None and self.connected.is_set():
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError, asyncio.CancelledError):
                await client.publish(self.topic("state"), OFFLINE, qos=1, retain=True, timeout=1.0)
        for task in [*self._tasks, *self._triggers]:
            task.cancel()
        await asyncio.gather(*self._tasks, *self._triggers, return_exceptions=True)
        if self._queue is not None:
            self.view.unsubscribe(self._queue)

    # --- service events -> outbox ------------------------------------------------------------------

    def _post(self, topic: str, payload: str) -> None:
        if len(self._outbox) == self._outbox.maxlen:
            self.dropped += 1
            if self.dropped == 1 or self.dropped % 100 == 0:
                log.warning("MQTT: broker away, outgoing queue full (service.mqtt.queue_max = %d): dropped the "
                            "oldest message (%d so far)", self.cfg.queue_max, self.dropped)
        self._outbox.append((topic, payload))
        self._wake.set()

    async def _follow(self) -> None:
        assert self._queue is not None
        while True:
            event = await self._queue.get()
            if event.get("type") == "state":
                self._state = _dumps(event)
                self._state_dirty = True
                self._wake.set()
            elif event.get("type") == "scan":
                self._post(self.topic("scans"), _dumps({k: v for k, v in event.items() if k != "type"}))

    # --- the connection ----------------------------------------------------------------------------

    def _client_for(self) -> aiomqtt.Client:
        return aiomqtt.Client(
            self.cfg.host, self.cfg.port, username=self.cfg.username, password=self._password,
            identifier=f"scan3d-{self.view.serial}", keepalive=self.cfg.keepalive_s, tls_context=self._tls,
            will=aiomqtt.Will(self.topic("state"), OFFLINE, qos=1, retain=True), timeout=PUBLISH_TIMEOUT_S,
            max_queued_incoming_messages=64)

    async def _run(self) -> None:
        delay = RECONNECT_FIRST_S
        failing = False
        while True:
            try:
                async with self._client_for() as client:
                    self._client = client
                    self.connects += 1
                    self._state_dirty = True
                    await client.subscribe(self.topic("cmd/trigger"), qos=1)
                    log.info("MQTT: connected to %s:%d%s", self.cfg.host, self.cfg.port,
                             " (again)" if failing else "")
                    failing, delay = False, RECONNECT_FIRST_S
                    self.connected.set()
                    await self._serve(client)
            except aiomqtt.MqttError as exc:
                if not failing:
                    log.warning("MQTT: broker %s:%d away (%s); retrying with backoff up to %g s", self.cfg.host,
                                self.cfg.port, exc, self.cfg.reconnect_max_s)
                failing = True
            finally:
                self.connected.clear()
                self._client = None
            await asyncio.sleep(delay)
            delay = min(delay * 2, self.cfg.reconnect_max_s)

    async def _serve(self, client: aiomqtt.Client) -> None:
        loop = asyncio.get_running_loop()
        tasks = [loop.create_task(self._pump(client)), loop.create_task(self._listen(client))]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for t in done:
            exc = t.exception()
            if exc is not None:
                raise exc

    async def _pump(self, client: aiomqtt.Client) -> None:
        self._wake.set()
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self._state_dirty:
                self._state_dirty = False
                try:
                    await client.publish(self.topic("state"), self._state, qos=1, retain=True)
                except BaseException:
                    self._state_dirty = True
                    raise
            while self._outbox:
                topic, payload = self._outbox[0]
                await client.publish(topic, payload, qos=1)
                if self._outbox and self._outbox[0] == (topic, payload):
                    self._outbox.popleft()  # sent: only now (a failed send stays queued)
                self.sent += 1

    async def _listen(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            if not message.topic.matches(self.topic("cmd/trigger")):
                continue
            p = message.payload
            raw = bytes(p) if isinstance(p, bytes | bytearray) else b"" if p is None else str(p).encode()
            task = asyncio.get_running_loop().create_task(self._trigger(raw))
            self._triggers.add(task)
            task.add_done_callback(self._triggers.discard)

    async def _trigger(self, raw: bytes) -> None:
        request: dict[str, Any] = {}
        if len(raw) > TRIGGER_PAYLOAD_MAX:
            self._post(self.topic("cmd/trigger/result"), _dumps(
                {"ok": False, "error": f"trigger payload of {len(raw)} bytes is over {TRIGGER_PAYLOAD_MAX}"}))
            return
        if raw.strip():
            try:
                parsed = json.loads(raw)
            except ValueError:
                parsed = None
            if not isinstance(parsed, dict):
                self._post(self.topic("cmd/trigger/result"), _dumps(
                    {"ok": False, "error": "the trigger payload must be empty or a JSON object like "
                     '{"wait": true, "id": "job-17"}'}))
                return
            request = parsed
        log.info("MQTT: trigger on %s", self.topic("cmd/trigger"))
        reply = await self.view.trigger(bool(request.get("wait", True)), "mqtt")
        if "id" in request:
            reply["request_id"] = request["id"]
        self._post(self.topic("cmd/trigger/result"), _dumps(reply))
