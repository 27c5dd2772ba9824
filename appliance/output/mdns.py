"""mDNS announcement of the appliance (``_scan3d._tcp``) and, optionally, of its SMB share (``_smb._tcp``).

Uses python-zeroconf bound to the configured interface addresses only (``service.mdns.interfaces``; never
every interface). The TXT record (state, scans done, last scan id, share location, version, serial) is kept
current: :meth:`MdnsAnnouncer.set_txt` may be called on every change of state; updates are coalesced so the
network sees at most one announcement per :data:`MIN_UPDATE_INTERVAL_S`.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import re
import socket

from zeroconf import IPVersion, ServiceInfo
from zeroconf.asyncio import AsyncZeroconf

from appliance.config.schema import MdnsConfig
from appliance.errors import ConfigError

log = logging.getLogger(__name__)

SERVICE_TYPE = "_scan3d._tcp.local."
SMB_TYPE = "_smb._tcp.local."
# Module-level so tests can shorten it.
MIN_UPDATE_INTERVAL_S = 0.25
TXT_VALUE_MAX = 200  # one TXT string is at most 255 bytes including "key="


def _label(text: str) -> str:
    """A DNS-safe host label."""
    label = re.sub(r"[^A-Za-z0-9-]+", "-", text).strip("-")[:63]
    return label or "scan3d"


def clean_txt(txt: dict[str, str]) -> dict[str, str]:
    """TXT entries with values cut to :data:`TXT_VALUE_MAX` bytes and no newlines."""
    out = {}
    for k, v in txt.items():
        value = str(v).replace("\n", " ").encode()[:TXT_VALUE_MAX].decode("utf-8", "ignore")
        out[str(k)[:9]] = value
    return out


class MdnsAnnouncer:
    """Announces the appliance on the configured interfaces and keeps its TXT record current.

    Parameters
    ----------
    cfg : MdnsConfig
        ``interfaces`` (IP addresses), ``instance_name`` (hostname when unset), ``announce_smb_share``,
        ``port``.
    """

    def __init__(self, cfg: MdnsConfig) -> None:
        self.cfg = cfg
        self.addresses = self._parse_addresses(cfg.interfaces)
        self.instance = cfg.instance_name or socket.gethostname()
        self.server = f"{_label(self.instance)}.local."
        self.name = f"{self.instance}.{SERVICE_TYPE}"
        self._zc: AsyncZeroconf | None = None
        self._info: ServiceInfo | None = None
        self._smb: ServiceInfo | None = None
        self._txt: dict[str, str] = {}
        self._pending: dict[str, str] | None = None
        self._flush_task: asyncio.Task[None] | None = None
        self.updates_sent = 0

    @staticmethod
    def _parse_addresses(items: tuple[str, ...]) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
        out = []
        for item in items:
            try:
                out.append(ipaddress.ip_address(item))
            except ValueError as exc:
                raise ConfigError(
                    f"service.mdns.interfaces: {item!r} is not an IP address; list the addresses of the "
                    "interfaces to announce on (e.g. 192.168.1.20)"
                ) from exc
        if not out:
            raise ConfigError("service.mdns.interfaces is empty; list at least one address or disable mdns")
        return out

    def _service_info(self, txt: dict[str, str]) -> ServiceInfo:
        return ServiceInfo(SERVICE_TYPE, self.name, port=self.cfg.port, properties=clean_txt(txt),
                           server=self.server, addresses=[a.packed for a in self.addresses])

    async def start(self, txt: dict[str, str]) -> None:
        """Bind to the interfaces and register the service(s) with ``txt``.

        Raises
        ------
        OSError
            When an interface address is not present on this machine.
        """
        v4 = all(a.version == 4 for a in self.addresses)
        v6 = all(a.version == 6 for a in self.addresses)
        ipv = IPVersion.V4Only if v4 else IPVersion.V6Only if v6 else IPVersion.All
        self._zc = AsyncZeroconf(interfaces=[str(a) for a in self.addresses], ip_version=ipv)
        try:
            self._txt = clean_txt(txt)
            self._info = self._service_info(self._txt)
            await (await self._zc.async_register_service(self._info, allow_name_change=True))
            if self.cfg.announce_smb_share:
                self._smb = ServiceInfo(SMB_TYPE, f"{self.cfg.announce_smb_share}.{SMB_TYPE}", port=445,
                                        properties={"path": self.cfg.announce_smb_share}, server=self.server,
                                        addresses=[a.packed for a in self.addresses])
                await (await self._zc.async_register_service(self._smb, allow_name_change=True))
        except BaseException:
            await self._zc.async_close()
            self._zc = None
            raise
        log.info("mDNS: announcing %s on %s", self._info.name, ", ".join(str(a) for a in self.addresses))

    @property
    def txt(self) -> dict[str, str]:
        """The TXT record as last announced (or pending)."""
        return dict(self._pending if self._pending is not None else self._txt)

    def set_txt(self, txt: dict[str, str]) -> None:
        """Announce ``txt`` soon (call from the event loop; coalesced)."""
        new = clean_txt(txt)
        if new == self._txt and self._pending is None:
            return
        self._pending = new
        if self._zc is not None and (self._flush_task is None or self._flush_task.done()):
            self._flush_task = asyncio.get_running_loop().create_task(self._flush(), name="mdns-update")

    async def _flush(self) -> None:
        while self._pending is not None and self._zc is not None:
            txt, self._pending = self._pending, None
            if txt != self._txt:
                self._txt = txt
                self._info = self._service_info(txt)
                try:
                    await (await self._zc.async_update_service(self._info))
                    self.updates_sent += 1
                except Exception as exc:  # zeroconf raises its own errors on a closing instance
                    log.warning("mDNS update failed: %s", exc)
            await asyncio.sleep(MIN_UPDATE_INTERVAL_S)

    async def close(self) -> None:
        """Unregister (goodbye packets) and release the sockets."""
        if self._flush_task is not None:
            self._flush_task.cancel()
            try:
                await self._flush_task
            except asyncio.CancelledError:
                pass
            self._flush_task = None
        if self._zc is not None:
            try:
                await self._zc.async_unregister_all_services()
            finally:
                await self._zc.async_close()
                self._zc = None
