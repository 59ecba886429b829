"""Pacing a producer on the estimator: at most a window of inputs ahead of its ``input_stamp``.

At ``--rate 0`` (docs/delivery.md) the drivers (``sim``, ``replay``) and ``slamlens play
--inputs-only`` stay at most :data:`PACE_WINDOW` inputs ahead of the ``input_stamp`` in the
estimator's newest state, so a whole run goes through at the estimator's speed with every
input applied (the drivers and the player use this one).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from slamlens.common.bus import Bus
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import peek_fields

log = logging.getLogger("slamlens.driver")

#: inputs a driver at full speed stays ahead of the estimator
PACE_WINDOW = 200


class Pacer:
    """Holds a driver back to ``window`` inputs ahead of the estimator's ``input_stamp``.

    The stamps of the inputs not yet applied are kept in publication order. When ``window``
    of them wait, the pacer asks the estimator where it is (a ``get`` on
    ``slamlens/robot/R/state?header``: the newest state's header only, not the map) until
    half of them are applied, so the estimator always has work queued and the driver never
    receives the states it does not need.
    """

    def __init__(self, bus: Bus, *, keys: Keys, robot: str, window: int = PACE_WINDOW,
                 stall_log_s: float = 10.0, poll_s: float = 0.001) -> None:
        self.window = max(2, int(window))
        self._bus = bus
        self._key = keys.state(robot) + "?header"
        self._pending: deque[float] = deque()
        self._acked = float("-inf")
        self._epoch: int | None = None
        self._stall_log_s = stall_log_s
        self._poll_s = poll_s
        self.waited_s = 0.0
        self.polls = 0

    def _poll(self) -> bool:
        """Ask the estimator for its newest state's header; False if none answered."""
        self.polls += 1
        replies = self._bus.get(self._key, timeout=1.0)
        if not replies:
            return False
        try:
            head = peek_fields(replies[0].payload, ("epoch", "input_stamp", "stamp"))
        except MessageError:
            return False
        stamp = head.get("input_stamp", head.get("stamp"))
        if isinstance(stamp, (int, float)):
            epoch = head.get("epoch")
            if epoch != self._epoch:
                if self._epoch is not None:  # a new map starts from what comes next
                    self._pending.clear()
                self._epoch = epoch if isinstance(epoch, int) else None
            self._acked = float(stamp)
        while self._pending and self._pending[0] <= self._acked:
            self._pending.popleft()
        return True

    def _wait_below(self, level: int, stop: threading.Event, *, deadline: float) -> None:
        started = said = time.monotonic()
        while len(self._pending) > level and not stop.is_set() \
                and time.monotonic() < deadline:
            answered = self._poll()
            if len(self._pending) > level:
                stop.wait(self._poll_s if answered else 0.2)
            if time.monotonic() - said >= self._stall_log_s:
                said = time.monotonic()
                log.warning("the estimator applied nothing for %.0f s (input stamp %.3f); "
                            "holding %d inputs", said - started, self._acked,
                            len(self._pending))
        self.waited_s += time.monotonic() - started

    def before(self, stamp: float, stop: threading.Event) -> None:
        """Wait (until ``stop``) while ``window`` inputs are unapplied, then count one more."""
        if len(self._pending) >= self.window:
            self._wait_below(self.window // 2, stop, deadline=float("inf"))
        self._pending.append(stamp)

    def drain(self, stop: threading.Event, *, timeout_s: float = 10.0) -> bool:
        """Wait until the estimator applied everything published, or until it applied
        nothing for ``timeout_s``: a driver that exits takes its cache (the inputs the
        estimator may still recover) with it, so an estimator slowed by a loaded machine is
        waited for as long as it makes progress."""
        while self._pending and not stop.is_set():
            before = len(self._pending)
            self._wait_below(0, stop, deadline=time.monotonic() + timeout_s)
            if len(self._pending) >= before:  # nothing applied for timeout_s
                break
        return not self._pending

    def close(self) -> None:
        """Nothing to undeclare (the pacer only queries)."""
