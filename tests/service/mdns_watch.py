"""A browser in another process that sees the appliance's mDNS TXT record change (loopback only), for
``test_mdns.py`` and the end-to-end service tests."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import IO, Any

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
