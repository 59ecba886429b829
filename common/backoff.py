"""Reconnecting with back-off: when to retry a lost device, and one log line per outage.

A camera, a video stream or a serial port can vanish and come back. Its owner reports
each failure (a failed open, or a working connection that broke) and each success (data
flowed again) to a :class:`Backoff`, and before each attempt asks :meth:`Backoff.wait_s`.
Retries follow a capped exponential back-off — after ``initial_s``, then twice that, … up
to ``max_s`` — so a missing device is polled gently; a success starts it over. An outage
is logged as one warning (its first failure) and one info line (the recovery); the
attempts in between only at debug level, and counted.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable


class Backoff:
    """Retry schedule and outage bookkeeping of one device named ``name`` in log lines."""

    def __init__(self, name: str, *, logger: logging.Logger, initial_s: float = 0.25,
                 max_s: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.initial_s = initial_s
        self.max_s = max_s
        self._log = logger
        self._clock = clock
        self._delay_s = initial_s  # the wait after the next failure
        self._retry_at = -float("inf")  # clock time of the next allowed attempt
        self.in_outage = False  #: failing since the last success
        self.failures = 0  #: failures reported (failed attempts and broken connections)
        self.outages = 0  #: times the device vanished
        self.recoveries = 0  #: times it came back

    def wait_s(self) -> float:
        """Seconds until the next attempt is due (0: try now)."""
        return max(0.0, self._retry_at - self._clock())

    def failed(self, reason: object) -> float:
        """Count a failure, log it (a warning if it starts an outage) and schedule the next
        attempt; returns the seconds until then."""
        self.failures += 1
        wait = self._delay_s
        if not self.in_outage:
            self.in_outage = True
            self.outages += 1
            self._log.warning("%s lost: %s; retrying with back-off up to %.1f s",
                              self.name, reason, self.max_s)
        else:
            self._log.debug("%s still unavailable: %s (next attempt in %.2f s)",
                            self.name, reason, wait)
        self._retry_at = self._clock() + wait
        # double each failure up to the cap: a missing device is polled gently
        self._delay_s = min(self._delay_s * 2.0, self.max_s)
        return wait

    def succeeded(self) -> None:
        """The device works: retries start from ``initial_s`` again; an outage ends."""
        self._delay_s = self.initial_s
        if self.in_outage:
            self.in_outage = False
            self.recoveries += 1
            self._log.info("%s is back after %d failed attempts", self.name, self.failures)
