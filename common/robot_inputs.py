"""A robot's inputs on the bus, as every driver publishes them (docs/delivery.md).

:class:`RobotPublisher` puts odometry and observations through advanced publishers with a
cache of at least the last 60 s and 10 000 samples (an estimator that missed some, or
restarted from a checkpoint, recovers them), congestion control drop (the driver never waits
for a slow consumer), and one counter over both keys, ``input_seq``, so the estimator merges
them in publication order exactly once (docs/protocol.md); truth is published plainly.
:func:`play` paces a stream of messages at a rate × their own time. Used by the drivers of
``services/slam/drivers.py`` and by the ROS 2 bridge (moved here unchanged from
``drivers.py`` so that both services publish inputs the same way).
"""

from __future__ import annotations

import copy
import logging
import threading
import time
from collections.abc import Iterable
from typing import Any, Protocol

from slamlens.common.bus import Bus
from slamlens.common.keys import Keys
from slamlens.common.messages import Message, Observations, Odometry, Truth
from slamlens.common.pacer import PACE_WINDOW, Pacer

log = logging.getLogger("slamlens.driver")

#: samples each input publisher caches (at least 10 000 and 60 s of inputs, docs/delivery.md)
INPUT_CACHE = 10_000
class RobotPublisher:
    """Publishes a robot's messages on their keys (``common/keys.py``), numbering the inputs."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str) -> None:
        self.bus = bus
        self.keys = keys
        self.robot = robot
        self._pubs = {
            Odometry: bus.publisher(keys.odometry(robot), cache=INPUT_CACHE),
            Observations: bus.publisher(keys.observations(robot), cache=INPUT_CACHE),
            Truth: bus.publisher(keys.truth(robot)),
        }
        self.counts = {cls.__name__: 0 for cls in self._pubs}
        self.input_seq = 0  #: inputs numbered so far (the last input_seq given)
        self.pacer: Pacer | None = None

    def pace_on_estimator(self, *, window: int = PACE_WINDOW) -> Pacer:
        """From now on, stay ``window`` inputs ahead of the estimator (``rate = 0``)."""
        self.pacer = Pacer(self.bus, keys=self.keys, robot=self.robot, window=window)
        return self.pacer

    def publish(self, message: Message, stop: threading.Event | None = None) -> None:
        if isinstance(message, (Odometry, Observations)):
            if self.pacer is not None:
                self.pacer.before(message.stamp, stop or threading.Event())
            self.input_seq += 1
            # a copy with the number set: the rest was validated when it was built
            # (dataclasses.replace would validate every field again: 30 % of a replay)
            message = copy.copy(message)
            object.__setattr__(message, "input_seq", self.input_seq)
        self._pubs[type(message)].put(message.to_bytes())
        self.counts[type(message).__name__] += 1

    def wait_for_estimator(self, stop: threading.Event, *, timeout_s: float) -> bool:
        """Wait until an estimator for this robot announces itself (liveliness) and its
        input subscription reaches us (Zenoh matching status)."""
        key = self.keys.estimator_alive(self.robot)
        deadline = time.monotonic() + timeout_s
        said = False
        while not stop.is_set():
            if self.bus.alive(key, timeout=1.0):
                left = max(0.1, deadline - time.monotonic())
                return all(self.bus.wait_for_subscriber(k, timeout=left) for k in
                           (self.keys.odometry(self.robot), self.keys.observations(self.robot)))
            if not said:
                log.info("waiting for an estimator on %s", key)
                said = True
            if time.monotonic() >= deadline:
                return False
            stop.wait(0.1)
        return False

    def close(self) -> None:
        if self.pacer is not None:
            self.pacer.close()


class InputPublisher(Protocol):
    """What :func:`play` publishes through: one robot's publisher or a fleet of them."""

    @property
    def counts(self) -> Any: ...

    def publish(self, message: Message, stop: threading.Event | None = None) -> None: ...


def _stamp(message: Message) -> float:
    return float(message.stamp)  # type: ignore[attr-defined]


def play(events: Iterable[Message], publisher: InputPublisher, stop: threading.Event, *,
         rate: float, progress_every_s: float = 0.0, bar: Any = None) -> float:
    """Publish ``events`` paced at ``rate`` × their own time (0 = as fast as possible:
    paced on the estimator if ``publisher`` has a pacer). Returns the wall seconds.

    ``bar`` (:func:`slamlens.common.progress.time_bar`) is advanced by the data time published.
    """
    start = time.monotonic()
    t0: float | None = None
    shown = 0.0
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
        publisher.publish(message, stop)
        if bar is not None and stamp - t0 > shown:
            bar.update(stamp - t0 - shown)
            shown = stamp - t0
        if progress_every_s and stamp - t0 >= next_report:
            next_report += progress_every_s
            log.info("t = %.1f s published (%s)", stamp - t0, publisher.counts)
    return time.monotonic() - start
