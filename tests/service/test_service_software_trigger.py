"""A camera without a trigger line (UVC, Aravis with software trigger) is fired by the scan, also in the service.

The simulated projector is cut off from the cameras (no trigger line) and the sim camera says it needs a
software trigger: a scan through ``scan3d run`` completes only if the service's camera wrapper passes
``needs_software_trigger`` and ``trigger()`` on to the scan (it once did not: every such scan timed out).
"""

from __future__ import annotations

from pathlib import Path

import e2e_helpers as e2e
import pytest

from appliance.hardware import sim
from appliance.service import daemon as D


def test_software_triggered_camera_scans_through_the_service(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fired: list[int] = []
    real_trigger = sim.SimCamera.trigger

    async def trigger(self: sim.SimCamera, index: int) -> None:
        fired.append(index)
        await real_trigger(self, index)

    monkeypatch.setattr(sim.SimWorld, "show", lambda self, index: None)  # no trigger line
    monkeypatch.setattr(sim.SimCamera, "needs_software_trigger", True)
    monkeypatch.setattr(sim.SimCamera, "trigger", trigger)
    scans: list[dict[str, object]] = []
    frames: list[int] = []

    async def body(svc: D.Service) -> None:
        assert svc.scanner is not None
        frames.append(len(svc.scanner.sequence))
        scans.append(await e2e.scan_once(svc))

    rc, _ = e2e.run_in_process(e2e.write_config(tmp_path), body)
    assert rc == 0
    assert scans[0]["ok"] and int(scans[0]["points"]) > 1000  # type: ignore[call-overload]
    assert sorted(set(fired)) == list(range(frames[0])) and frames[0] > 0
