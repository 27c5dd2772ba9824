"""A failed scan ends only after the frame pushes it handed to the decode threads: the next scan's decoder
reset can never race a push of the failed one (the virtual rig's camera dies mid-scan)."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from appliance import scan as scan_mod
from appliance.config import load_config
from appliance.errors import ScanError
from appliance.hardware.registry import build_rig
from appliance.reconstruct.decode import StreamingDecoder
from appliance.scan import Scanner, load_calibration_for

SMALL_RIG = {
    "projector": {"width": 320, "height": 200, "focal_px": 400, "principal_px": [160, 190],
                  "position_mm": [175, 0, 0], "look_at_mm": [0, 40, 580]},
    "cameras": {"cam0": {"width": 320, "height": 256, "focal_px": 450, "position_mm": [0, 0, 0],
                         "look_at_mm": [0, 0, 580]}},
}


def test_a_failed_scan_waits_for_its_pending_pushes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "appliance.yaml"
    path.write_text(yaml.safe_dump({
        "cameras": {"cam0": {"type": "sim", "fail_after_frames": 6}},
        "virtual_rig": SMALL_RIG,
        "reconstruction": {"min_depth_mm": 300, "max_depth_mm": 900},
    }))
    cfg = load_config(path)
    monkeypatch.setattr(scan_mod, "FRAME_TIMEOUT_S", 0.2)
    monkeypatch.setattr(scan_mod, "FRAME_TIMEOUT_PER_FRAME_S", 0.0)
    real_push = StreamingDecoder.push
    submitted, finished = [0], [0]
    lock = threading.Lock()

    def slow_push(self: StreamingDecoder, index: int, frame: Any) -> None:  # a slow decode thread
        with lock:
            submitted[0] += 1
        time.sleep(0.08)
        real_push(self, index, frame)
        with lock:
            finished[0] += 1

    rig = build_rig(cfg)  # renders the scene and builds ray tables: before the loop, not on it
    scanner = Scanner(cfg, rig, load_calibration_for(cfg, rig))

    async def main() -> tuple[int, int]:
        await scanner.open()
        await scanner.warm_up()  # the virtual rig's geometry and the kernels, before the frame timeouts count
        try:
            monkeypatch.setattr(StreamingDecoder, "push", slow_push)
            with pytest.raises(ScanError, match="scan failed"):
                await scanner.scan()
            with lock:  # at the moment the failure is reported
                return submitted[0], finished[0]
        finally:
            monkeypatch.setattr(StreamingDecoder, "push", real_push)
            await scanner.close()

    started, done = asyncio.run(main())
    assert started == 6  # the frames the camera delivered before it died
    assert done == started, f"{started - done} push(es) still running when the failed scan ended"
