"""What a recorder does, for tests and benchmarks: every state on a key, received on a
thread through a recovering channel (``Bus.channel(recover=True)``) with history.

Subclasses say what they keep of each payload in :meth:`StateCollector.take` (set their
own fields *before* calling ``super().__init__``: the thread starts there).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from slamlens.common.session import BusSettings, open_bus


class StateCollector:
    """Every sample on ``key`` in arrival order, handed to :meth:`take` on a thread."""

    def __init__(self, endpoint: str, key: str, *, history_s: float = 30.0) -> None:
        self.bus = open_bus(BusSettings(connect=(endpoint,)))
        self.channel = self.bus.channel(key, recover=True, history_s=history_s)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="state-collector")
        self._thread.start()

    def take(self, payload: bytes) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while not self._stop.is_set():
            sample = self.channel.recv(timeout=0.2)
            if sample is not None:
                self.take(sample.payload)

    def wait(self, predicate: Callable[[Any], bool], timeout: float = 60.0) -> bool:
        """True as soon as ``predicate(self)`` holds; its last value after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            self._stop.wait(0.05)
        return predicate(self)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.bus.close()
