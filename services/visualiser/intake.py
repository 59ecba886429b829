"""What the viewer receives, kept latest-wins: bus callbacks store bytes, the viewer decodes.

A Zenoh callback only stores the raw payload and its receipt time and wakes the viewer
(O(1), no decoding), so a slow viewer never slows the estimator or the camera. Decoding
happens on the viewer's own threads; a bad payload is logged (the first few of each kind,
then one line in a hundred: :class:`~common.drops.DropCounter`), counted and dropped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from common.drops import DropCounter

log = logging.getLogger("slamlens.viewer")

T = TypeVar("T")


@dataclass(frozen=True)
class Raw:
    """One payload as it arrived."""

    payload: bytes
    received: float  #: time.monotonic() at receipt, s
    version: int  #: +1 per payload stored in its slot


class Slot:
    """The newest payload of one input (latest wins); ``take`` returns each one once."""

    def __init__(self, name: str, wake: Callable[[], None]) -> None:
        self.name = name
        self._wake = wake
        self._lock = threading.Lock()
        self._raw: Raw | None = None
        self._taken = 0
        self.received_count = 0

    def offer(self, payload: bytes, *, received: float | None = None) -> None:
        """Store ``payload`` (called on a Zenoh thread: no work beyond this)."""
        with self._lock:
            self.received_count += 1
            self._raw = Raw(payload, time.monotonic() if received is None else received,
                            self.received_count)
        self._wake()

    def offer_if_empty(self, payload: bytes) -> bool:
        """Store a late-join reply unless a live sample already arrived."""
        with self._lock:
            if self._raw is not None:
                return False
        self.offer(payload)
        return True

    def take(self) -> Raw | None:
        """The newest payload if it was not taken before, else None."""
        with self._lock:
            raw = self._raw
            if raw is None or raw.version == self._taken:
                return None
            self._taken = raw.version
            return raw


class Queue:
    """A bounded FIFO of payloads (health: every verdict counts for the time series)."""

    def __init__(self, name: str, wake: Callable[[], None], *, maxlen: int = 512) -> None:
        self.name = name
        self._wake = wake
        self._items: deque[Raw] = deque(maxlen=maxlen)  # oldest dropped when the viewer lags
        self._lock = threading.Lock()
        self.received_count = 0

    def offer(self, payload: bytes) -> None:
        with self._lock:
            self.received_count += 1
            self._items.append(Raw(payload, time.monotonic(), self.received_count))
        self._wake()

    def drain(self) -> list[Raw]:
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


def decode(source: str, raw: Raw, decoder: Callable[[bytes], T], drops: DropCounter) -> T | None:
    """``decoder(raw.payload)``, or None (counted and logged) when it is malformed."""
    try:
        return decoder(raw.payload)
    except Exception as exc:  # any decoder failure is a bad message, never a crash
        drops.drop(source, str(exc))
        return None


class RateMeter:
    """Events per second over a sliding window (frame rates in the status line)."""

    def __init__(self, window_s: float = 2.0) -> None:
        self._window = window_s
        self._times: deque[float] = deque()
        self._lock = threading.Lock()

    def tick(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._times.append(now)
            self._trim(now)

    def rate(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._trim(now)
            if len(self._times) < 2:
                return 0.0
            # (count − 1) intervals over the span between first and last event in the window
            return (len(self._times) - 1) / max(self._times[-1] - self._times[0], 1e-6)

    def _trim(self, now: float) -> None:
        while self._times and now - self._times[0] > self._window:
            self._times.popleft()
