"""The ``large`` world through real processes: sim → estimator over Zenoh."""

from __future__ import annotations

import time

import msgpack
import numpy as np

from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState
from slamlens.services.harness.procs import spawn, stop, wait_for_line
from slamlens.services.slam.world import load_world

KEYS = Keys()


def test_a_short_large_run_maps_its_features(router_endpoint, make_client) -> None:
    """A stretch of the lawnmower run at full speed: the estimator maps the first lanes'
    landmarks, each with the id of a landmark of the world, near where it truly is."""
    estimator = spawn("estimator", "--robot", "r1", "--connect", router_endpoint)
    sim = None
    try:
        wait_for_line(estimator, "estimator ready")
        sim = spawn("sim", "--robot", "r1", "--scenario", "large", "--rate", "0",
                    "--seed", "5", "--connect", router_endpoint, "--progress", "off")
        client = make_client()
        deadline = time.monotonic() + 120
        n = 0
        while n < 150:  # the estimator's header says how far the map has grown
            assert time.monotonic() < deadline, f"only {n} landmarks after 120 s"
            assert sim.poll() is None, sim.output()
            replies = client.get(KEYS.state("r1") + "?header", timeout=2.0)
            n = int(msgpack.unpackb(replies[0].payload).get("n", 0)) if replies else 0
        stop(sim)
        state = SlamState.from_bytes(client.get(KEYS.state("r1"), timeout=10.0)[0].payload)
    finally:
        if sim is not None and sim.poll() is None:
            stop(sim)
        out, err = stop(estimator)
    assert estimator.returncode == 0, err
    world = load_world("large")
    truth = dict(zip(world.landmark_ids.tolist(), world.landmarks_xy, strict=True))
    assert state.n >= 150 and set(state.landmark_ids.tolist()) <= set(truth)
    assert len(set(state.landmark_ids.tolist())) == state.n
    # the map frame is the world frame here (start pose at the origin, facing +x). Over a
    # 38 m lane the whole map drifts (tens of cm: EKF-SLAM without a loop closure yet), so
    # the test is that each landmark's error is what its own covariance says it may be,
    # and that the map's local shape is right
    ids = [int(i) for i in state.landmark_ids]
    P = state.covariance
    for k, i in enumerate(ids):
        e = state.landmarks[k] - truth[i]
        d2 = float(e @ np.linalg.solve(P[3 + 2 * k:5 + 2 * k, 3 + 2 * k:5 + 2 * k], e))
        assert d2 < 18.4, (i, e, d2)  # χ²(2) at 1 − 1e-4
    near = [abs(float(np.hypot(*(state.landmarks[a] - state.landmarks[b]))
                      - np.hypot(*(truth[ids[a]] - truth[ids[b]]))))
            for a in range(state.n) for b in range(a + 1, state.n)
            if np.hypot(*(truth[ids[a]] - truth[ids[b]])) < 1.5]
    assert len(near) > state.n and np.median(near) < 0.05
    assert np.allclose(P, P.T)
