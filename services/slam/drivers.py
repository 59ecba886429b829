"""Robot drivers on the bus: the simulator, dataset replay and a serial robot.

Every driver turns a stream of ``Odometry`` / ``Observations`` / ``Truth`` messages into
reliable, in-order publications on the robot's keys. All three publish through one
:class:`RobotPublisher`, so odometry and observations keep their order on the wire.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable

from common.bus import Bus
from common.keys import Keys
from common.messages import Message, Observations, Odometry, Truth

log = logging.getLogger("slamlens.driver")


class RobotPublisher:
    """Publishes a robot's messages on their SPEC §7 keys."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str) -> None:
        self.bus = bus
        self.keys = keys
        self.robot = robot
        self._pubs = {
            Odometry: bus.publisher(keys.odometry(robot)),
            Observations: bus.publisher(keys.observations(robot)),
            Truth: bus.publisher(keys.truth(robot)),
        }
        self.counts = {cls.__name__: 0 for cls in self._pubs}

    def publish(self, message: Message) -> None:
        pub = self._pubs[type(message)]
        pub.put(message.to_bytes())
        self.counts[type(message).__name__] += 1

    def wait_for_estimator(self, stop: threading.Event, *, timeout_s: float) -> bool:
        """Wait until an estimator for this robot announces itself (liveliness)."""
        key = self.keys.estimator_alive(self.robot)
        deadline = time.monotonic() + timeout_s
        said = False
        while not stop.is_set():
            if self.bus.alive(key, timeout=1.0):
                time.sleep(0.2)  # let its subscription reach every router on the path
                return True
            if not said:
                log.info("waiting for an estimator on %s", key)
                said = True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.1)
        return False


def _stamp(message: Message) -> float:
    return float(message.stamp)  # type: ignore[attr-defined]


def play(events: Iterable[Message], publisher: RobotPublisher, stop: threading.Event, *,
         rate: float, progress_every_s: float = 0.0) -> float:
    """Publish ``events`` paced at ``rate`` × their own time (0 = as fast as possible).

    Returns the wall-clock seconds it took.
    """
    start = time.monotonic()
    t0: float | None = None
    next_report = progress_every_s
    for message in events:
        if stop.is_set():
            break
        stamp = _stamp(message)
        if t0 is None:
            t0 = stamp
        if rate > 0:
            due = start + (stamp - t0) / rate
            delay = due - time.monotonic()
            if delay > 0:
                stop.wait(delay)
        publisher.publish(message)
        if progress_every_s and stamp - t0 >= next_report:
            next_report += progress_every_s
            log.info("t = %.1f s published (%s)", stamp - t0, publisher.counts)
    return time.monotonic() - start
