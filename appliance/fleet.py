"""``scan3d fleet``: the appliances announcing ``_scan3d._tcp`` on one interface, for a person with several
scanners on a line.

Browses mDNS bound to the given interface address only (never every interface) for ``timeout_s``, resolves
each appliance's TXT record (state, scans done, last scan id, version, serial, share; see
:meth:`appliance.service.publish.Publisher.txt_record`) and prints one line per appliance, or JSON.
"""

from __future__ import annotations

import ipaddress
import json
import sys
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

from zeroconf import IPVersion, ServiceBrowser, ServiceInfo, ServiceStateChange, Zeroconf

from appliance.errors import ConfigError
from appliance.output.mdns import SERVICE_TYPE


@dataclass
class Appliance:
    """One appliance as its announcement describes it."""

    name: str
    addresses: list[str]
    port: int
    state: str
    scans: str
    last: str
    version: str
    serial: str
    share: str
    fault: str


def _appliance(info: ServiceInfo) -> Appliance:
    txt = {k.decode(errors="replace"): (v or b"").decode(errors="replace") for k, v in info.properties.items()}
    name = info.name[: -len(SERVICE_TYPE) - 1] if info.name.endswith("." + SERVICE_TYPE) else info.name
    return Appliance(name, [str(a) for a in info.parsed_addresses()], int(info.port or 0), txt.get("state", "?"),
                     txt.get("scans", "?"), txt.get("last", ""), txt.get("version", "?"), txt.get("serial", ""),
                     txt.get("share", ""), txt.get("fault", ""))


def discover(interface: str, timeout_s: float = 2.0) -> list[Appliance]:
    """Browse ``_scan3d._tcp`` on ``interface`` for ``timeout_s``; the appliances seen, by name.

    Parameters
    ----------
    interface : str
        IP address of the interface to browse on (e.g. ``127.0.0.1``, ``192.168.3.5``).
    timeout_s : float
        How long to listen for announcements (s).

    Raises
    ------
    ConfigError
        When ``interface`` is not an IP address.
    OSError
        When the address is not on this machine.
    """
    try:
        addr = ipaddress.ip_address(interface)
    except ValueError as exc:
        raise ConfigError(f"--interface {interface!r}: not an IP address; give the address of the interface the "
                          "appliances are on (e.g. 192.168.3.5, or 127.0.0.1)") from exc
    if not 0 < timeout_s <= 60:
        raise ConfigError(f"--timeout {timeout_s:g}: must be > 0 and <= 60 (seconds to listen)")
    zc = Zeroconf(interfaces=[str(addr)], ip_version=IPVersion.V4Only if addr.version == 4 else IPVersion.V6Only)
    names: set[str] = set()
    lock = threading.Lock()

    def changed(zeroconf: Zeroconf, service_type: str, name: str, state_change: ServiceStateChange) -> None:
        with lock:
            if state_change is ServiceStateChange.Removed:
                names.discard(name)
            else:
                names.add(name)

    try:
        browser = ServiceBrowser(zc, SERVICE_TYPE, handlers=[changed])
        time.sleep(timeout_s)
        browser.cancel()
        found = []
        with lock:
            todo = sorted(names)
        for name in todo:
            info = ServiceInfo(SERVICE_TYPE, name)
            if info.request(zc, 1000):
                found.append(_appliance(info))
        return found
    finally:
        zc.close()


def format_fleet(appliances: list[Appliance]) -> str:
    """A table: one line per appliance (name, address, state, scans, last scan, version)."""
    if not appliances:
        return "no appliances found"
    rows = [("NAME", "ADDRESS", "STATE", "SCANS", "LAST SCAN", "VERSION")]
    for a in appliances:
        state = a.state + (f" ({a.fault[:60]})" if a.fault else "")
        rows.append((a.name, ",".join(a.addresses) or "-", state, a.scans, a.last or "-", a.version))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows)


def fleet_command(interface: str, timeout_s: float, as_json: bool) -> int:
    """``scan3d fleet``: print the appliances on ``interface``; exit status 0 (1 when none was found)."""
    found = discover(interface, timeout_s)
    if as_json:
        data: list[dict[str, Any]] = [asdict(a) for a in found]
        print(json.dumps(data, indent=2))
    else:
        print(format_fleet(found))
    sys.stdout.flush()
    return 0 if found else 1
