"""Shared parts of the line-integration tests (HTTP, MQTT, OPC UA, status page): a copy of the reference
configuration with a face enabled, the service run in-process, a real Mosquitto broker and a real headless
Chromium driven over its DevTools socket. Everything listens on 127.0.0.1 only."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import getpass
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from appliance.service import daemon as D
from appliance.service.faces import ServiceFaces

REPO = Path(__file__).resolve().parents[2]
TOKEN = "tok-3f9a1c77e2b84d05"

# A small virtual rig (320x256 camera): a scan takes ~0.1 s, so the tests stay short.
SMALL_RIG = {
    "projector": {"width": 320, "height": 200, "focal_px": 400, "principal_px": [160, 190],
                  "position_mm": [175, 0, 0], "look_at_mm": [0, 40, 580]},
    "cameras": {"cam0": {"width": 320, "height": 256, "focal_px": 450, "position_mm": [0, 0, 0],
                         "look_at_mm": [0, 0, 580]}},
}


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def appliance_copy(tmp: Path, top: dict[str, Any] | None = None, **service: Any) -> Path:
    """``config/appliance.yaml`` copied into ``tmp`` with its paths under ``tmp``, mDNS off, the small rig,
    ``top`` merged into its top-level sections and ``service`` into its service section; returns the copy."""
    doc = yaml.safe_load((REPO / "config" / "appliance.yaml").read_text())
    # the small rig has one camera: the configuration's one-camera rig (see its comments); ``top`` may add more
    doc["virtual_rig"].update(SMALL_RIG)
    doc["cameras"] = {n: c for n, c in doc["cameras"].items() if n in SMALL_RIG["cameras"]}
    doc["reconstruction"]["mode"], doc["sequence"]["axes"] = "projector", "x"
    for key, value in (top or {}).items():
        if isinstance(value, dict) and isinstance(doc.get(key), dict):
            doc[key].update(value)
        else:
            doc[key] = value
    doc["output"].update(directory=str(tmp / "share"), spool_directory=str(tmp / "spool"), min_free_mb=0)
    (tmp / "share").mkdir(exist_ok=True)
    doc["service"].update(control_socket=str(tmp / "ctl.sock"), state_directory=str(tmp / "state"),
                          config_poll_s=0.1, mdns={"enabled": False})
    for key, value in service.items():
        if isinstance(value, dict) and isinstance(doc["service"].get(key), dict):
            doc["service"][key].update(value)
        else:
            doc["service"][key] = value
    path = tmp / "appliance.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def token_file(tmp: Path, token: str = TOKEN) -> Path:
    """A token file (mode 600) holding ``token``."""
    p = tmp / "http-token"
    p.write_text(token + "\n")
    p.chmod(0o600)
    return p


def faces_of(svc: D.Service) -> ServiceFaces:
    """The service's line-integration faces."""
    assert isinstance(svc.faces, ServiceFaces)
    return svc.faces


async def wait_until(pred: Callable[[], bool], timeout_s: float = 10.0, what: str = "condition") -> None:
    """Poll ``pred`` every 10 ms until true (AssertionError after ``timeout_s``)."""
    end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > end:
            raise AssertionError(f"{what} not met within {timeout_s} s")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def running_service(config: Path) -> AsyncIterator[D.Service]:
    """The service of ``config`` running in this loop, ready (idle); stopped (and awaited) on exit."""
    svc = await asyncio.to_thread(D.Service, config)  # loading the configuration is file work
    task = asyncio.create_task(svc.run())
    try:
        try:
            await wait_until(lambda: (svc.board.state == "idle" and str(svc.board.phase) == "ready") or task.done(),
                                 120, "service ready")
        except AssertionError as exc:
            raise AssertionError(f"{exc}: {svc.board.one_line()}; last error {svc.board.last_error}") from None
        assert not task.done(), "the service stopped during start-up"
        await asyncio.wait_for(faces_of(svc).started.wait(), 60)
        yield svc
    finally:
        svc.request_stop()
        assert await asyncio.wait_for(task, 30) == 0


def warm_kernels() -> None:
    """Start and stop the service once on the small rig, outside any measured loop: numba loads its kernels
    (holding the interpreter) on the first start in a process; tests under ``loop_guard`` start after this.
    Both sequences the face tests use (the reference one and two axes): each needs kernels of its own, which a
    clean clone compiles (seconds of held interpreter) on first use."""

    async def once(cfg: Path) -> None:
        async with running_service(cfg):
            pass

    for top in ({}, {"sequence": {"axes": "xy"}}):
        with tempfile.TemporaryDirectory(prefix="scan3d-warm-") as tmp:
            asyncio.run(once(appliance_copy(Path(tmp), top=top)))


@pytest.fixture(scope="module")
def warm() -> None:
    """:func:`warm_kernels` once per test module."""
    warm_kernels()


# --- a real Mosquitto broker ----------------------------------------------------------------------------

class Broker:
    """``mosquitto`` on 127.0.0.1:``port`` (anonymous, no persistence); kill/start at will."""

    def __init__(self, tmp: Path, port: int | None = None, users: dict[str, str] | None = None) -> None:
        self.port = port or free_port()
        self.conf = tmp / "mosquitto.conf"
        auth = "allow_anonymous true\n"
        if users:  # only these users, with these passwords
            pw = tmp / "mosquitto.passwd"
            pw.write_text("")
            for user, password in users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(pw), user, password], check=True, timeout=30)
            auth = f"allow_anonymous false\npassword_file {pw}\n"
        # run as whoever runs the test (as root, mosquitto would switch to its own user, who cannot read tmp)
        self.conf.write_text(f"listener {self.port} 127.0.0.1\n{auth}persistence false\nlog_dest stderr\n"
                             f"user {getpass.getuser()}\n")
        self.log = tmp / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            pytest.skip("mosquitto is not installed (scripts/install-system-packages installs it)")
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([exe, "-c", str(self.conf)], stdout=log, stderr=log)
        end = time.monotonic() + 10
        while time.monotonic() < end:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port), 0.2):
                return
            if self.proc.poll() is not None:
                raise AssertionError(f"mosquitto exited: {self.log.read_text()[-500:]}")
            time.sleep(0.02)
        raise AssertionError("mosquitto did not listen within 10 s")

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)
        self.proc = None


@pytest.fixture
def broker(tmp_path: Path) -> Any:
    """A running Mosquitto broker on a free loopback port (killed at teardown)."""
    b = Broker(tmp_path)
    b.start()
    try:
        yield b
    finally:
        b.kill()


# --- a real headless Chromium -----------------------------------------------------------------------------

class Chromium:
    """Debian's ``chromium`` in headless mode on a URL, driven over the DevTools protocol (127.0.0.1 only)."""

    def __init__(self, url: str, width: int = 1280, height: int = 900) -> None:
        exe = shutil.which("chromium") or shutil.which("chromium-browser")
        if exe is None:
            pytest.skip("chromium is not installed (scripts/install-system-packages installs it)")
        self.profile = Path(tempfile.mkdtemp(prefix="scan3d-chromium-"))
        self.port = free_port()
        self.proc = subprocess.Popen(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-extensions", "--disable-dev-shm-usage", f"--user-data-dir={self.profile}",
             f"--remote-debugging-port={self.port}", "--remote-debugging-address=127.0.0.1",
             f"--window-size={width},{height}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        self._ws: Any = None
        self._session: Any = None
        self._id = 0
        self.events: list[dict[str, Any]] = []  # DevTools events seen (Runtime.exceptionThrown, ...)

    async def connect(self, timeout_s: float = 30.0) -> None:
        import aiohttp

        self._session = aiohttp.ClientSession()
        end = time.monotonic() + timeout_s
        while True:
            try:
                async with self._session.get(f"http://127.0.0.1:{self.port}/json/list") as r:
                    pages = [p for p in await r.json() if p.get("type") == "page"]
                if pages:
                    self._ws = await self._session.ws_connect(pages[0]["webSocketDebuggerUrl"], max_msg_size=0)
                    return
            except (aiohttp.ClientError, OSError, ValueError):
                pass
            if time.monotonic() > end or self.proc.poll() is not None:
                raise AssertionError("chromium's DevTools endpoint did not come up")
            await asyncio.sleep(0.1)

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        me = self._id
        await self._ws.send_str(json.dumps({"id": me, "method": method, "params": params}))
        while True:
            msg = json.loads((await self._ws.receive()).data)
            if "method" in msg:
                self.events.append(msg)
            if msg.get("id") == me:
                if "error" in msg:
                    raise AssertionError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))

    async def evaluate(self, expression: str) -> Any:
        res = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return res.get("result", {}).get("value")

    async def screenshot(self, path: Path) -> None:
        res = await self.call("Page.captureScreenshot", format="png")
        await asyncio.to_thread(path.write_bytes, base64.b64decode(res["data"]))

    async def disconnect(self) -> None:
        """Close the DevTools connection (the browser keeps running until :meth:`kill`)."""
        with contextlib.suppress(Exception):
            if self._ws is not None:
                await self._ws.close()
        if self._session is not None:
            await self._session.close()

    def kill(self) -> None:
        """Kill the browser (its whole process group) and remove its profile."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        shutil.rmtree(self.profile, ignore_errors=True)
