"""Robot drivers on the bus: the simulator, dataset replay and a serial robot.

Every driver turns a stream of ``Odometry`` / ``Observations`` / ``Truth`` messages into
publications on the robot's keys through one :class:`RobotPublisher` (docs/delivery.md):

* odometry and observations go through advanced publishers with a cache of at least the
  last 60 s and 10 000 samples (an estimator that missed some, or restarted from a
  checkpoint, recovers them), congestion control drop (the driver never waits for a slow
  consumer), and one counter over both keys, ``input_seq``, so the estimator can merge
  them in publication order exactly once (docs/protocol.md);
* truth is published plainly (nobody needs every sample of it).

At ``rate = 0`` (as fast as possible) a :class:`Pacer` keeps the driver at most a window
of inputs ahead of the ``input_stamp`` in the estimator's newest state, so a whole dataset
goes through at the estimator's speed with every input applied. :class:`RobotPublisher`
and :func:`play` live in ``common/robot_inputs.py`` (the ROS 2 bridge publishes a ROS 2
robot's inputs with them too); this module adds :class:`Fleet`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable

from slamlens.common.bus import Bus
from slamlens.common.keys import Keys
from slamlens.common.messages import Message
from slamlens.common.pacer import PACE_WINDOW
from slamlens.common.robot_inputs import INPUT_CACHE, RobotPublisher, play

__all__ = ["INPUT_CACHE", "Fleet", "RobotPublisher", "play"]


class Fleet:
    """Several robots' publishers driven as one (a simulator or a replay of several robots):
    each message goes to its robot's :class:`RobotPublisher`."""

    def __init__(self, bus: Bus, *, keys: Keys, robots: Iterable[str]) -> None:
        self.publishers = {r: RobotPublisher(bus, keys=keys, robot=r) for r in robots}

    @property
    def robots(self) -> list[str]:
        return list(self.publishers)

    @property
    def counts(self) -> dict[str, int]:
        """Messages published per type, over every robot."""
        total: dict[str, int] = {}
        for p in self.publishers.values():
            for kind, n in p.counts.items():
                total[kind] = total.get(kind, 0) + n
        return total

    @property
    def pacer(self) -> Fleet | None:
        """Itself once pacing (``drain`` then waits for every robot's estimator), else None."""
        return self if any(p.pacer is not None for p in self.publishers.values()) else None

    def pace_on_estimator(self, *, window: int = PACE_WINDOW) -> None:
        for p in self.publishers.values():
            p.pace_on_estimator(window=window)

    def publish(self, message: Message, stop: threading.Event | None = None) -> None:
        self.publishers[message.robot].publish(message, stop)  # type: ignore[attr-defined]

    def wait_for_estimator(self, stop: threading.Event, *, timeout_s: float) -> bool:
        """Wait until every robot's estimator is there (see RobotPublisher)."""
        deadline = time.monotonic() + timeout_s
        return all(p.wait_for_estimator(stop, timeout_s=max(0.1, deadline - time.monotonic()))
                   for p in self.publishers.values())

    def drain(self, stop: threading.Event, *, timeout_s: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout_s
        return all(p.pacer.drain(stop, timeout_s=max(0.0, deadline - time.monotonic()))
                   for p in self.publishers.values() if p.pacer is not None)

    def close(self) -> None:
        for p in self.publishers.values():
            p.close()
