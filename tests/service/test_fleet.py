"""``scan3d fleet`` on loopback: a running service (small virtual rig, mDNS on 127.0.0.1) and a second
announcer are listed by the command in another process, with state, scans, last scan id and version."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import uuid
from pathlib import Path

from faces_helpers import appliance_copy, running_service

from appliance import __version__
from appliance.config.schema import MdnsConfig
from appliance.fleet import Appliance, format_fleet
from appliance.output.mdns import MdnsAnnouncer
from appliance.service.control import request


def fleet(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "appliance", "fleet", *args], capture_output=True, text=True,
                          timeout=60)


def test_fleet_lists_the_appliances_on_loopback(tmp_path: Path) -> None:
    tag = uuid.uuid4().hex[:6]
    cfg = appliance_copy(tmp_path, mdns={"enabled": True, "interfaces": ["127.0.0.1"],
                                         "instance_name": f"line-a-{tag}"})

    async def main() -> None:
        async with running_service(cfg) as svc:
            scan = (await asyncio.to_thread(request, svc.socket_path, {"cmd": "trigger", "wait": True}))["scan"]
            other = MdnsAnnouncer(MdnsConfig(interfaces=("127.0.0.1",), instance_name=f"line-b-{tag}"))
            await other.start({"txtvers": "1", "state": "fault", "scans": "7", "last": "x-7", "version": "0.0.9",
                               "serial": "B-2", "share": "/srv/scans", "fault": "camera 'cam0': no frame"})
            try:
                # 3 s of listening covers the ~2 s the announcements probe before they go out
                done = await asyncio.to_thread(fleet, "--interface", "127.0.0.1", "--timeout", "3", "--json")
            finally:
                await other.close()
        assert done.returncode == 0, done.stderr
        seen = {a["name"]: a for a in json.loads(done.stdout)}
        a, b = seen[f"line-a-{tag}"], seen[f"line-b-{tag}"]
        assert a["state"] == "idle" and a["scans"] == "1" and a["last"] == scan["scan_id"]
        assert a["version"] == __version__ and a["serial"] == "SIM-0001" and "127.0.0.1" in a["addresses"]
        assert b["state"] == "fault" and b["fault"].startswith("camera") and b["version"] == "0.0.9"
        table = format_fleet([Appliance(**a), Appliance(**b)])
        assert f"line-a-{tag}" in table and scan["scan_id"] in table and "fault (camera 'cam0': no frame)" in table

    asyncio.run(main())


def test_fleet_bad_interface_is_one_line_and_empty_lists_say_so() -> None:
    bad = fleet("--interface", "eth0")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "not an IP address" in bad.stderr
    assert "Traceback" not in bad.stderr
    neg = fleet("--timeout", "-1")
    assert neg.returncode == 2 and "must be > 0" in neg.stderr
    assert format_fleet([]) == "no appliances found"
    row = Appliance("x", ["127.0.0.1"], 0, "idle", "3", "id-3", "1.0", "S", "/s", "")
    assert format_fleet([row]).splitlines()[1].split() == ["x", "127.0.0.1", "idle", "3", "id-3", "1.0"]
