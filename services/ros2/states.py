"""A ROS 2 estimator's states on the bus, published as slamlens's estimator publishes its own.

``slamlens/robot/R/state`` through an advanced publisher with a cache (a monitor or a
recorder that missed some recovers them), a ``get`` on the key answered with the newest
state (``?header``: its header only, what drivers pace on), and the liveliness token
``slamlens/robot/R/alive/estimator`` while it runs: the viewer, the monitor, the recorder
and Foxglove work on it unchanged (docs/protocol.md).
"""

from __future__ import annotations

import threading
from typing import Any

import msgpack

from slamlens.common.bus import Bus, joined
from slamlens.common.keys import Keys
from slamlens.common.messages import Message, SlamState

#: states kept for subscribers that recover what they missed, and the memory they may hold
STATE_CACHE = 1000
STATE_CACHE_BYTES = 256 << 20


class StatePublisher:
    """Publishes one robot's SlamStates (module docstring); ``publish`` from one thread."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str) -> None:
        self.robot = robot
        self.counts = {"SlamState": 0}
        self._lock = threading.Lock()
        self._latest: Any = None
        self._header: bytes | None = None
        self._publisher = bus.publisher(keys.state(robot), cache=STATE_CACHE,
                                        cache_bytes=STATE_CACHE_BYTES)
        bus.answer(keys.state(robot), self._on_query)
        bus.declare_alive(keys.estimator_alive(robot))

    def _on_query(self, key: str, payload: bytes | None, parameters: str) -> Any:
        with self._lock:
            latest, header = self._latest, self._header
        if "header" in parameters.split(";"):
            return header
        if isinstance(latest, list):
            latest = joined(latest)
            with self._lock:
                self._latest = latest
        return latest

    def publish(self, message: Message, stop: threading.Event | None = None) -> None:
        if not isinstance(message, SlamState):
            return
        parts = message.wire_parts()
        header = msgpack.packb({"schema": 1, "robot": message.robot, "seq": message.seq,
                                "stamp": message.stamp, "step": message.step,
                                "epoch": message.epoch, "input_stamp": message.input_stamp,
                                "n": message.n, "origin_stamp": message.origin_stamp},
                               use_bin_type=True)
        with self._lock:  # gettable before it is put: a get never answers older than a
            self._latest, self._header = parts, header  # state a subscriber has seen
        self._publisher.put(parts)
        self.counts["SlamState"] += 1
