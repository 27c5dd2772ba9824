"""HDR benchmark (part of ``scripts/bench``): a scan with one exposure against three, on the virtual rig.

The default configuration's rig (one 1280x1024 camera), scanned by :class:`appliance.scan.Scanner` as the
service runs it (frames given back as the decoder is done with them), once with ``sequence.exposures_us``
empty and once with three exposures. Per variant: the median scan time, the capture (the virtual rig renders
every frame, so this is the renderer's speed, not a camera's), the post-capture latency (last frame to cloud in
memory: the last decodes, the fusion and the reconstruction), and the peak resident memory the scanner added.
Run alone: ``.venv/bin/python scripts/bench_hdr.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import statistics
import sys
from pathlib import Path
from typing import Any

from bench_common import REPO

HDR_EXPOSURES_US = (2500, 10_000, 40_000)


def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def _reset_peak() -> bool:
    """Reset the process's peak RSS (VmHWM) to its current RSS (Linux >= 4.0); False where not allowed."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


async def _scans(exposures: tuple[int, ...], repeats: int) -> dict[str, Any]:
    from appliance.config import load_config
    from appliance.hardware.registry import build_rig
    from appliance.scan import Scanner, load_calibration_for

    base = load_config(REPO / "config" / "appliance.yaml")
    cfg = base.model_copy(update={"sequence": base.sequence.model_copy(update={"exposures_us": exposures})})
    gc.collect()
    rss0 = _status_kb("VmRSS")
    peak_ok = _reset_peak()

    def make() -> Scanner:
        rig = build_rig(cfg)
        return Scanner(cfg, rig, load_calibration_for(cfg, rig), keep_frames=False)

    scanner = await asyncio.to_thread(make)
    runs: list[dict[str, float]] = []
    points = 0
    try:
        await scanner.warm_up()
        for _ in range(repeats):
            result = await scanner.scan()
            t = result.timings_ms
            runs.append({"scan_ms": t["scan_ms"], "capture_ms": t["capture_ms"],
                         "post_capture_ms": t["scan_ms"] - t["capture_ms"],
                         "decode_finish_ms": t["decode_finish_ms"]})  # fmt: skip
            points = len(result.cloud)
    finally:
        await scanner.close()
    peak_mb = (_status_kb("VmHWM") - rss0) / 1024 if peak_ok else float("nan")
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    return {"passes": max(1, len(exposures)), "frames": len(scanner.capture), "points": points,
            "cameras": [f"{c.width}×{c.height}" for n, c in cfg.virtual_rig.cameras.items() if n in cfg.cameras],
            "peak_added_mb": peak_mb, **med}  # fmt: skip


def bench_hdr(repeats: int) -> dict[str, Any]:
    """One exposure against :data:`HDR_EXPOSURES_US`, in one run (medians over ``repeats`` scans each)."""
    one = asyncio.run(_scans((), repeats))
    three = asyncio.run(_scans(HDR_EXPOSURES_US, repeats))
    return {"one": one, "three": three, "exposures_us": list(HDR_EXPOSURES_US)}


def report_line(r: dict[str, Any]) -> str:
    """The README's HDR line."""
    one, three = r["one"], r["three"]
    return (
        f"one exposure ({one['frames']} frames) against three ({', '.join(f'{e / 1000:g}' for e in r['exposures_us'])}"
        f" ms, {three['frames']} frames), cameras {' + '.join(one['cameras']) or '?'} (the default configuration's "
        f"rig), service settings, medians: post-capture latency "
        f"(last frame to cloud) **{one['post_capture_ms']:.0f} → {three['post_capture_ms']:.0f} ms "
        f"({three['post_capture_ms'] / one['post_capture_ms']:.2f}×)** of which the last decode + fusion "
        f"{one['decode_finish_ms']:.0f} → {three['decode_finish_ms']:.0f} ms; whole scan {one['scan_ms']:.0f} → "
        f"{three['scan_ms']:.0f} ms (the capture is the virtual rig's rendering: {one['capture_ms']:.0f} → "
        f"{three['capture_ms']:.0f} ms); peak memory the scanner added {one['peak_added_mb']:.0f} → "
        f"{three['peak_added_mb']:.0f} MB; {one['points']} → {three['points']} points."
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    print(report_line(bench_hdr(a.repeats)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
