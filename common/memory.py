"""Giving freed memory back to the system.

glibc's allocator keeps memory a process freed for its next allocations: after a viewer
dropped 40 views of 2.8 MB pictures, their memory stays in the process (RSS) although
nothing uses it. ``malloc_trim(0)`` hands free pages of every arena back (glibc ≥ 2.8
returns pages inside the heap too, not only at its top). Elsewhere (musl, macOS) it is
a no-op that says so.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import time

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
