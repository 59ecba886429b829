"""A ROS 2 estimator's states on the bus, published as slamlens's estimator publishes its own.

``slamlens/robot/R/state`` through an advanced publisher with a cache (a monitor or a
recorder that missed some recovers them), a ``get`` on the key answered with the newest
state (``?header``: its header only, what drivers pace on), and the liveliness token
``slamlens/robot/R/alive/estimator`` while it runs: the viewer, the monitor, the recorder
and Foxglove work on it unchanged (docs/protocol.md).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from slamlens.common.bus import Bus
from slamlens.common.keys import Keys
from slamlens.common.messages import Message, SlamState
from slamlens.common.state_header import state_header
from slamlens.common.state_outlet import StateOutlet

#: states kept for subscribers that recover what they missed, and the memory they may hold
STATE_CACHE = 1000
STATE_CACHE_BYTES = 256 << 20


class StatePublisher:
    """Publishes one robot's SlamStates (module docstring); ``publish`` from one thread.

    Through the estimator's own :class:`~slamlens.common.state_outlet.StateOutlet`, each
    state put as it comes (an imported estimate is one input); the ``?header`` counts are
    the publisher's: ``dropped`` what ``dropped()`` says, the input-order counts 0 (it has
    no input order)."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str,
                 dropped: Callable[[], int] = lambda: 0) -> None:
        self.robot = robot
        self.counts = {"SlamState": 0}
        self._dropped = dropped
        self._out = StateOutlet(bus, keys.state(robot), cache=STATE_CACHE,
                                cache_bytes=STATE_CACHE_BYTES, header=self._header_of)
        bus.declare_alive(keys.estimator_alive(robot))

    def _header_of(self, state: SlamState) -> bytes:
        return state_header(state, {"dropped": self._dropped()})

    def publish(self, message: Message, stop: threading.Event | None = None) -> None:
        if not isinstance(message, SlamState):
            return
        if self._out.is_open:
            self._out.publish(message)
        else:  # the first: a get is answered from now on
            self._out.open(message)
        self.counts["SlamState"] += 1
