"""``slamlens.common.arrays.RecycledBuffers``: a buffer is reused, or reclaimed to change in place,
only when nothing else can read it."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.arrays import RecycledBuffers, bytes_backed_array


def _published(pool: RecycledBuffers) -> np.ndarray:
    a = pool.array((5, 5), "<f8")
    a[...] = np.arange(25.0).reshape(5, 5)
    a.flags.writeable = False  # as a message's matrix
    return a


def test_an_array_nobody_else_holds_is_reclaimed_as_the_same_memory() -> None:
    pool = RecycledBuffers()
    a = _published(pool)
    address = a.ctypes.data
    b = pool.reclaim(a, holders=1)
    assert b is not None and b.flags.writeable and b.ctypes.data == address
    np.testing.assert_array_equal(b, np.arange(25.0).reshape(5, 5))  # contents kept


@pytest.mark.parametrize("holder", ["view", "transpose", "memoryview", "list", "name",
                                    "another array on the buffer"])
def test_an_array_anything_else_can_read_is_not_reclaimed(holder: str) -> None:
    pool = RecycledBuffers()
    a = _published(pool)
    held = {"view": lambda: a[1:], "transpose": lambda: a.T, "memoryview": lambda: memoryview(a),
            "list": lambda: [a], "name": lambda: a,
            "another array on the buffer": lambda: np.frombuffer(pool._buffers[-1])}[holder]()
    assert pool.reclaim(a, holders=1) is None
    del held


def test_the_callers_own_references_are_counted_as_said() -> None:
    pool = RecycledBuffers()
    a = _published(pool)
    also = a  # the caller's second reference, declared
    assert pool.reclaim(a, holders=2) is not None
    del also


def test_an_array_not_from_the_pool_is_never_reclaimed() -> None:
    pool = RecycledBuffers()
    assert pool.reclaim(bytes_backed_array((3, 3), "<f8"), holders=1) is None
    assert pool.reclaim(np.zeros((3, 3)), holders=1) is None
