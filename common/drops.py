"""Counting bad input: one clear log line, a counter, and the service keeps running."""

from __future__ import annotations

import logging
import threading
from collections import Counter


class DropCounter:
    """Counts dropped inputs by reason and logs them without flooding the log.

    The first ``burst`` drops of each kind are logged one line each, then one line every
    ``every`` drops, always with the running total.
    """

    def __init__(self, logger: logging.Logger, *, burst: int = 5, every: int = 100) -> None:
        self._log = logger
        self._burst = burst
        self._every = every
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()

    def drop(self, kind: str, reason: str) -> None:
        """Record one dropped input of ``kind`` (e.g. "Odometry") with a reason."""
        with self._lock:
            self.counts[kind] += 1
            n = self.counts[kind]
        if n <= self._burst or n % self._every == 0:
            self._log.warning("dropped bad %s (%d so far): %s", kind, n, reason)

    @property
    def total(self) -> int:
        return sum(self.counts.values())
