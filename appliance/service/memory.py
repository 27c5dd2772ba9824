"""Keeping the service's resident memory small on glibc: large blocks go back to the system when freed.

A scan's temporaries are tens of MB each (per-pixel float64 rays, clouds, PLY bytes). glibc's allocator
raises its mmap threshold to the largest block freed so far, after which such blocks come from the heap and
stay resident once freed (the service measured 740 MB at ready and 880 MB after 10 scans on the default
virtual rig, a third of it freed memory). :func:`tune_malloc` fixes the threshold at :data:`MMAP_THRESHOLD_B`
and caps the per-thread arenas at :data:`ARENA_MAX`; :func:`trim` hands free heap memory back (after the
warm-up and after each scan). Elsewhere than glibc both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from functools import cache

log = logging.getLogger(__name__)

MMAP_THRESHOLD_B = 1 << 20  # blocks from 1 MiB up are mapped on their own and unmapped when freed
ARENA_MAX = 2  # malloc arenas (default 8 per core: each keeps its own freed memory)

_M_ARENA_MAX = -8  # mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3


@cache
def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
    except (OSError, AttributeError):  # not glibc (musl has no mallopt / malloc_trim)
        return None
    return libc


def tune_malloc() -> bool:
    """Fix glibc's mmap threshold and arena count (once, before the big allocations); True when applied.

    ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_ARENA_MAX`` in the environment win (set by the operator).
    """
    libc = _libc()
    if libc is None:
        return False
    ok = True
    if "MALLOC_MMAP_THRESHOLD_" not in os.environ:
        ok = bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_B)) and ok
    if "MALLOC_ARENA_MAX" not in os.environ:
        ok = bool(libc.mallopt(_M_ARENA_MAX, ARENA_MAX)) and ok
    return ok


def trim() -> None:
    """Give free heap memory back to the system (a few ms; call from a thread, not the event loop)."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


def rss_mb() -> float:
    """This process's resident memory (MB), from /proc (0 where there is none)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return 0.0
    return round(pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1)
