"""Large arrays recycled once nobody else holds them (no fresh memory per block).

A fresh multi-megabyte numpy array is fresh memory from the operating system: thousands of page
faults (or a few huge-page faults) and the zeroing of every page, by whichever thread first writes
it. In a streaming loop that allocates one such array per block (the simulator's spike blocks, a
reader's rate chunks) this costs about as much as a memset of the block, several times over on a
virtual machine, and on a 2-core machine it is taken from the kernel's own cores. A
:class:`RecyclingPool` hands back an array of the same shape once every other reference to it is
gone, so the memory stays mapped and warm.
"""

from __future__ import annotations

import sys

import numpy as np


class RecyclingPool:
    """Arrays of one dtype, handed out again once nobody but the pool holds them.

    ``take(shape)`` returns an array of ``shape`` whose contents are undefined: a recycled one when
    an array of that shape has no reference left but the pool's (views count: they hold their
    ``base``), else a new one (the pool keeps the ``keep`` newest). The "no reference left" test is
    a reference count measured at construction in the loop that :meth:`take` runs, not assumed, so
    an interpreter that counts differently cannot make the pool hand out an array still in use;
    recycling is off where reference counts are deferred (free-threaded builds), where
    :meth:`take` always allocates.

    Callers must take from one thread at a time (each reader or simulator owns its pool).
    """

    def __init__(self, dtype=np.float32, keep: int = 6):
        self.dtype = np.dtype(dtype)
        self.keep = int(keep)
        self.arrays: list[np.ndarray] = []
        self.recycled = 0  # how many takes were served by a recycled array (diagnostics and tests)
        self._free = self._free_count() if getattr(sys, "_is_gil_enabled", lambda: True)() else None

    def _free_count(self) -> int:
        # what sys.getrefcount reports, in the same loop as take's, for an array nobody else holds
        # (the pool's list, the loop variable, the call's argument: 3 on CPython 3.11-3.13)
        probe = [np.empty(1, self.dtype)]
        count = None
        for a in probe:
            count = sys.getrefcount(a)
        return count

    def take(self, shape) -> np.ndarray:
        """An array of ``shape`` and the pool's dtype, contents undefined."""
        shape = tuple(int(s) for s in shape)
        for a in self.arrays if self._free is not None else ():
            if a.shape == shape and sys.getrefcount(a) == self._free:
                self.recycled += 1
                return a
        return self._add(np.empty(shape, self.dtype))

    def _add(self, a: np.ndarray) -> np.ndarray:
        if len(self.arrays) >= self.keep:
            self.arrays.pop(0)
        self.arrays.append(a)
        return a

    def reserve(self, shape, count: int):
        """Add ``count`` arrays of ``shape`` to the pool now and fault their memory in on a helper thread.

        For memory a stream will need soon, made while a core is idle (a command's start-up) instead of
        in the middle of the work: fresh memory costs its first writer the page faults and the zeroing,
        0.4-8 GB/s on the project's VM (memory returned to the host is faulted in again). The helper
        writes zeros over each array (``ctypes.memset``, which runs without the GIL) and holds it until
        then, so :meth:`take` cannot hand out an array it is still writing (it makes a new one instead).
        Call it from the thread that takes, or before any other thread takes. Returns the helper thread
        (None when nothing is reserved).
        """
        shape = tuple(int(s) for s in shape)
        count = min(int(count), self.keep)
        if count < 1 or self._free is None or not all(shape):
            return None
        import threading
        fresh = [self._add(np.empty(shape, self.dtype)) for _ in range(count)]
        th = threading.Thread(target=_fault_in, args=(fresh,), name="r2s-prefault", daemon=True)
        th.start()
        return th


def _fault_in(arrays: list) -> None:
    """Write zeros over each array of ``arrays``, dropping each (from the list, too) once written."""
    import ctypes
    while arrays:
        a = arrays.pop(0)
        ctypes.memset(a.__array_interface__["data"][0], 0, a.nbytes)  # no GIL held while it runs
        del a
