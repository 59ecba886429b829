"""The EKF-SLAM estimator as a bus service (SPEC §4, §7).

One ordered FIFO channel on ``slamlens/robot/{robot}/*`` carries odometry and
observations in publication order, and one thread applies them: odometry is never
reordered against observations (separate callbacks would race on separate threads).
After every event applied it publishes one ``SlamState`` and keeps its bytes as the
answer to a ``get`` on the state key. A liveliness token announces the estimator.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from common.bus import Bus, pump
from common.drops import DropCounter
from common.errors import MessageError
from common.keys import Keys
from common.messages import Observations, Odometry, SlamState
from services.slam.estimator import Estimator, EstimatorSettings

log = logging.getLogger("slamlens.estimator")


@dataclass
class EstimatorStats:
    """Counters the service keeps (and logs at exit)."""

    odometry: int = 0
    observation_batches: int = 0
    states: int = 0
    foreign_robot: int = 0


def _warm_up(settings: EstimatorSettings) -> None:
    """Run a throwaway estimator through every code path once before serving.

    The first update otherwise pays for lazy imports and BLAS/LAPACK set-up (≈ 0.4 s
    measured), which would stall the first real events and skew their latency.
    """
    est = Estimator(EstimatorSettings(robot=settings.robot))
    est.predict(v=0.1, w=0.1, dt=0.1, stamp=0.1)
    est.observe(ids=[1, 2], ranges=[1.0, 1.5], bearings=[0.3, -0.3], stamp=0.1)
    est.predict(v=0.1, w=0.1, dt=0.1, stamp=0.2)
    report = est.observe(ids=[1, -1], ranges=[0.99, 1.49], bearings=[0.29, -0.31], stamp=0.2)
    state = est.to_state(seq=1, stamp=0.2, step="update", report=report)
    SlamState.from_bytes(state.to_bytes())
    Odometry.from_bytes(Odometry(robot="w", stamp=0.0, dt=0.1, v=0.0, w=0.0).to_bytes())
    Observations.from_bytes(Observations(robot="w", stamp=0.0, ids=np.array([1]),
                                         ranges=np.array([1.0]),
                                         bearings=np.array([0.0])).to_bytes())


class EstimatorService:
    """Wires an :class:`Estimator` to the bus; ``handle`` is the whole event logic."""

    def __init__(self, bus: Bus, *, keys: Keys, settings: EstimatorSettings) -> None:
        _warm_up(settings)
        self.robot = settings.robot
        self.keys = keys
        self.estimator = Estimator(settings)
        self.stats = EstimatorStats()
        self.drops = DropCounter(log)
        self._seq = 0
        self._lock = threading.Lock()
        self._publisher = bus.publisher(keys.state(self.robot))
        # The input channel is declared before the liveliness token, so a driver that
        # waits for the token never publishes into the void.
        self._inputs = bus.channel(
            keys.robot_inputs(self.robot),
            accept=lambda key: key.endswith(("/odometry", "/observations")))
        init = self.estimator.to_state(seq=0, stamp=0.0, step="init")
        self._latest = init.to_bytes()
        bus.serve_latest(keys.state(self.robot), self.latest_bytes)
        self._publisher.put(self._latest)
        bus.declare_alive(keys.estimator_alive(self.robot))

    def latest_bytes(self) -> bytes:
        with self._lock:
            return self._latest

    def handle(self, key: str, payload: bytes) -> SlamState | None:
        """Apply one input sample; returns the state published, or None if ignored."""
        leaf = self.keys.leaf_of(key)
        if leaf not in ("odometry", "observations"):
            return None  # truth, state, health… share the prefix; not ours to apply
        try:
            if leaf == "odometry":
                odo = Odometry.from_bytes(payload)
                if not self._mine(odo.robot):
                    return None
                self.estimator.predict(v=odo.v, w=odo.w, dt=odo.dt, stamp=odo.stamp)
                self.stats.odometry += 1
                return self._publish(stamp=odo.stamp, step="predict", report=None)
            obs = Observations.from_bytes(payload)
            if not self._mine(obs.robot):
                return None
            report = self.estimator.observe(ids=obs.ids, ranges=obs.ranges,
                                            bearings=obs.bearings, stamp=obs.stamp)
            self.stats.observation_batches += 1
            return self._publish(stamp=obs.stamp, step="update", report=report)
        except MessageError as exc:
            self.drops.drop(exc.message_type, f"on {key}: {exc}")
        except ValueError as exc:  # the estimator refused the input (NaN, bad control…)
            self.drops.drop(leaf, f"on {key}: {exc}")
        return None

    def _mine(self, robot: str) -> bool:
        if robot != self.robot:
            self.stats.foreign_robot += 1
            self.drops.drop("robot", f"message for robot {robot!r} on {self.robot!r}'s key")
            return False
        return True

    def _publish(self, *, stamp: float, step: str, report: object) -> SlamState:
        self._seq += 1
        state = self.estimator.to_state(seq=self._seq, stamp=stamp, step=step,
                                        report=report)  # type: ignore[arg-type]
        payload = state.to_bytes()
        with self._lock:
            self._latest = payload
        self._publisher.put(payload)
        self.stats.states += 1
        return state

    def run(self, stop: threading.Event) -> None:
        """Apply events until ``stop`` is set."""
        pump(self._inputs, self.handle, stop, status=lambda: log.info(
            "seq %d, %d landmarks, %d odometry, %d observation batches, %d dropped",
            self._seq, self.estimator.n, self.stats.odometry, self.stats.observation_batches,
            self.drops.total))
