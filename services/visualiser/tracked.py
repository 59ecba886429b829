"""The camera-tracked robot pose, matched with the estimate of the same instant.

The registration service measures the robot's pose from its marker every frame and
publishes it on ``slamlens/robot/{robot}/tracked``. The viewer draws the newest one beside
the estimate of the state whose stamp is nearest its own: the robot moves, so only the
same instant is a fair comparison, and the camera's pose lags the newest state by its
capture and detection time.
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from slamlens.common.messages import Truth

#: the newest tracked pose is compared with the estimate of the state nearest its stamp,
#: if one is within this (s): the robot moves, so only the same instant is a fair comparison
#: (the camera's pose lags the newest state by its capture and detection time)
TRACKED_MATCH_S = 0.06


class TrackedMatch:
    """The newest tracked pose and the recent estimates it is matched against."""

    def __init__(self, *, history: int = 240, match_s: float = TRACKED_MATCH_S) -> None:
        self.match_s = match_s
        self._lock = threading.Lock()
        self._tracked: Truth | None = None
        self._estimates: deque[tuple[float, np.ndarray]] = deque(maxlen=history)

    def add_estimate(self, stamp: float, pose: np.ndarray) -> None:
        """Remember the estimated pose (x, y, θ) of the state stamped ``stamp`` (s)."""
        with self._lock:
            self._estimates.append((stamp, pose))

    def reset(self) -> None:
        """A new map: the old estimates and tracked pose are in another frame."""
        with self._lock:
            self._tracked = None
            self._estimates.clear()

    def set_tracked(self, tracked: Truth) -> None:
        with self._lock:
            self._tracked = tracked

    def reference(self) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
        """(newest tracked pose, the estimate of the state nearest its stamp), if any
        estimate lies within ``match_s`` of it; else (None, None)."""
        with self._lock:
            tracked, estimates = self._tracked, list(self._estimates)
        if tracked is None or not estimates:
            return None, None
        stamp, pose = min(estimates, key=lambda e: abs(e[0] - tracked.stamp))
        if abs(stamp - tracked.stamp) > self.match_s:
            return None, None
        return tracked.pose, pose
