"""Router, sim and estimator as separate processes over real Zenoh on loopback."""

from __future__ import annotations

import json
import time

import msgpack
import numpy as np
import pytest
import zenoh

from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState
from slamlens.services.harness.collect import StateCollector
from slamlens.services.harness.procs import spawn, stop, wait_for_line

KEYS = Keys()


class _Collector(StateCollector):
    """Every state, as a recorder gets them: states go out with congestion control *drop*
    (delivery.md), so a consumer that needs all of them recovers what a loaded machine drops."""

    def __init__(self, endpoint: str) -> None:
        self.states: list[SlamState] = []
        super().__init__(endpoint, KEYS.state("r1"), history_s=30.0)

    def take(self, payload: bytes) -> None:
        self.states.append(SlamState.from_bytes(payload))


@pytest.fixture
def estimator(router_endpoint):
    proc = spawn("estimator", "--robot", "r1", "--connect", router_endpoint)
    wait_for_line(proc, "estimator ready")
    yield proc
    out, err = stop(proc)
    assert proc.returncode == 0, err


def test_paper_run_every_state_received_in_order(router_endpoint, make_client, estimator,
                                                 request):
    got = _Collector(router_endpoint)
    request.addfinalizer(got.close)
    assert make_client().wait_for_subscriber(KEYS.state("r1"))  # ours reached the router
    sim = spawn("sim", "--robot", "r1", "--rate", "0", "--loops", "1", "--seed", "3",
                "--connect", router_endpoint)
    out, err = sim.communicate(timeout=120)
    assert sim.returncode == 0, err
    assert "sim done" in out
    counts = json.loads(out.split("sim done: ", 1)[1].split(" in ")[0])
    expected = counts["Odometry"] + counts["Observations"]
    got.wait(lambda g: len([s for s in g.states if s.step != "init"]) >= expected, timeout=20)
    states = [s for s in got.states if s.step != "init"]
    assert len(states) == expected
    seqs = [s.seq for s in states]
    assert seqs == list(range(seqs[0], seqs[0] + expected))
    assert {s.step for s in states} == {"predict", "update"}
    final = states[-1]
    assert final.n == 15
    assert np.allclose(final.covariance, final.covariance.T)

    # A late joiner's get returns the latest state at once.
    late = make_client()
    replies = late.get(KEYS.state("r1"), timeout=5.0)
    assert len(replies) == 1
    assert SlamState.from_bytes(replies[0].payload).seq == final.seq


def _spec_array(a: np.ndarray, dtype: str) -> dict:
    a = np.ascontiguousarray(a, dtype=dtype)
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def test_third_party_client_from_spec_only(router_endpoint, estimator):
    """A client written only from docs/protocol.md: raw zenoh and msgpack, no slamlens import."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{router_endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    received: list[dict] = []
    try:
        sub = session.declare_subscriber(
            "slamlens/robot/r1/state",
            lambda s: received.append(msgpack.unpackb(s.payload.to_bytes(), raw=False)))
        # our subscriber is declared on this session's link before anything we publish;
        # the estimator's input subscription is another session's: wait until it matches
        pubs = {}
        for leaf in ("odometry", "observations"):
            pubs[leaf] = pub = session.declare_publisher(f"slamlens/robot/r1/{leaf}")
            deadline = time.monotonic() + 10
            while not pub.matching_status and time.monotonic() < deadline:
                time.sleep(0.01)
            assert pub.matching_status, leaf
        pubs["odometry"].put(msgpack.packb(
            {"schema": 1, "robot": "r1", "stamp": 0.1, "dt": 0.1, "v": 0.2, "w": 0.0}))
        pubs["observations"].put(msgpack.packb(
            {"schema": 1, "robot": "r1", "stamp": 0.1,
             "ids": _spec_array(np.array([7, 8]), "<i8"),
             "ranges": _spec_array(np.array([1.0, 1.5]), "<f8"),
             "bearings": _spec_array(np.array([0.5, -0.5]), "<f8")}, use_bin_type=True))
        deadline = time.monotonic() + 10
        # (the estimator's "init" state, published at start-up, may still be in flight
        # when we subscribe: it is a state like the others, but not one of ours)
        events = [m for m in received if m["step"] != "init"]
        while len(events) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
            events = [m for m in received if m["step"] != "init"]
        assert len(events) == 2
        predict, update = events
        assert predict["schema"] == 1 and predict["step"] == "predict"
        pose = np.frombuffer(predict["pose"]["data"], predict["pose"]["dtype"])
        np.testing.assert_allclose(pose, [0.02, 0.0, 0.0], atol=1e-12)
        assert update["step"] == "update"
        ids = np.frombuffer(update["landmark_ids"]["data"], update["landmark_ids"]["dtype"])
        assert ids.tolist() == [7, 8]
        n = len(ids)
        cov = np.frombuffer(update["covariance"]["data"], update["covariance"]["dtype"])
        assert cov.size == (3 + 2 * n) ** 2
        cov = cov.reshape(3 + 2 * n, 3 + 2 * n)
        np.testing.assert_allclose(cov, cov.T, atol=1e-15)
        assert np.all(np.linalg.eigvalsh(cov) > -1e-12)
        lms = np.frombuffer(update["landmarks"]["data"], "<f8")
        lms = lms.reshape(update["landmarks"]["shape"])
        np.testing.assert_allclose(lms[0], [0.02 + np.cos(0.5), np.sin(0.5)], atol=1e-12)
        sub.undeclare()
    finally:
        session.close()


def test_estimator_survives_garbage(router_endpoint, make_client, estimator, request):
    client = make_client()
    got = _Collector(router_endpoint)
    request.addfinalizer(got.close)
    probe = make_client()
    assert probe.wait_for_subscriber(KEYS.state("r1"))  # ours reached the router
    assert probe.wait_for_subscriber(KEYS.odometry("r1"))  # and the estimator's
    odo = client.publisher(KEYS.odometry("r1"))
    obs = client.publisher(KEYS.observations("r1"))
    assert odo.wait_matched() and obs.wait_matched()  # type: ignore[attr-defined]
    odo.put(b"\x00garbage")
    odo.put(msgpack.packb({"schema": 1, "robot": "r1", "stamp": 1.0, "dt": 0.1,
                           "v": float("nan"), "w": 0.0}))
    odo.put(msgpack.packb({"schema": 1, "robot": "r1", "stamp": 1.0, "dt": 0.1, "v": [1, 2],
                           "w": 0.0}))
    obs.put(msgpack.packb(
        {"schema": 1, "robot": "r1", "stamp": 1.0, "ids": [1, 2], "ranges": [1.0],
         "bearings": [0.0, 0.1]}))
    odo.put(msgpack.packb({"schema": 1, "robot": "r1", "stamp": 1.1, "dt": 0.1, "v": 0.1,
                           "w": 0.0}))
    got.wait(lambda g: any(s.step != "init" for s in g.states), timeout=10)
    applied = [s for s in got.states if s.step != "init"]
    assert [s.step for s in applied] == ["predict"]
    assert applied[0].seq == 1
    out, err = stop(estimator)
    assert "dropped bad Odometry (1 so far)" in err
    assert "dropped bad Observations (1 so far)" in err
