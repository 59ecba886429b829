"""The monitor's NIS band counts innovations correlated in time (docs/monitor.md,
"Statistical tests"; Health ``statistics`` ``nis_tau``): a third party whose innovations
follow S in their mean but persist from one to the next (an AR(1) process, as a real
sensor's errors do) is not called inconsistent once the dependence is measured; the same
innovations four times larger than S says are, and the violation says how many independent
innovations the window counted.

The third party publishes update states with five innovations each (a NIS window of 50
every 10 states), in lock step with the monitor's Health of each seq; no truth. Nothing here
waits on time: each state waits for its Health.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import kit_wire as wire
import numpy as np
import pytest
from kit_procs import endpoint, start

S = np.diag([0.01, 4e-4])  #: the innovation covariance the states declare
PER_STATE = 5  #: innovations per state: a window of 50 every 10 states
MEASURED_FROM = 10 * 5  #: seq after which the band is the measured one (4 windows, and one)
PHI = 0.9  #: each innovation is 0.9 of the one before plus fresh noise (AR(1))
STATES = 600  #: 60 windows


class Correlated:
    """The third party: update states whose innovations are AR(1) in time, scaled."""

    def __init__(self, port: int, robot: str, scale: float) -> None:
        self.robot = robot
        self.session = wire.session(port)
        rng = np.random.default_rng(7)
        white = rng.normal(size=(STATES * PER_STATE, 2))
        unit = np.empty_like(white)
        unit[0] = white[0]
        for t in range(1, unit.shape[0]):  # unit variance at every step: NIS mean 2 × scale
            unit[t] = PHI * unit[t - 1] + np.sqrt(1.0 - PHI * PHI) * white[t]
        self.innovations = unit @ np.sqrt(S) * np.sqrt(scale)
        self.lockstep = wire.LockStep(self.session, robot)
        self.seq = 0

    def step(self) -> dict[str, Any]:
        """One more update state; the monitor's Health of it."""
        self.seq += 1
        k = (self.seq - 1) * PER_STATE
        state = wire.pack({
            "robot": self.robot, "seq": self.seq, "stamp": 0.1 * self.seq, "step": "update",
            "pose": wire.array([0.0, 0.0, 0.0], "<f8"),
            "landmark_ids": wire.array([], "<i8"), "landmarks": wire.array(np.zeros((0, 2)),
                                                                          "<f8"),
            "covariance": wire.array(np.diag([1e-4, 1e-4, 1e-5]).reshape(-1), "<f8"),
            "innovation_ids": wire.array(list(range(PER_STATE)), "<i8"),
            "innovations": wire.array(self.innovations[k:k + PER_STATE], "<f8"),
            "innovation_covariances": wire.array(np.repeat(S[None], PER_STATE, 0), "<f8")})
        return self.lockstep.exchange(state, self.seq)

    def run(self) -> list[dict[str, Any]]:
        return [self.step() for _ in range(STATES)]

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def party(router: int, request: pytest.FixtureRequest) -> Iterator[Correlated]:
    """A monitor process for the robot, and the third party matched to it."""
    robot, scale = request.param
    monitor = start("monitor", "--robot", robot, "--connect", endpoint(router),
                    ready="monitor ready")
    third = Correlated(router, robot, scale)
    try:
        wire.wait_matched(third.session, wire.key(robot, "state"))
        yield third
    finally:
        third.close()
        monitor.stop()


def nis_violations(healths: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [v for h in healths for v in h.get("violations", []) if v["kind"] == "nis"]


@pytest.mark.parametrize("party", [("persistent", 1.0)], indirect=True)
def test_correlated_innovations_with_the_right_mean_are_not_called_inconsistent(
        party: Correlated) -> None:
    healths = party.run()
    assert nis_violations(healths[MEASURED_FROM:]) == []
    tau = healths[-1]["statistics"]["nis_tau"]
    assert tau > 3.0, tau  # ≈ 1 + 2·Σ 0.81^k (1 − k/50): about 9
    assert healths[-1].get("verdict", "ok") == "ok", healths[-1]
    # the band the monitor shows is wider than the textbook χ²(100)/50 one (≤ 3.70)
    assert healths[-1]["statistics"]["nis_window_hi"] > 3.8


@pytest.mark.parametrize("party", [("overconfident", 4.0)], indirect=True)
def test_the_same_innovations_four_times_larger_than_s_are(party: Correlated) -> None:
    healths = party.run()
    late = nis_violations(healths[MEASURED_FROM:])
    assert len(late) >= 10, late  # most of the 55 windows after the first five
    assert all(v["statistic"] > v["bound"] for v in late), late
    assert all("independent, correlated in time): the innovations are larger than S"
               in v["detail"] for v in late), late[0]["detail"]
    assert healths[-1]["verdict"] == "tuning", healths[-1]
