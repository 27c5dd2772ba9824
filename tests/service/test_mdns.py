"""mDNS: the appliance is announced on loopback only, and a browser in another process sees its TXT change.

Every Zeroconf instance here is bound to 127.0.0.1 (never all interfaces).
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
import uuid
from typing import IO, Any

import pytest
from zeroconf import IPVersion
from zeroconf.asyncio import AsyncZeroconf

from appliance.config.schema import MdnsConfig
from appliance.errors import ConfigError
from appliance.output import mdns as M

# A second process: browses _scan3d._tcp on loopback and prints each new TXT record as a JSON line.
WATCH_SCRIPT = r"""
import json, select, sys
from zeroconf import IPVersion, ServiceBrowser, ServiceInfo, Zeroconf
name = sys.argv[1] + "._scan3d._tcp.local."
zc = Zeroconf(interfaces=["127.0.0.1"], ip_version=IPVersion.V4Only)
browser = ServiceBrowser(zc, "_scan3d._tcp.local.", handlers=[lambda **kw: None])  # keeps the cache fresh
print("{}", flush=True)
last = None
while not select.select([sys.stdin], [], [], 0.2)[0]:  # until stdin closes
    info = ServiceInfo("_scan3d._tcp.local.", name)
    if info.request(zc, 500):  # answered from the cache, which the announcements update
        txt = {k.decode(): (v or b"").decode() for k, v in info.properties.items()}
        if txt != last:
            last = txt
            print(json.dumps(txt), flush=True)
browser.cancel()
zc.close()
"""


class TxtWatcher:
    """The browsing process; ``wait_for(pred)`` returns the first TXT record (dict) matching ``pred``."""

    def __init__(self, instance: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", WATCH_SCRIPT, instance],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.seen: list[dict[str, str]] = []
        assert self._line(20.0) == {}  # started

    def _line(self, timeout_s: float) -> dict[str, str] | None:
        import select

        out: IO[str] = self.proc.stdout  # type: ignore[assignment]
        r, _, _ = select.select([out], [], [], timeout_s)
        if not r:
            return None
        line = out.readline()
        return json.loads(line) if line else None

    def wait_for(self, pred: Any, timeout_s: float = 15.0) -> dict[str, str]:
        for txt in self.seen:
            if pred(txt):
                return txt
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            txt = self._line(end - time.monotonic())
            if txt is None:
                continue
            self.seen.append(txt)
            if pred(txt):
                return txt
        raise AssertionError(f"no TXT record matched within {timeout_s} s; seen: {self.seen}")

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def unique_name() -> str:
    return f"scan3d-test-{uuid.uuid4().hex[:8]}"


def test_interfaces_must_be_addresses() -> None:
    with pytest.raises(ConfigError, match="not an IP address"):
        M.MdnsAnnouncer(MdnsConfig(interfaces=("eth0",)))
    with pytest.raises(ConfigError, match="empty"):
        M.MdnsAnnouncer(MdnsConfig(interfaces=()))


def test_txt_values_are_cut_to_fit() -> None:
    txt = M.clean_txt({"state": "fault", "fault": "x" * 400 + "\nmore"})
    assert len(txt["fault"]) == M.TXT_VALUE_MAX and txt["state"] == "fault"


def test_announce_update_and_smb_seen_by_another_process(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(M, "MIN_UPDATE_INTERVAL_S", 0.05)
    name = unique_name()
    watcher = TxtWatcher(name)
    try:

        async def main() -> None:
            ann = M.MdnsAnnouncer(
                MdnsConfig(interfaces=("127.0.0.1",), instance_name=name, announce_smb_share=f"{name}-scans")
            )
            await ann.start({"state": "idle", "scans": "0", "serial": "T-1"})
            try:
                first = await asyncio.to_thread(watcher.wait_for, lambda t: t.get("state") == "idle")
                assert first["serial"] == "T-1"
                for i in range(1, 4):  # coalesced: only the latest must arrive
                    ann.set_txt({"state": "scanning", "scans": str(i), "serial": "T-1"})
                ann.set_txt({"state": "idle", "scans": "3", "serial": "T-1", "last": "scan-3"})
                txt = await asyncio.to_thread(
                    watcher.wait_for, lambda t: t.get("scans") == "3" and t.get("state") == "idle"
                )
                assert txt["last"] == "scan-3"
                assert ann.updates_sent <= 2
                # the share is announced too (same loopback, a separate browser instance)
                zc = AsyncZeroconf(interfaces=["127.0.0.1"], ip_version=IPVersion.V4Only)
                try:
                    info = await zc.async_get_service_info(M.SMB_TYPE, f"{name}-scans.{M.SMB_TYPE}", 3000)
                finally:
                    await zc.async_close()
                assert info is not None and info.port == 445
            finally:
                await ann.close()

        asyncio.run(main())
    finally:
        watcher.close()
