"""HDR benchmark (part of ``scripts/bench``): a scan with one exposure against three, on the virtual rig.

The default configuration's rig (two 1280x1024 cameras), scanned by :class:`appliance.scan.Scanner` as the
service runs it (frames given back as the decoder is done with them), with ``sequence.exposures_us`` empty and
with three exposures: two scanners in one process whose scans alternate, so that the machine's slow spells hit
both alike. Per variant: the median scan time, the capture (the virtual rig renders every frame, so this is the
renderer's speed, not a camera's), the post-capture latency (last frame to cloud in memory: the last decodes,
the fusion and the reconstruction) with the median of the rounds' ratios, the resident memory the scanner holds
between scans, and the peak a scan adds above it.
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


def _config(exposures: tuple[int, ...]) -> Any:
    from appliance.config import load_config

    base = load_config(REPO / "config" / "appliance.yaml")
    return base.model_copy(update={"sequence": base.sequence.model_copy(update={"exposures_us": exposures})})


async def _interleaved(variants: dict[str, tuple[int, ...]], repeats: int) -> dict[str, dict[str, Any]]:
    """Scan with every variant's scanner in turn, ``repeats`` rounds: a slow spell of the machine hits all alike.

    Per variant the medians of its scans, the peak memory one scan added above the process's resident memory
    just before it (the scanner's standing buffers are counted apart, as ``standing_mb``), and per round the
    ratio of each variant's post-capture latency to the first variant's of the same round.
    """
    from appliance.hardware.registry import build_rig
    from appliance.scan import Scanner, load_calibration_for

    scanners: dict[str, Scanner] = {}
    cfgs = {name: _config(exp) for name, exp in variants.items()}
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in variants}
    points: dict[str, int] = {}
    standing: dict[str, float] = {}
    def make(cfg: Any) -> Scanner:
        rig = build_rig(cfg)
        return Scanner(cfg, rig, load_calibration_for(cfg, rig), keep_frames=False)

    # a first scanner, thrown away: the process's one-time loading (compiled kernels, imports) is then not
    # counted in the first variant's standing memory
    first_scanner = await asyncio.to_thread(make, next(iter(cfgs.values())))
    try:
        await first_scanner.warm_up()
        await first_scanner.scan()
    finally:
        await first_scanner.close()
    del first_scanner
    try:
        for name, cfg in cfgs.items():
            gc.collect()
            rss0 = _status_kb("VmRSS")
            scanners[name] = await asyncio.to_thread(make, cfg)
            await scanners[name].warm_up()
            await scanners[name].scan()  # first scan: buffers and caches in place
            gc.collect()
            standing[name] = (_status_kb("VmRSS") - rss0) / 1024
        for _ in range(repeats):
            for name, scanner in scanners.items():
                gc.collect()
                rss = _status_kb("VmRSS")
                peak_ok = _reset_peak()
                result = await scanner.scan()
                peak = (_status_kb("VmHWM") - rss) / 1024 if peak_ok else float("nan")
                t = result.timings_ms
                runs[name].append({"scan_ms": t["scan_ms"], "capture_ms": t["capture_ms"],
                                   "post_capture_ms": t["scan_ms"] - t["capture_ms"],
                                   "decode_finish_ms": t["decode_finish_ms"], "peak_scan_mb": peak})  # fmt: skip
                points[name] = len(result.cloud)
                del result
    finally:
        for scanner in scanners.values():
            await scanner.close()
    first = next(iter(variants))
    out: dict[str, dict[str, Any]] = {}
    for name, exp in variants.items():
        cfg = cfgs[name]
        med = {k: statistics.median(r[k] for r in runs[name]) for k in runs[name][0]}
        ratios = [r["post_capture_ms"] / f["post_capture_ms"] for r, f in zip(runs[name], runs[first], strict=True)]
        out[name] = {"passes": max(1, len(exp)), "frames": len(scanners[name].capture), "points": points[name],
                     "cameras": [f"{c.width}×{c.height}" for n, c in cfg.virtual_rig.cameras.items()
                                 if n in cfg.cameras],
                     "standing_mb": standing[name], "ratios": ratios, **med}  # fmt: skip
    return out


def bench_hdr(repeats: int) -> dict[str, Any]:
    """One exposure against :data:`HDR_EXPOSURES_US`, in one run, their scans interleaved (medians over
    ``repeats`` scans each; the latency ratio is the median of the rounds' ratios)."""
    got = asyncio.run(_interleaved({"one": (), "three": HDR_EXPOSURES_US}, repeats))
    return {"one": got["one"], "three": got["three"], "exposures_us": list(HDR_EXPOSURES_US),
            "ratio": statistics.median(got["three"]["ratios"]),
            "ratio_range": (min(got["three"]["ratios"]), max(got["three"]["ratios"]))}  # fmt: skip


def report_line(r: dict[str, Any]) -> str:
    """The README's HDR line."""
    one, three = r["one"], r["three"]
    lo, hi = r["ratio_range"]
    return (
        f"one exposure ({one['frames']} frames) against three ({', '.join(f'{e / 1000:g}' for e in r['exposures_us'])}"
        f" ms, {three['frames']} frames), cameras {' + '.join(one['cameras']) or '?'} (the default configuration's "
        f"rig), service settings, scans interleaved, {len(three['ratios'])} of each, medians: post-capture latency "
        f"(last frame to cloud) **{one['post_capture_ms']:.0f} → {three['post_capture_ms']:.0f} ms "
        f"({r['ratio']:.2f}×, the rounds' ratios {lo:.2f}–{hi:.2f}×)** of which the last decode + fusion "
        f"{one['decode_finish_ms']:.0f} → {three['decode_finish_ms']:.0f} ms; whole scan {one['scan_ms']:.0f} → "
        f"{three['scan_ms']:.0f} ms (the capture is the virtual rig's rendering: {one['capture_ms']:.0f} → "
        f"{three['capture_ms']:.0f} ms); memory: the scanner's standing buffers {one['standing_mb']:.0f} → "
        f"{three['standing_mb']:.0f} MB, peak a scan adds {one['peak_scan_mb']:.0f} → {three['peak_scan_mb']:.0f} MB; "
        f"{one['points']} → {three['points']} points."
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    print(report_line(bench_hdr(a.repeats)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
