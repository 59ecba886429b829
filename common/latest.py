"""Keep the newest: a one-item slot that a producer overwrites and a consumer empties.

The latest-wins buffer of every place where only the newest input matters (a camera
frame, a state to draw, an image to register): ``put`` never blocks and never fails, so
it is safe on a Zenoh callback thread; an item nobody took before the next ``put`` is
dropped and counted. A consumer either blocks in ``take(timeout)`` (it is woken by the
next ``put``) or, waiting for several inputs at once, is woken by ``on_put`` and polls
each slot with ``take()``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class Latest(Generic[T]):
    """The newest item of one input; ``take`` hands each item out once.

    ``dropped`` counts the items replaced before anybody took them, ``count`` every item
    put. After ``close`` a ``put`` is ignored and ``take`` returns None at once.
    """

    def __init__(self, *, on_put: Callable[[], None] | None = None) -> None:
        self._on_put = on_put
        self._cond = threading.Condition(threading.Lock())
        self._item: T | None = None
        self._full = False  # an item was put and not taken yet (the item itself may be falsy)
        self._closed = False
        self.dropped = 0  #: items overwritten before they were taken
        self.count = 0  #: items put so far

    def put(self, item: T) -> None:
        """Store ``item``, replacing (and counting) one that was not taken yet."""
        with self._cond:
            if self._closed:
                return
            if self._full:
                self.dropped += 1
            self._item, self._full = item, True
            self.count += 1
            self._cond.notify()
        if self._on_put is not None:
            self._on_put()

    def take(self, timeout: float | None = 0.0) -> T | None:
        """The newest item not taken before, waiting up to ``timeout`` s for one (0: do not
        wait, None: until one comes or the slot is closed); None if there is none."""
        with self._cond:
            if not self._full and not self._closed and timeout != 0.0:
                self._cond.wait_for(lambda: self._full or self._closed, timeout)
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            return item

    def close(self) -> None:
        """Wake every waiter; from now on nothing is stored."""
        with self._cond:
            self._closed = True
            self._item, self._full = None, False
            self._cond.notify_all()
