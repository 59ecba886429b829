"""The drivers' logic in-process (InProcessBus): numbering, pacing on the estimator, drain.

The simulator and a replay of a small MRCLAM cut go through ``drivers.play`` at rate 0
into an :class:`EstimatorService` running on its own thread, as ``slamlens sim`` and
``slamlens replay`` do over Zenoh (tests/system covers that). The oracle is an estimator
fed the same events directly: the service must end bit-equal to it, having published one
state per input, and the pacer must have held the driver back to its window.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Message, Observations, Odometry, SlamState, peek_fields
from slamlens.services.slam.drivers import Fleet, RobotPublisher, play
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.estimator_service import EstimatorService
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

KEYS = Keys("t")
SMALL = Path(__file__).resolve().parents[1] / "fixtures" / "mrclam_small"


def _direct(events: Iterable[Message], settings: EstimatorSettings) -> tuple[Estimator, int]:
    est = Estimator(settings)
    inputs = 0
    for m in events:
        if isinstance(m, Odometry):
            est.predict(v=m.v, w=m.w, dt=m.dt, stamp=m.stamp)
            inputs += 1
        elif isinstance(m, Observations):
            est.observe(ids=m.ids, ranges=m.ranges, bearings=m.bearings, stamp=m.stamp)
            inputs += 1
    return est, inputs


class Pipeline:
    """An estimator service on its own thread, and every state it publishes."""

    def __init__(self, bus: InProcessBus, robot: str, settings: EstimatorSettings) -> None:
        self.heads: list[dict] = []
        self.last: bytes | None = None
        self.unapplied_max = 0
        self._bus = bus
        self._robot = robot
        bus.subscribe(KEYS.state(robot), self._on_state)
        # published on its key as they are put: counts inputs the service has not applied
        self.published = 0
        bus.subscribe(KEYS.odometry(robot), self._on_input)
        bus.subscribe(KEYS.observations(robot), self._on_input)
        self.service = EstimatorService(bus, keys=KEYS, settings=settings)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self.service.run, args=(self._stop,),
                                        daemon=True)
        self._thread.start()

    def _on_state(self, key: str, payload: bytes) -> None:
        self.heads.append(peek_fields(payload, ("seq", "step")))
        self.last = payload

    def _on_input(self, key: str, payload: bytes) -> None:
        self.published += 1
        applied = self.heads[-1]["seq"] if self.heads else 0
        self.unapplied_max = max(self.unapplied_max, self.published - applied)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        assert not self._thread.is_alive()


def _check(pipe: Pipeline, expected: Estimator, inputs: int, window: int) -> None:
    assert [h["seq"] for h in pipe.heads] == list(range(inputs + 1))  # init, one per input
    assert pipe.last is not None
    final = SlamState.from_bytes(pipe.last)
    np.testing.assert_array_equal(final.pose, expected.pose)
    np.testing.assert_array_equal(final.covariance, expected.covariance)
    np.testing.assert_array_equal(final.landmark_ids, expected.landmark_ids)
    # the driver never ran further ahead than its window, plus the one being published, plus
    # one state the service already answers `get` with but has not yet put to this test's
    # subscriber (it makes a state gettable, then puts it: the pacer can see it first)
    assert pipe.unapplied_max <= window + 2, pipe.unapplied_max


def test_the_simulator_paced_on_the_estimator_applies_every_input() -> None:
    robot, window = "r1", 16
    settings = EstimatorSettings(robot=robot)
    bus = InProcessBus()
    pipe = Pipeline(bus, robot, settings)
    publisher = RobotPublisher(bus, keys=KEYS, robot=robot)
    stop = threading.Event()
    try:
        assert publisher.wait_for_estimator(stop, timeout_s=5.0)
        pacer = publisher.pace_on_estimator(window=window)
        play(Simulator(load_world("paper"), robot=robot, seed=4).events(), publisher, stop,
             rate=0)
        assert pacer.drain(stop, timeout_s=30.0)
    finally:
        pipe.close()
    expected, inputs = _direct(Simulator(load_world("paper"), robot=robot, seed=4).events(),
                               settings)
    assert publisher.input_seq == inputs and publisher.counts["Truth"] > 0
    assert pacer.polls > 0  # it did wait on the estimator's header
    _check(pipe, expected, inputs, window)


def test_a_replay_through_a_fleet_applies_every_input_in_order() -> None:
    robot, window = "robot1", 32
    settings = EstimatorSettings(robot=robot)
    run = load_mrclam(SMALL, 1, robot_name=robot)
    bus = InProcessBus()
    pipe = Pipeline(bus, robot, settings)
    fleet = Fleet(bus, keys=KEYS, robots=[robot])
    stop = threading.Event()
    try:
        assert fleet.wait_for_estimator(stop, timeout_s=5.0)
        fleet.pace_on_estimator(window=window)
        play(run.events(), fleet, stop, rate=0)
        assert fleet.drain(stop, timeout_s=30.0)
    finally:
        pipe.close()
    expected, inputs = _direct(run.events(), settings)
    assert inputs > 100 and fleet.counts["Odometry"] + fleet.counts["Observations"] == inputs
    _check(pipe, expected, inputs, window)
