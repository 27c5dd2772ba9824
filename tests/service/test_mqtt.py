"""The MQTT face against a real Mosquitto broker on 127.0.0.1 started by the test, seen by a real aiomqtt
client: retained state, one message per finished scan, the trigger command and its result, the offline state
at stop, and the broker killed and restarted while the service keeps scanning."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
import yaml
from faces_helpers import Broker, appliance_copy, faces_of, running_service, wait_until

from appliance.service import mqtt as M
from appliance.service.control import request

PREFIX = "scan3d/SIM-0001"  # the reference config's serial in the default topic_prefix


class Watcher:
    """A subscriber to ``<PREFIX>/#`` collecting every message (retained flag kept)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.messages: list[tuple[str, dict[str, Any], bool]] = []
        self._task: asyncio.Task[None] | None = None
        self.subscribed = asyncio.Event()

    async def _run(self) -> None:
        async with aiomqtt.Client("127.0.0.1", self.port, identifier="test-watcher") as c:
            await c.subscribe(f"{PREFIX}/#", qos=1)
            self.subscribed.set()
            async for m in c.messages:
                assert isinstance(m.payload, bytes)
                self.messages.append((str(m.topic), json.loads(m.payload), bool(m.retain)))

    async def __aenter__(self) -> Watcher:
        self._task = asyncio.create_task(self._run())
        await asyncio.wait_for(self.subscribed.wait(), 10)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)

    def on(self, topic: str) -> list[dict[str, Any]]:
        return [p for t, p, _ in self.messages if t == f"{PREFIX}/{topic}"]


async def publish(port: int, topic: str, payload: str) -> None:
    async with aiomqtt.Client("127.0.0.1", port, identifier="test-line") as c:
        await c.publish(f"{PREFIX}/{topic}", payload, qos=1)


def mqtt_config(tmp: Path, port: int, **mqtt: Any) -> Path:
    return appliance_copy(tmp, mqtt={"enabled": True, "host": "127.0.0.1", "port": port, **mqtt})


def test_state_scans_and_trigger_command(tmp_path: Path) -> None:
    broker = Broker(tmp_path)
    broker.start()
    try:
        async def main() -> None:
            async with running_service(mqtt_config(tmp_path, broker.port)) as svc:
                face = faces_of(svc).face("mqtt")
                assert isinstance(face, M.MqttFace) and face.prefix == PREFIX
                await asyncio.wait_for(face.connected.wait(), 10)
                async with Watcher(broker.port) as w:
                    await wait_until(lambda: bool(w.on("state")), 5, "retained state")
                    assert w.on("state")[-1]["state"] == "idle" and w.messages[0][2]  # retained
                    await publish(broker.port, "cmd/trigger", json.dumps({"id": "job-17"}))
                    await wait_until(lambda: bool(w.on("cmd/trigger/result")) and bool(w.on("scans")), 10,
                                     "trigger result and scan message")
                    result, scan = w.on("cmd/trigger/result")[0], w.on("scans")[0]
                    assert result["ok"] and result["request_id"] == "job-17" and result["result"] == "started"
                    sid = result["scan"]["scan_id"]
                    assert scan["scan_id"] == sid and scan["trigger"] == "mqtt" and scan["points"] > 1000
                    cloud = next(f for f in scan["files"] if f.endswith(f"{sid}.ply"))
                    assert await asyncio.to_thread(Path(cloud).is_file)
                    assert scan["timings_ms"]["trigger_to_file_ms"] > 0 and "calibration_health" in scan
                    assert svc.board.last_scan_id() == sid
                    await wait_until(lambda: w.on("state")[-1].get("scans_done") == 1, 5, "state after the scan")
                    assert w.on("state")[-1]["last_scan_id"] == sid
                    # a payload that is not a JSON object gets an answer, not a scan
                    await publish(broker.port, "cmd/trigger", "[1, 2]")
                    await wait_until(lambda: len(w.on("cmd/trigger/result")) == 2, 5, "error reply")
                    assert not w.on("cmd/trigger/result")[1]["ok"] and svc.board.counters["triggers"] == 1
                    # a new serial in the configuration: the face moves to the new prefix, the old one says offline
                    path = svc.config_path
                    doc = yaml.safe_load(await asyncio.to_thread(path.read_text))
                    doc["serial"] = "SIM-0002"
                    await asyncio.to_thread(path.write_text, yaml.safe_dump(doc))
                    await wait_until(lambda: getattr(faces_of(svc).face("mqtt"), "prefix", "") == "scan3d/SIM-0002",
                                     10, "MQTT face on the new prefix")
                    await wait_until(lambda: w.on("state")[-1] == {"state": "offline"}, 5, "old prefix offline")
                async with aiomqtt.Client("127.0.0.1", broker.port, identifier="test-renamed") as c:
                    await c.subscribe("scan3d/SIM-0002/state", qos=1)
                    async with asyncio.timeout(10):  # the face's first state on the new prefix
                        async for m in c.messages:
                            assert isinstance(m.payload, bytes)
                            if json.loads(m.payload).get("serial") == "SIM-0002":
                                break
                # ... is retained: a client that subscribes after it was published gets it at once (the one above
                # may have subscribed before the face published, and a message delivered live has no retain flag)
                async with aiomqtt.Client("127.0.0.1", broker.port, identifier="test-renamed-late") as c:
                    await c.subscribe("scan3d/SIM-0002/state", qos=1)
                    async with asyncio.timeout(5):
                        async for m in c.messages:
                            assert isinstance(m.payload, bytes)
                            state = json.loads(m.payload)
                            break
                    assert m.retain and state["serial"] == "SIM-0002" and state["state"] == "idle"
            async with aiomqtt.Client("127.0.0.1", broker.port, identifier="test-late") as c:
                await c.subscribe("scan3d/SIM-0002/state", qos=1)  # the service stopped: retained offline
                async for m in c.messages:
                    assert isinstance(m.payload, bytes) and json.loads(m.payload) == {"state": "offline"}
                    break

        asyncio.run(main())
    finally:
        broker.kill()


def test_broker_killed_and_restarted_mid_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(M, "RECONNECT_FIRST_S", 0.5)
    broker = Broker(tmp_path)
    broker.start()
    try:
        async def main() -> None:
            cfg = mqtt_config(tmp_path, broker.port, reconnect_max_s=0.5, queue_max=2)
            async with running_service(cfg) as svc:
                face = faces_of(svc).face("mqtt")
                assert isinstance(face, M.MqttFace)
                await asyncio.wait_for(face.connected.wait(), 10)
                first = await asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True})
                assert first["ok"]
                await wait_until(lambda: face.sent == 1 and face.queued == 0, 5, "first scan published")
                broker.kill()
                await wait_until(lambda: not face.connected.is_set(), 10, "disconnect noticed")
                away = []
                for _ in range(3):  # the service keeps scanning while the broker is away
                    reply = await asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True})
                    assert reply["ok"], reply
                    away.append(reply["scan"])
                assert svc.board.counters["scans_done"] == 4 and svc.board.state == "idle"
                assert max(s["timings_ms"]["trigger_to_file_ms"] for s in away) < 5000
                await asyncio.sleep(0.2)
                assert face.dropped == 1 and face.queued == 2  # 3 scans, queue_max 2: the oldest is dropped
                broker.start()  # a fresh broker: no retained messages, no sessions
                async with Watcher(broker.port) as w:
                    await asyncio.wait_for(face.connected.wait(), 10)
                    await wait_until(lambda: len(w.on("scans")) == 2 and bool(w.on("state")), 10,
                                     "republished state and queued scans")
                    state = w.on("state")[-1]
                    assert state["state"] == "idle" and state["scans_done"] == 4
                    assert [s["scan_id"] for s in w.on("scans")] == [s["scan_id"] for s in away[1:]]
                    assert face.connects == 2
                    after = await asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True})
                    await wait_until(lambda: len(w.on("scans")) == 3, 10, "scan after the restart")
                    assert w.on("scans")[-1]["scan_id"] == after["scan"]["scan_id"]
            async with Watcher(broker.port) as late:  # the retained state survives our client
                await wait_until(lambda: bool(late.on("state")), 5, "retained state")
                assert late.on("state")[-1] == {"state": "offline"}

        asyncio.run(main())
    finally:
        broker.kill()


def test_broker_with_users_takes_the_password_file(tmp_path: Path) -> None:
    broker = Broker(tmp_path, users={"scanner-3": "mq-pass-81f2", "line": "line-pass"})
    broker.start()
    pw = tmp_path / "mqtt-password"
    pw.write_text("mq-pass-81f2\n")
    try:
        async def main() -> None:
            cfg = mqtt_config(tmp_path, broker.port, username="scanner-3", password_file=str(pw))
            async with running_service(cfg) as svc:
                face = faces_of(svc).face("mqtt")
                assert isinstance(face, M.MqttFace)
                await asyncio.wait_for(face.connected.wait(), 10)
                async with aiomqtt.Client("127.0.0.1", broker.port, username="line", password="line-pass") as c:
                    await c.subscribe(f"{PREFIX}/state", qos=1)
                    async for m in c.messages:
                        assert isinstance(m.payload, bytes) and json.loads(m.payload)["state"] == "idle"
                        break
                with pytest.raises(aiomqtt.MqttError):  # the broker does check
                    async with aiomqtt.Client("127.0.0.1", broker.port, username="line", password="nope"):
                        pass

        asyncio.run(main())
    finally:
        broker.kill()
