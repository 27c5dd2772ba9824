"""Error against the virtual rig's ground truth of every reconstruction mode, from one scan's decoded maps, and
the calibration health from all three checks.

``scripts/run`` prints it after the service's scans on a multi-camera rig: the service writes the configured
mode's cloud (fused, by default), and this shows what each mode alone gives on the same frames: camera-projector
per camera, camera-camera, and both fused. Then one scan with both projector axes coded: the default sequence
codes columns only (half the frames), which gives the service's every scan the three-view check; both axes add
the ray-ray residual of each camera with the projector and the cameras' epipolar residual.

    .venv/bin/python scripts/mode_errors.py [config/appliance.yaml]
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt

from appliance.config.loader import load_config
from appliance.reconstruct.pipeline import Reconstructor, available_modes
from appliance.scan import scan_once
from appliance.sim.accuracy import compare_to_ground_truth


def main(config: Path) -> int:
    cfg = load_config(config)
    names = list(cfg.cameras)
    result, scanner = asyncio.run(scan_once(cfg))
    virtual = scanner.rig.virtual
    if virtual is None:
        print("mode errors: not a virtual rig (no ground truth)")
        return 0
    white: dict[str, npt.NDArray[np.generic]] = dict(result.white)
    for mode in available_modes(scanner.calibration, names):
        settings = cfg.reconstruction.model_copy(update={"mode": mode})
        rec = Reconstructor(scanner.calibration, cfg.sequence.axes, settings, scanner.sequence)
        cloud = rec.run(result.maps, white).cloud
        if mode == "projector":  # each camera with the projector alone
            for i, name in enumerate(names):
                alone = cloud.select(cloud.camera == i)
                alone.camera[:] = 0
                print(f"mode projector, {name}: {compare_to_ground_truth(alone, virtual, [name]).line()}")
        else:
            cams = names[:1] if mode == "stereo" else names
            what = f"{names[0]} + {names[1]}" if mode == "stereo" else f"fused, {', '.join(names)}"
            print(f"mode {mode} ({what}): {compare_to_ground_truth(cloud, virtual, cams).line()}")
    if len(names) >= 2 and cfg.sequence.axes != "xy":
        print("calibration health from all three checks (one more scan, both projector axes coded):")
        both = cfg.model_copy(update={"sequence": cfg.sequence.model_copy(update={"axes": "xy"})})
        result, _ = asyncio.run(scan_once(both))
    health = result.calibration_health
    checks = health.get("checks", [])
    print(f"calibration health {health.get('status', 'not measured')}: "
          + "; ".join(f"{c['kind']} {c['status']} ({c['reason']})" for c in checks))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "config/appliance.yaml")))
