"""Large states (≥ 1 MiB: through Zenoh's shared memory) from the estimator service on a
real Zenoh bus: after each is put, a ``get`` answers with what went out (the
shared-memory buffer), nothing holds the state's matrix any more, and the next predict
patches that matrix in place. Every state a recorder gets is still exactly the dense P of
its moment — none changed after it went out — and a ``get`` answers the newest."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from slamlens.common.keys import Keys
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.services.harness.collect import StateCollector
from slamlens.services.slam.estimator_service import EstimatorService
from slamlens.services.slam.settings import EstimatorSettings

KEYS = Keys()
ROBOT = "big"
N_LANDMARKS = 200  #: N = 403: a 1.3 MB covariance, above the shared-memory threshold


class Seqs(StateCollector):
    def __init__(self, endpoint: str) -> None:
        self.states: dict[int, SlamState] = {}
        super().__init__(endpoint, KEYS.state(ROBOT), history_s=60.0)

    def take(self, payload: bytes) -> None:
        state = SlamState.from_bytes(payload)
        self.states[state.seq] = state


def _big_map() -> SlamState:
    """200 landmarks on a ring 3 m around the robot, a random correlated SPD P."""
    rng = np.random.default_rng(7)
    N = 3 + 2 * N_LANDMARKS
    A = rng.standard_normal((N, N)) * 0.02
    P = A @ A.T + np.eye(N) * 0.01
    angles = np.linspace(-math.pi, math.pi, N_LANDMARKS, endpoint=False)
    xy = np.column_stack([3 * np.cos(angles), 3 * np.sin(angles)])
    return SlamState(robot=ROBOT, seq=0, stamp=0.0, step="update", pose=np.zeros(3),
                     landmark_ids=np.arange(1, N_LANDMARKS + 1, dtype=np.int64),
                     landmarks=xy, covariance=P)


def _dense(service: EstimatorService) -> np.ndarray:
    """The textbook symmetric P from the filter's lower-triangle storage (numpy's own
    triangles: independent of ``ekf.symmetric``)."""
    est = service.estimator
    N = 3 + 2 * est.n
    lower = np.tril(est.store.L[:N, :N])
    return lower + np.tril(lower, -1).T


def test_large_states_go_out_from_shared_memory_and_predicts_patch_in_place(
        router_endpoint, make_client) -> None:
    bus = make_client()
    service = EstimatorService(bus, keys=KEYS, settings=EstimatorSettings(robot=ROBOT))
    service.estimator.restore(_big_map())
    recorder = Seqs(router_endpoint)
    client = make_client()
    try:
        assert bus.wait_for_subscriber(KEYS.state(ROBOT), timeout=30.0)
        seq = itertools.count(1)
        expected: dict[int, np.ndarray] = {}
        t = 0.0
        for k in range(30):  # odometry then one observation batch of 3 landmarks, 15 times
            t += 0.1
            if k % 2 == 0:
                message = Odometry(robot=ROBOT, stamp=t, dt=0.1, v=0.05, w=0.01)
                key = KEYS.odometry(ROBOT)
            else:
                ids = np.array([1 + k, 60 + k, 120 + k], dtype=np.int64)
                xy = _big_map().landmarks[ids - 1]
                message = Observations(robot=ROBOT, stamp=t, ids=ids,
                                       ranges=np.hypot(xy[:, 0], xy[:, 1]),
                                       bearings=np.arctan2(xy[:, 1], xy[:, 0]))
                key = KEYS.observations(ROBOT)
            payload = dataclasses.replace(message, input_seq=next(seq)).to_bytes()
            state = service.handle(key, payload)
            assert state is not None, key
            expected[state.seq] = _dense(service)
            del state  # as the worker does: nothing of ours holds the state
        last = max(expected)
        assert bus.shm.shared >= len(expected)  # every state went through shared memory
        # all but the first predict (the restored map's first state) patched in place
        assert service.estimator.predicts_in_place >= 14, service.estimator.predicts_in_place
        assert recorder.wait(lambda r: last in r.states, timeout=60.0), sorted(recorder.states)
        assert set(expected) <= set(recorder.states), sorted(set(expected) - set(recorder.states))
        for s in expected:
            np.testing.assert_array_equal(recorder.states[s].covariance, expected[s],
                                          err_msg=f"seq {s}")
        replies = client.get(KEYS.state(ROBOT), timeout=10.0)
        newest = SlamState.from_bytes(replies[0].payload)
        assert newest.seq == last
        np.testing.assert_array_equal(newest.covariance, expected[last])
        # and the checkpoint's copy of the newest state is the same state
        assert SlamState.from_bytes(service.latest_bytes()).seq == last
    finally:
        recorder.close()

