"""The allocator's policy: freed memory kept for the next large arrays, given back on request.

**Kept** (:func:`keep_freed_memory`, called by the ``slamlens`` program before a command
runs). A service at n = 1000 allocates and frees arrays of 16–32 MB on every state (the
viewer's overview kernel, a state's payload copied out of Zenoh, the monitor's checks).
glibc's defaults hand such memory back to the system as soon as it is freed: a block
above the mmap threshold is unmapped, a thread's arena (each thread gets its own, up to
8 per core) deletes a heap that became empty, and the main heap's top is trimmed past
128 kB. The next array of that size then faults in its pages again, one 4 kB page at a
time — ~1 200 faults per state in the viewer's state thread, 7 500–8 200 a second in
the n = 1000 pipeline (``/proc/PID/stat``), each ~4 µs on this VM: the overview kernel
took 15.5 ms with its faults and 11 ms without. So every ``slamlens`` process uses one
arena (threads share the main heap), puts blocks up to glibc's ceiling for it (32 MiB)
on the heap instead of in mappings of their own, and keeps up to ``TRIM_THRESHOLD`` of
free memory at the heap's top: in the pipeline the viewer's faults fell to 1–30 a second
and the monitor's to 0 (docs/large_maps.md). The price is memory held at the process's
peak, not more: at n = 1000 the monitor keeps 1.4–2.0 GB (1.3–1.7 GB with the defaults).

**Given back** (:func:`release_freed_memory`): after a viewer dropped 40 views of 2.8 MB
pictures, their memory stays in the process (RSS) although nothing uses it.
``malloc_trim(0)`` hands free pages of every arena back (glibc ≥ 2.8 returns pages inside
the heap too, not only at its top), whatever the thresholds above. Elsewhere (musl,
macOS) both are no-ops that say so.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import time

#: ``mallopt`` parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
#: blocks up to this size come from the heap: glibc's ceiling on 64-bit (HEAP_MAX_SIZE / 2)
MMAP_THRESHOLD = 32 << 20
#: free memory at the heap's top kept for the next allocations (above it: trimmed)
TRIM_THRESHOLD = 512 << 20

_lock = threading.Lock()
_libc: ctypes.CDLL | None = None
_last = -float("inf")


def _glibc() -> ctypes.CDLL | None:
    global _libc
    if _libc is None and sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None)
            libc.malloc_trim.argtypes = [ctypes.c_size_t]
            libc.malloc_trim.restype = ctypes.c_int
            libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
            libc.mallopt.restype = ctypes.c_int
            _libc = libc
        except (OSError, AttributeError):  # not glibc
            return None
    return _libc


def release_freed_memory(*, at_most_every_s: float = 1.0) -> bool:
    """Return the allocator's free pages to the system (at most once per
    ``at_most_every_s``: it walks every arena); True if it did."""
    global _last
    libc = _glibc()
    if libc is None:
        return False
    now = time.monotonic()
    with _lock:
        if now - _last < at_most_every_s:
            return False
        _last = now
    libc.malloc_trim(0)
    return True


def keep_freed_memory() -> bool:
    """Keep freed memory in the process for the next large arrays (module docstring):
    one arena, blocks up to ``MMAP_THRESHOLD`` on the heap, up to ``TRIM_THRESHOLD`` of
    free heap top kept. Call it before the process starts threads (an arena, once made,
    stays). True if glibc took every setting."""
    libc = _glibc()
    if libc is None:
        return False
    return all([libc.mallopt(param, value) == 1 for param, value in (
        (_M_ARENA_MAX, 1), (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD))])
