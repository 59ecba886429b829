"""The monitor's verdict on a third party's conservative filter (docs/protocol.md, Health
``verdict``): a NIS window below its band makes ``"tuning"`` without a truth, does not once
the pose NEES against a truth is in its band — also after the truth stops, for longer than
the monitor's clearance — and makes it again once a truth contradicts the pose covariance
(docs/monitor.md, "The verdict"); and a failed NIS
window stands, however many states come without innovations, until a NIS window passes
(docs/monitor.md, "Clearance rule").

The third party publishes, in lock step with the monitor's Health of each seq, states whose
pose error is drawn from their own P (pose NEES ≈ 3) and whose innovations are drawn from
S / 4 (NIS ≈ 0.5, under its band), with or without a Truth before each. Nothing here waits
on time: each state waits for its Health, and each phase runs until the verdict it expects
or a bound of states.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import kit_wire as wire
import numpy as np
import pytest
from kit_procs import endpoint, start

ROBOT = "conservative"
LANDMARK_IDS = [5, 9]
LANDMARKS = np.array([[2.0, 1.0], [-1.0, 2.5]])
P_POSE = np.diag([1e-4, 1e-4, 1e-5])
SIGMA_LM = 0.06  #: each landmark coordinate's σ in P; the map is off by exactly one σ
S = np.diag([0.01, 4e-4])  #: the innovation covariance the states declare
INNOVATIONS = 4  #: per state
CLEAR_AFTER = 200  #: the monitor's default clearance, in states (docs/monitor.md)


class Conservative:
    """The third party: a state publisher, a truth publisher, and every Health heard."""

    def __init__(self, port: int) -> None:
        self.session = wire.session(port)
        self.rng = np.random.default_rng(32)
        self.lockstep = wire.LockStep(self.session, ROBOT)
        self.truths = wire.plain(self.session, wire.key(ROBOT, "truth"))
        self.seq = 0

    def step(self, *, truth: bool, s_over: float | None = 4.0,
             truth_off: float = 0.0) -> dict[str, Any]:
        """One more state (after its truth, if ``truth``, placed ``truth_off`` m from the
        robot along x); the monitor's Health of it. Its innovations are drawn from
        S / ``s_over``; None: none (its sightings, say, all new landmarks the state does not
        list: P unchanged, as in every state here)."""
        self.seq += 1
        stamp = 0.1 * self.seq
        true_pose = np.array([0.5 * np.cos(stamp), 0.5 * np.sin(stamp), stamp])
        pose = true_pose + self.rng.multivariate_normal(np.zeros(3), P_POSE)
        if truth:
            self.truths.put(wire.pack({
                "robot": ROBOT, "stamp": stamp,
                "pose": wire.array(true_pose + [truth_off, 0.0, 0.0], "<f8"),
                "landmark_ids": wire.array(LANDMARK_IDS, "<i8"),
                "landmarks": wire.array(LANDMARKS, "<f8")}))
        n = len(LANDMARK_IDS)
        cov = np.zeros((3 + 2 * n, 3 + 2 * n))
        cov[:3, :3] = P_POSE
        cov[3:, 3:] = np.eye(2 * n) * SIGMA_LM ** 2
        fields: dict[str, Any] = {} if s_over is None else {
            "innovation_ids": wire.array([LANDMARK_IDS[k % n] for k in range(INNOVATIONS)],
                                         "<i8"),
            "innovations": wire.array(self.rng.multivariate_normal(
                np.zeros(2), S / s_over, INNOVATIONS), "<f8"),
            "innovation_covariances": wire.array(np.repeat(S[None], INNOVATIONS, 0), "<f8")}
        state = wire.pack({
            "robot": ROBOT, "seq": self.seq, "stamp": stamp, "step": "update",
            "pose": wire.array([pose[0], pose[1], np.arctan2(np.sin(pose[2]),
                                                             np.cos(pose[2]))], "<f8"),
            "landmark_ids": wire.array(LANDMARK_IDS, "<i8"),
            "landmarks": wire.array(LANDMARKS + SIGMA_LM, "<f8"),  # feature NEES 2 each
            "covariance": wire.array(cov.reshape(-1), "<f8"), **fields})
        return self.lockstep.exchange(state, self.seq)

    def close(self) -> None:
        self.session.close()


def timid_nis(health: dict[str, Any]) -> bool:
    return any(v["kind"] == "nis" and v["statistic"] < v["bound"]
               for v in health.get("standing", []))


@pytest.fixture
def party(router: int) -> Iterator[Conservative]:
    """A monitor process for the robot, and the third party matched to it."""
    monitor = start("monitor", "--robot", ROBOT, "--connect", endpoint(router),
                    ready="monitor ready")
    third = Conservative(router)
    try:
        wire.wait_matched(third.session, wire.key(ROBOT, "state"))
        yield third
    finally:
        third.close()
        monitor.stop()


def until_timid_nis(party: Conservative) -> dict[str, Any]:
    """States without a truth until a NIS window stands below its band; that Health."""
    health = party.step(truth=False)
    while not timid_nis(health):
        assert party.seq < 100, f"no NIS window below its band by seq {party.seq}"
        health = party.step(truth=False)
    return health


def test_a_timid_nis_is_ok_while_the_truths_word_bears_the_pose_out(
        party: Conservative) -> None:
    # no truth: once a NIS window has left its band from below, it is "tuning"
    health = until_timid_nis(party)
    assert health["verdict"] == "tuning", health
    for _ in range(20):
        health = party.step(truth=False)
        assert health["verdict"] == "tuning" and timid_nis(health), health
    # a truth with every state: "ok" once a pose NEES window has passed, the NIS listed
    while health.get("verdict", "ok") != "ok":
        assert party.seq < 600, f"still {health['verdict']} at seq {party.seq}"
        assert not any(v["kind"] == "nees" for v in health.get("standing", [])), health
        health = party.step(truth=True)
    assert timid_nis(health), health
    ok_from = party.seq
    for _ in range(50):
        health = party.step(truth=True)
        assert health.get("verdict", "ok") == "ok" and timid_nis(health), health
    # the truth gone: its word stands, past the clearance, and the Health says whose it is
    stopped = party.seq
    for _ in range(CLEAR_AFTER + 50):
        health = party.step(truth=False)
        assert health.get("verdict", "ok") == "ok" and timid_nis(health), health
        assert health["statistics"]["nees_pose_judged_seq"] <= stopped, health
    # a truth 10 cm off, against a pose σ of 1 cm: once a NEES window fails, "tuning"
    contradicted = party.seq
    while health.get("verdict", "ok") == "ok":
        assert party.seq < contradicted + 150, f"still ok {party.seq - contradicted} states"
        health = party.step(truth=True, truth_off=0.1)
    assert health["verdict"] == "tuning", health
    assert {"nees", "nis"} <= {v["kind"] for v in health["standing"]}, health
    assert ok_from > 30  # it was "tuning" before the first truths


def test_a_failed_nis_window_stands_until_a_nis_window_passes(party: Conservative) -> None:
    health = until_timid_nis(party)
    # states without innovations, more of them than the clearance: no window, no evidence
    for _ in range(CLEAR_AFTER + 50):
        health = party.step(truth=False, s_over=None)
        assert health["verdict"] == "tuning" and timid_nis(health), health
    # innovations as S says: once a window passed, and the clearance after the last
    # failed one, "ok"
    passed_from = party.seq
    while health.get("verdict", "ok") != "ok":
        assert party.seq < passed_from + 400, f"still {health['verdict']}"
        health = party.step(truth=False, s_over=1.0)
    assert not health.get("standing"), health
