"""Malformed payloads on every key a service subscribes to, through real processes.

A fast sample of tests/fuzz.py per key (benchmarks/bench_fuzz.py sends ≥ 100 000 each):
the service never crashes, counts every rejection, and still produces correct output
afterwards.
"""

from __future__ import annotations

import json
import threading

import numpy as np

from common.keys import Keys
from common.messages import Health, Observations, Odometry, SlamState, Truth
from tests.fuzz import bad_payloads, valid
from tests.procs import spawn, stop

KEYS = Keys()
ROBOT = "robot1"
PER_KEY = 400


def _final(out: str, name: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: ")][-1]
    return json.loads(line.split(": ", 1)[1])


class Inbox:
    def __init__(self, bus, key: str, kind) -> None:
        self.items: list = []
        self.kind = kind
        self.cond = threading.Condition()
        bus.subscribe(key, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        with self.cond:
            self.items.append(self.kind.from_bytes(payload))
            self.cond.notify_all()

    def wait(self, predicate, timeout: float = 30.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: predicate(self.items), timeout)


def _flood(bus, key: str, kind, count: int, seed: int) -> int:
    pub = bus.publisher(key)
    assert pub.wait_matched()  # a new publisher may drop what it puts before it matches
    n = 0
    for payload in bad_payloads(kind, np.random.default_rng(seed), count):
        pub.put(payload)
        n += 1
    return n


def test_estimator_survives_garbage_on_both_input_keys(router_endpoint, make_client) -> None:
    est = spawn("estimator", "--robot", ROBOT, "--connect", router_endpoint)
    est.wait_for_line("estimator ready")
    client = make_client()
    states = Inbox(client, KEYS.state(ROBOT), SlamState)
    assert client.wait_for_subscriber(KEYS.odometry(ROBOT))
    try:
        sent = _flood(client, KEYS.odometry(ROBOT), Odometry, PER_KEY, 1)
        sent += _flood(client, KEYS.observations(ROBOT), Observations, PER_KEY, 2)
        # afterwards, correct output: an odometry step then an observation batch
        client.publisher(KEYS.odometry(ROBOT)).put(valid(Odometry, robot=ROBOT).to_bytes())
        client.publisher(KEYS.observations(ROBOT)).put(
            valid(Observations, robot=ROBOT).to_bytes())
        assert states.wait(lambda s: any(x.step == "update" and x.n == 2 for x in s))
        assert est.poll() is None
    finally:
        out, err = stop(est)
    assert est.returncode == 0, err
    summary = _final(out, "estimator")
    assert summary["dropped"] == sent, summary
    assert summary["odometry"] == 1 and summary["observation_batches"] == 1
    assert "Traceback" not in err


def test_monitor_survives_garbage_on_state_truth_and_tracked(router_endpoint,
                                                            make_client) -> None:
    mon = spawn("monitor", "--robot", ROBOT, "--connect", router_endpoint)
    mon.wait_for_line("monitor ready")
    client = make_client()
    healths = Inbox(client, KEYS.health(ROBOT), Health)
    assert client.wait_for_subscriber(KEYS.state(ROBOT))
    try:
        sent = _flood(client, KEYS.state(ROBOT), SlamState, PER_KEY, 3)
        sent += _flood(client, KEYS.truth(ROBOT), Truth, PER_KEY, 4)
        sent += _flood(client, KEYS.tracked(ROBOT), Truth, PER_KEY, 5)
        pub = client.publisher(KEYS.state(ROBOT))
        for seq in (1, 2):
            pub.put(valid(SlamState, robot=ROBOT, seq=seq).to_bytes())
        assert healths.wait(lambda h: [x.seq for x in h] == [1, 2])
        assert all(h.ok for h in healths.items)
        assert mon.poll() is None
    finally:
        out, err = stop(mon)
    assert mon.returncode == 0, err
    summary = _final(out, "monitor")
    assert summary["dropped"] == sent and summary["checked"] == 2, summary
    assert "Traceback" not in err
