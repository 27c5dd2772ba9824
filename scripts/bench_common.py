"""What the benchmark scripts share (``bench.py``, ``bench_stereo.py``): paths, the median timer and the
memory-read floor kernel."""

from __future__ import annotations

import functools
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def median_ms(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> tuple[float, list[float]]:
    """The median wall time of ``fn`` over ``repeats`` calls after ``warmup`` untimed ones (ms), and every time."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times), times


@functools.cache
def parallel_read_floor() -> Callable[[np.ndarray], int]:
    """A numba kernel that reads every byte of an (F, H, W) uint8 stack once with every core (a sum)."""
    from numba import njit, prange

    @njit(parallel=True, nogil=True, cache=False)
    def read_all(s: np.ndarray) -> int:  # pragma: no cover - benchmark helper
        n, h, w = s.shape
        acc = np.zeros(h, np.int64)
        for y in prange(h):
            a = 0
            for k in range(n):
                row = s[k, y]
                for x in range(w):
                    a += row[x]
            acc[y] = a
        return int(acc.sum())

    return read_all  # type: ignore[no-any-return]
