"""The queue behind every bus channel: in order, fed by a subscriber callback that never
waits, bounded by memory (counted), latest-wins on request (:meth:`Bus.channel`)."""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from slamlens.common.bus import DEFAULT_QUEUE_BYTES, Sample

log = logging.getLogger("slamlens.common.bus")

_LOST_LOG_EVERY = 1000


@dataclass(eq=False)
class _Deferred:
    """A large sample left in Zenoh's buffer until it is taken (``newest_above``)."""

    sample: Sample  #: key and timestamp; the payload is fetched when taken
    fetch: Callable[[], bytes]
    size: int

    def resolve(self) -> Sample:
        s = self.sample
        return Sample(s.key, self.fetch(), source=s.source, time=s.time)


def _size(item: Sample | _Deferred) -> int:
    return item.size if isinstance(item, _Deferred) else len(item.payload)


class QueueChannel:
    """An in-order queue of samples fed by a subscriber callback; ``push`` never blocks.

    ``recv`` wakes the moment a sample arrives (no polling). With ``capacity`` (1 = latest
    wins) the oldest samples beyond it are dropped; otherwise the queue grows until its
    payloads hold ``max_bytes``, then drops its oldest — counted in ``dropped`` and logged —
    rather than ever making the feeding (Zenoh) thread wait. A sample pushed with
    :meth:`push_newest` (a large one) is copied only when taken, and replaces an older one of
    its key still waiting (counted in ``superseded``): the queue holds at most one such
    payload per key, so it pins at most that much of the publisher's shared memory.
    """

    def __init__(self, *, name: str = "", capacity: int | None = None,
                 max_bytes: int = DEFAULT_QUEUE_BYTES) -> None:
        self.name = name
        self._items: deque[Sample | _Deferred] = deque()
        self._newest: dict[str, _Deferred] = {}  #: the deferred sample waiting, per key
        self._superseded = 0
        self._capacity = None if capacity is None else max(1, capacity)
        self._max_bytes = max(1, max_bytes)
        self._bytes = 0
        self._cond = threading.Condition()
        self._closed = False
        self._dropped = 0
        self._lost = 0
        self.received = 0  #: samples pushed in all
        self.high_water = 0  #: the largest backlog seen
        self._on_close: list[Callable[[], None]] = []

    @property
    def backlog(self) -> int:
        return len(self._items)

    @property
    def backlog_bytes(self) -> int:
        """Payload bytes received and not yet taken."""
        return self._bytes

    def take_all(self) -> list[Sample]:
        """Everything queued now, oldest first, without waiting."""
        with self._cond:
            items, self._items = list(self._items), deque()
            self._bytes = 0
            self._newest.clear()
        return [x.resolve() if isinstance(x, _Deferred) else x for x in items]

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def lost(self) -> int:
        return self._lost

    @property
    def superseded(self) -> int:
        return self._superseded

    def count_lost(self, n: int) -> None:
        """Record ``n`` samples known to be missed for good (sample-miss detection)."""
        with self._cond:
            self._lost += n
            total = self._lost
        if total == n or total // _LOST_LOG_EVERY != (total - n) // _LOST_LOG_EVERY:
            log.warning("%s: %d sample(s) missed and not recoverable (%d so far)",
                        self.name or "channel", n, total)

    def push_newest(self, sample: Sample, fetch: Callable[[], bytes], size: int) -> None:
        """Queue a large sample whose payload (``size`` bytes) ``fetch`` copies when it is
        taken; an older one of its key still waiting is dropped, uncopied (``superseded``)."""
        self.push(_Deferred(sample, fetch, size))

    def push(self, sample: Sample | _Deferred) -> None:
        overflow = False
        with self._cond:
            if self._closed:
                return
            if isinstance(sample, _Deferred):
                older = self._newest.pop(sample.sample.key, None)
                if older is not None:
                    self._items.remove(older)
                    self._bytes -= older.size
                    self._superseded += 1
                self._newest[sample.sample.key] = sample
            self._items.append(sample)
            self._bytes += _size(sample)
            self.received += 1
            if self._capacity is not None:
                while len(self._items) > self._capacity:
                    self._forget(self._items.popleft())
                    self._dropped += 1
            else:
                while self._bytes > self._max_bytes and len(self._items) > 1:
                    self._forget(self._items.popleft())
                    self._dropped += 1
                    overflow = True
            if len(self._items) > self.high_water:
                self.high_water = len(self._items)
            dropped = self._dropped
            self._cond.notify()
        if overflow and (dropped == 1 or dropped % _LOST_LOG_EVERY == 0):
            log.warning("%s: queue over %d MB, oldest samples dropped (%d so far)",
                        self.name or "channel", self._max_bytes >> 20, dropped)

    def _forget(self, item: Sample | _Deferred) -> None:
        """Account for ``item`` leaving the queue (under the lock)."""
        self._bytes -= _size(item)
        if isinstance(item, _Deferred) and self._newest.get(item.sample.key) is item:
            del self._newest[item.sample.key]

    def recv(self, timeout: float | None = None) -> Sample | None:
        with self._cond:
            if not self._cond.wait_for(lambda: self._items or self._closed, timeout):
                return None
            if not self._items:
                return None
            item = self._items.popleft()
            self._forget(item)
        return item.resolve() if isinstance(item, _Deferred) else item

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._items.clear()
            self._newest.clear()
            self._bytes = 0
            self._cond.notify_all()
        for undeclare in reversed(self._on_close):
            try:
                undeclare()
            except Exception:  # already gone with the session
                pass
