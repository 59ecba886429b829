"""Counting bad input: one clear log line, a counter, and the service keeps running."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable


class DropCounter:
    """Counts dropped inputs by kind and logs them without flooding the log.

    The first ``burst`` drops of each kind are logged one line each; after that at most one
    line per ``interval_s`` per kind, saying how many more were dropped since the last line
    (a flood of 100 000 bad messages is a handful of lines, not 100 000).
    """

    def __init__(self, logger: logging.Logger, *, burst: int = 5, interval_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = logger
        self._burst = burst
        self._interval_s = interval_s
        self._clock = clock
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._said: dict[str, tuple[float, int]] = {}  #: kind → (when, count) of last line

    def drop(self, kind: str, reason: str) -> None:
        """Record one dropped input of ``kind`` (e.g. "Odometry") with a reason."""
        now = self._clock()
        with self._lock:
            self.counts[kind] += 1
            n = self.counts[kind]
            when, then = self._said.get(kind, (-float("inf"), 0))
            say = n <= self._burst or now - when >= self._interval_s
            if say:
                self._said[kind] = (now, n)
        if not say:
            return
        if n <= self._burst:
            self._log.warning("dropped bad %s (%d so far): %s", kind, n, reason)
        else:
            self._log.warning("dropped bad %s: %d more in %.0f s (%d so far), the last: %s",
                              kind, n - then, now - when, n, reason)

    @property
    def total(self) -> int:
        return sum(self.counts.values())
