"""The behaviour monitor as a bus service (SPEC §5, §7; issue 5).

It listens to one robot's keys through a single ordered channel — states, simulator
truth and the camera-tracked pose arrive in the order they were published — and
publishes one ``Health`` per state. The channel is a ring: if the monitor ever falls
behind it drops the oldest samples instead of slowing the estimator, and the checks are
valid across the resulting gaps (the Loewner order is transitive).

States from any estimator are accepted, ours or a third party's; the symmetry check is
the monitor's own (decoding does not reject an asymmetric covariance).
"""

from __future__ import annotations

import logging
import threading

from common.bus import Bus, pump
from common.drops import DropCounter
from common.errors import MessageError
from common.keys import Keys
from common.messages import Health, SlamState, Truth
from services.slam.monitor import Monitor
from services.slam.monitor_settings import MonitorSettings

log = logging.getLogger("slamlens.monitor")


class MonitorService:
    """Wires a :class:`Monitor` to the bus."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str, settings: MonitorSettings,
                 ring_capacity: int = 2048) -> None:
        self.robot = robot
        self.keys = keys
        self.monitor = Monitor(settings)
        self.drops = DropCounter(log)
        self.checked = 0
        self.violations = 0
        self._latest: bytes | None = None
        self._lock = threading.Lock()
        self._publisher = bus.publisher(keys.health(robot))
        self._inputs = bus.channel(keys.robot_inputs(robot), capacity=ring_capacity,
                                   drop_oldest=True,
                                   accept=lambda key: key.endswith(("/state", "/truth",
                                                                    "/tracked")))
        bus.serve_latest(keys.health(robot), self.latest_bytes)

    def latest_bytes(self) -> bytes | None:
        with self._lock:
            return self._latest

    def handle(self, key: str, payload: bytes) -> Health | None:
        leaf = self.keys.leaf_of(key)
        try:
            if leaf in ("truth", "tracked"):
                self.monitor.add_truth(Truth.from_bytes(payload))
                return None
            if leaf != "state":
                return None
            state = SlamState.from_bytes(payload, check_symmetry=False)
        except MessageError as exc:
            self.drops.drop(exc.message_type, f"on {key}: {exc}")
            return None
        health = self.monitor.check(state)
        self.checked += 1
        if not health.ok:
            self.violations += len(health.violations)
            if self.violations == len(health.violations):
                log.warning("first violation at seq %d: %s; suspects %s", health.seq,
                            "; ".join(v.detail or v.kind for v in health.violations[:3]),
                            list(health.suspects))
        payload_out = health.to_bytes()
        with self._lock:
            self._latest = payload_out
        self._publisher.put(payload_out)
        return health

    def run(self, stop: threading.Event) -> None:
        """Check states until ``stop`` is set."""
        pump(self._inputs, self.handle, stop, status=lambda: log.info(
            "%d states checked, %d violations, suspects %s", self.checked, self.violations,
            self.monitor.summary))
