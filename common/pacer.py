"""Pacing a producer on the estimator: at most a window of inputs ahead of its ``input_stamp``.

SPEC §7a: at ``--rate 0`` the drivers (``sim``, ``replay``) and ``slamlens play --inputs-only``
stay at most :data:`PACE_WINDOW` inputs ahead of the ``input_stamp`` in the estimator's newest
state, so a whole run goes through at the estimator's speed with every input applied (moved
here unchanged from ``services/slam/drivers.py`` so that both services use the same one).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from common.bus import Bus
from common.errors import MessageError
from common.keys import Keys
from common.messages import peek_fields

log = logging.getLogger("slamlens.driver")

#: inputs a driver at full speed stays ahead of the estimator
PACE_WINDOW = 200


class Pacer:
    """Holds a driver back to ``window`` inputs ahead of the estimator's ``input_stamp``.

    It watches the robot's state key (latest wins) and reads only the state's header; the
    stamps of the inputs still unapplied are kept in publication order.
    """

    def __init__(self, bus: Bus, *, keys: Keys, robot: str, window: int = PACE_WINDOW,
                 stall_log_s: float = 10.0) -> None:
        self.window = max(1, int(window))
        self._states = bus.channel(keys.state(robot), latest_wins=True)
        self._pending: deque[float] = deque()
        self._acked = float("-inf")
        self._epoch: int | None = None
        self._stall_log_s = stall_log_s
        self.waited_s = 0.0

    def _take(self, timeout: float) -> bool:
        sample = self._states.recv(timeout=timeout)
        if sample is None:
            return False
        try:
            head = peek_fields(sample.payload, ("epoch", "input_stamp", "stamp"))
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

    def before(self, stamp: float, stop: threading.Event) -> None:
        """Wait (until ``stop``) while ``window`` inputs are unapplied, then count one more."""
        started = time.monotonic()
        said = started
        while len(self._pending) >= self.window and not stop.is_set():
            self._take(0.2)
            if time.monotonic() - said >= self._stall_log_s:
                said = time.monotonic()
                log.warning("the estimator applied nothing for %.0f s (input stamp %.3f); "
                            "holding %d inputs", said - started, self._acked,
                            len(self._pending))
        self._take(0.0)
        self.waited_s += time.monotonic() - started
        self._pending.append(stamp)

    def drain(self, stop: threading.Event, *, timeout_s: float = 10.0) -> bool:
        """Wait until the estimator applied everything published (or ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while self._pending and not stop.is_set() and time.monotonic() < deadline:
            self._take(0.2)
        return not self._pending

    def close(self) -> None:
        self._states.close()
