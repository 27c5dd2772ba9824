"""sd_notify over $NOTIFY_SOCKET (filesystem and abstract '@' addresses), and the watchdog interval."""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from appliance.service.notify import SdNotifier, watchdog_interval_s


@pytest.fixture
def receiver(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = tmp_path / "notify"
    s.bind(str(path))
    s.settimeout(2)
    yield s, str(path)
    s.close()


def recv(s: socket.socket) -> dict[str, str]:
    data = s.recv(4096).decode()
    return dict(line.split("=", 1) for line in data.splitlines())


def test_messages_reach_a_path_socket(receiver: tuple[socket.socket, str]) -> None:
    s, path = receiver
    n = SdNotifier.from_env({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("idle; 0 scans")
    assert recv(s) == {"READY": "1", "STATUS": "idle; 0 scans"}
    assert n.status("scanning\nnext line")
    assert recv(s) == {"STATUS": "scanning next line"}
    assert n.watchdog()
    assert recv(s) == {"WATCHDOG": "1"}
    assert n.stopping()
    assert recv(s) == {"STOPPING": "1"}
    n.close()


def test_abstract_namespace() -> None:
    name = f"scan3d-test-{uuid.uuid4().hex}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(2)
    try:
        n = SdNotifier(f"@{name}")
        assert n.ready()
        assert recv(s) == {"READY": "1"}
        n.close()
    finally:
        s.close()


def test_without_systemd_everything_is_a_no_op(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    n = SdNotifier.from_env({})
    assert not n.enabled and not n.ready() and not n.watchdog()
    gone = SdNotifier(str(tmp_path / "nobody-listens"))
    assert not gone.status("x") and not gone.status("y")  # failures never raise
    assert sum("sd_notify" in r.message for r in caplog.records) == 1  # and are logged once


def test_watchdog_interval() -> None:
    me = str(os.getpid())
    assert watchdog_interval_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": me}) == 2.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "4000000"}) == 2.0
    assert (
        watchdog_interval_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}) is None
    )  # for another process
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "junk"}) is None
