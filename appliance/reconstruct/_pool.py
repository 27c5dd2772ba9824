"""Reuse of large result buffers once their caller has dropped them (private).

Results of a scan (decoded maps, point clouds) are fresh arrays the caller owns. Allocating ~200 MB of
them per scan costs first-touch page faults (~0.1-0.2 ms per MB, more in VMs that hand freed memory back
to the host), a large share of the reconstruction time. A :class:`BufferPool` hands out arrays carved from a
few blocks it keeps.

Ownership is explicit: each hand-out is a *lease* of one block. Every array of a lease is made through the
array interface of a small holder that refers to the lease, so the array, and every view derived from it
(slices, reshapes, transposes, memoryviews), keeps the lease alive. When the last of them is gone the lease's
finaliser returns the block to the pool; until then the block is marked leased and never handed out again.
No reference counts are read (``sys.getrefcount`` values are an implementation detail of CPython).
"""

from __future__ import annotations

import gc
import threading
import weakref
from typing import Any

import numpy as np
import numpy.typing as npt

_ALIGN = 64


class _Lease:
    """One hand-out of a block; the block is free again when this object is gone."""

    __slots__ = ("__weakref__", "block")

    def __init__(self, block: npt.NDArray[np.uint8]) -> None:
        self.block = block


class _Holder:
    """Gives numpy one array of a lease (its ``base``), and keeps the lease alive."""

    __slots__ = ("__array_interface__", "lease")

    def __init__(self, lease: _Lease, interface: dict[str, Any]) -> None:
        self.lease = lease
        self.__array_interface__ = interface


class BufferPool:
    """Blocks of bytes, each leased to one set of arrays at a time and reused once they are all gone.

    Parameters
    ----------
    max_blocks : int
        Most blocks kept (callers holding several results at once get fresh memory beyond this).
    """

    def __init__(self, max_blocks: int = 2) -> None:
        self._blocks: list[npt.NDArray[np.uint8]] = []
        self._leased: set[int] = set()  # indices into _blocks that are leased
        self._max_blocks = max_blocks
        self._lock = threading.RLock()  # a finaliser may run inside _take (a garbage collection)

    @property
    def leased(self) -> int:
        """How many kept blocks are leased now."""
        with self._lock:
            return len(self._leased)

    @property
    def nbytes(self) -> int:
        """Bytes held by the kept blocks."""
        with self._lock:
            return sum(b.nbytes for b in self._blocks)

    def arrays(
        self, specs: list[tuple[tuple[int, ...], type]]
    ) -> list[npt.NDArray[np.generic]]:
        """C-contiguous uninitialised arrays of the given (shape, dtype), carved from one free block."""
        offsets = []
        size = 0
        for shape, dtype in specs:
            offsets.append(size)
            nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
            size += -(-nbytes // _ALIGN) * _ALIGN
        lease = self._take(max(size, _ALIGN) + _ALIGN)
        start = int(lease.block.__array_interface__["data"][0])
        base = start + (-start) % _ALIGN  # every array starts on a 64-byte boundary
        out = []
        for (shape, dtype), off in zip(specs, offsets, strict=True):
            iface = {"version": 3, "shape": tuple(int(s) for s in shape), "typestr": np.dtype(dtype).str,
                     "data": (base + off, False), "strides": None}
            out.append(np.asarray(_Holder(lease, iface)))
        return out

    def _take(self, size: int) -> _Lease:
        with self._lock:
            if self._leased and not any(i not in self._leased and b.size >= size for i, b in enumerate(self._blocks)):
                # a result its caller dropped into a reference cycle (an asyncio task's, say) holds its lease
                # until the cyclic collector runs: run it now, not allocate a block beside it (the service's
                # two-camera peak was 75 MB higher, one cloud, whenever the collector had not run between scans)
                gc.collect()
            free = [i for i in range(len(self._blocks)) if i not in self._leased]
            for i in free:
                if self._blocks[i].size >= size:
                    return self._lease(i)
            fresh = np.empty(size + size // 8, np.uint8)  # slack: the next scan may be a little larger
            if len(self._blocks) < self._max_blocks:
                self._blocks.append(fresh)
                return self._lease(len(self._blocks) - 1)
            if free:
                self._blocks[free[0]] = fresh  # replaces a free block that was too small
                return self._lease(free[0])
            return _Lease(fresh)  # every kept block is leased: plain memory, not kept

    def _lease(self, index: int) -> _Lease:
        lease = _Lease(self._blocks[index])
        self._leased.add(index)
        weakref.finalize(lease, self._give_back, index, self._blocks[index])
        return lease

    def _give_back(self, index: int, block: npt.NDArray[np.uint8]) -> None:
        with self._lock:
            if index < len(self._blocks) and self._blocks[index] is block:
                self._leased.discard(index)
