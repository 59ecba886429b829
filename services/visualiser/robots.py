"""What the viewer remembers of each robot it shows: path, clusters, plots, tracked pose.

One :class:`RobotHistory` per robot (a :class:`~slamlens.services.visualiser.render.Renderer` for
its path and cluster identities, a :class:`~slamlens.services.visualiser.tracked.TrackedMatch`,
a :class:`~slamlens.services.visualiser.series.SeriesStore`), created the first time the robot is
seen and emptied when its estimator starts a new map (:meth:`RobotHistory.new_map`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.series import SeriesStore
from slamlens.services.visualiser.tracked import TrackedMatch


class RobotHistory:
    """The history of one robot's current map."""

    def __init__(self, name: str, new_series: Callable[[], SeriesStore]) -> None:
        self.name = name
        self.renderer = Renderer()
        self.tracked = TrackedMatch()
        self._new_series = new_series
        self.series = new_series()  #: replaced (with its cluster identities) by a new map
        self.maps = 1  #: maps seen (1 + restarts)

    def new_map(self) -> None:
        """The estimator began a new map: drop the old one's path, clusters and plots."""
        self.renderer.new_map()
        self.tracked.reset()
        self.series = self._new_series()
        self.maps += 1


class RobotHistories:
    """The :class:`RobotHistory` of every robot seen, by name (thread-safe)."""

    def __init__(self, new_series: Callable[[], SeriesStore]) -> None:
        self._new_series = new_series
        self._lock = threading.Lock()
        self._robots: dict[str, RobotHistory] = {}

    def get(self, name: str) -> RobotHistory:
        with self._lock:
            history = self._robots.get(name)
            if history is None:
                history = self._robots[name] = RobotHistory(name, self._new_series)
            return history

    def find(self, name: str) -> RobotHistory | None:
        with self._lock:
            return self._robots.get(name)
