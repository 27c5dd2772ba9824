"""Reuse of large result buffers once their caller has dropped them (private).

Results of a scan (decoded maps, point clouds) are fresh arrays the caller owns. Allocating ~200 MB of
them per scan costs first-touch page faults (~0.1-0.2 ms per MB, more in VMs that hand freed memory back
to the host), a large share of the reconstruction time. A :class:`BufferPool` hands out arrays that are
views of a few blocks it keeps; a block is handed out again only when nothing outside the pool refers
to it any more (every view of an array, however derived, keeps its block referenced).
"""

from __future__ import annotations

import sys
import threading

import numpy as np
import numpy.typing as npt

_ALIGN = 64


class BufferPool:
    """Blocks of bytes reused once unreferenced.

    Parameters
    ----------
    max_blocks : int
        Most blocks kept (callers holding several results at once get fresh memory beyond this).
    """

    def __init__(self, max_blocks: int = 2) -> None:
        self._blocks: list[npt.NDArray[np.uint8]] = []
        self._max_blocks = max_blocks
        self._lock = threading.Lock()

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
        block = self._take(max(size, _ALIGN))
        return [
            np.ndarray(shape, dtype, buffer=block, offset=off)
            for (shape, dtype), off in zip(specs, offsets, strict=True)
        ]

    def _take(self, size: int) -> npt.NDArray[np.uint8]:
        with self._lock:
            # references to a free block: the list and getrefcount's argument; each carved array adds one
            free = [i for i in range(len(self._blocks)) if sys.getrefcount(self._blocks[i]) == 2]
            for i in free:
                if self._blocks[i].size >= size:
                    return self._blocks[i]
            fresh = np.empty(size + size // 8, np.uint8)  # slack: the next scan may be a little larger
            if len(self._blocks) < self._max_blocks:
                self._blocks.append(fresh)
            elif free:
                self._blocks[free[0]] = fresh  # replaces a free block that was too small
            return fresh
