"""``scripts/bench --against REV``: the reference workload's timings of this tree and of a git revision, in one run.

The revision is checked out into a temporary git worktree (its own numba cache); the two benchmarks then run in
turns, ``--rounds`` times each (old, new, old, new, ...), so that a machine that slows down or speeds up during
the run weighs on both alike. Prints, per timing, the median over the rounds of each side and their ratio
(new / old: below 1 is faster). Each side's run is its own ``scripts/bench.py --skip ... --json`` process, so the
revision's own code is measured, not this tree's with its data.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench_common import REPO

#: Everything but the reference workload (decode, triangulate, the memory floors) is skipped on both sides.
SKIP = ["opencv", "stereo", "accuracy", "service", "hdr"]


def _run(tree: Path, cache: Path, repeats: int, out: Path) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(cache)}
    cmd = [sys.executable, str(tree / "scripts" / "bench.py"), "--repeats", str(repeats), "--skip", *SKIP,
           "--json", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise SystemExit(f"bench --against: the benchmark of {tree} failed: {tail[0]}")
    raw = json.loads(out.read_text())
    ref = raw.get("reference", {})
    return {k: float(v) for k, v in ref.items() if k.endswith("_ms") and isinstance(v, int | float)}


def compare(rev: str, rounds: int, repeats: int) -> int:
    """Benchmark ``rev`` and this tree in turns; print the medians and ratios. Returns the exit status."""
    sha = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=REPO, capture_output=True,
                         text=True, check=False)  # fmt: skip
    if sha.returncode != 0:
        print(f"bench --against: {rev!r} is not a commit of {REPO}: give a revision such as HEAD~1", file=sys.stderr)
        return 2
    commit = sha.stdout.strip()
    work = Path(tempfile.mkdtemp(prefix="scan3d-bench-"))
    tree = work / "tree"
    try:
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), commit], cwd=REPO, check=True,
                       capture_output=True)  # fmt: skip
        sides: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
        for r in range(rounds):
            for side, root in (("old", tree), ("new", REPO)):
                res = _run(root, work / f"cache-{side}", repeats, work / f"{side}-{r}.json")
                sides[side].append(res)
                print(f"round {r + 1}/{rounds} {side}: decode_triangulate_ms {res.get('decode_triangulate_ms', 0):.1f}",
                      flush=True)  # fmt: skip
        keys = [k for k in sides["new"][0] if all(k in s for s in sides["old"] + sides["new"])]
        print(f"\nthis tree against {rev} ({commit[:10]}): median of {rounds} rounds, each the median of {repeats}")
        print("| timing | old ms | new ms | new / old |")
        print("|---|---|---|---|")
        for k in keys:
            old = sorted(s[k] for s in sides["old"])[rounds // 2]
            new = sorted(s[k] for s in sides["new"])[rounds // 2]
            print(f"| {k} | {old:.1f} | {new:.1f} | {new / old:.3f} |")
        return 0
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, capture_output=True,
                       check=False)  # fmt: skip
        shutil.rmtree(work, ignore_errors=True)
