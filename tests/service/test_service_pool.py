"""The result buffer pool: a block is leased to one set of arrays and reused only once every array and every
view derived from them is gone (explicit ownership, no reference-count reading)."""

from __future__ import annotations

import gc
import sys

import numpy as np
import pytest

from appliance.reconstruct._pool import BufferPool

SPECS = [((480, 640), np.float32), ((480, 640), np.bool_), ((1000, 3), np.float32)]


def test_arrays_have_the_shapes_and_dtypes_asked_for_and_are_writable() -> None:
    pool = BufferPool()
    a, b, c = pool.arrays(SPECS)  # type: ignore[misc]
    assert (a.shape, a.dtype, b.shape, b.dtype, c.shape) == ((480, 640), np.float32, (480, 640), np.bool_, (1000, 3))
    assert all(x.flags.c_contiguous and x.flags.writeable for x in (a, b, c))
    a[:] = 1.5
    b[:] = True
    c[:] = -2
    assert float(a.sum()) == 1.5 * a.size and bool(b.all()) and float(c.min()) == -2  # no overlap
    assert a.ctypes.data % 64 == 0 and b.ctypes.data % 64 == 0 and c.ctypes.data % 64 == 0


def test_a_block_is_reused_only_when_nothing_refers_to_it() -> None:
    pool = BufferPool(max_blocks=1)
    first = pool.arrays(SPECS)
    addr = first[0].ctypes.data
    kept_view = first[2][10:20].T  # a derived view outlives the arrays it came from
    kept_mv = memoryview(first[1])
    del first
    gc.collect()
    assert pool.leased == 1
    second = pool.arrays(SPECS)
    assert second[0].ctypes.data != addr and not np.shares_memory(second[2], kept_view)
    del second, kept_view
    gc.collect()
    assert pool.leased == 1  # the memoryview still holds the block
    del kept_mv
    gc.collect()
    assert pool.leased == 0
    third = pool.arrays(SPECS)
    assert third[0].ctypes.data == addr  # handed out again
    assert pool.leased == 1


def test_results_held_at_once_beyond_max_blocks_get_fresh_memory() -> None:
    pool = BufferPool(max_blocks=2)
    held = [pool.arrays(SPECS) for _ in range(3)]
    addrs = {h[0].ctypes.data for h in held}
    assert len(addrs) == 3 and pool.leased == 2
    held[2][0][:] = 7  # the unkept one is ordinary memory
    assert float(held[2][0][0, 0]) == 7


def test_no_reference_counts_are_read(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(obj: object) -> int:
        raise AssertionError("the pool must not depend on sys.getrefcount")

    monkeypatch.setattr(sys, "getrefcount", forbidden)
    pool = BufferPool(max_blocks=1)
    a = pool.arrays(SPECS)
    addr = a[0].ctypes.data
    del a
    gc.collect()
    assert pool.arrays(SPECS)[0].ctypes.data == addr
