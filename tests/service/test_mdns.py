"""mDNS: the appliance is announced on loopback only, and a browser in another process sees its TXT change.

Every Zeroconf instance here is bound to 127.0.0.1 (never all interfaces).
"""

from __future__ import annotations

import asyncio
import uuid

import pytest
from mdns_watch import TxtWatcher
from zeroconf import IPVersion
from zeroconf.asyncio import AsyncZeroconf

from appliance.config.schema import MdnsConfig
from appliance.errors import ConfigError
from appliance.output import mdns as M


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
