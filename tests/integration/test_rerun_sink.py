"""``slamlens rerun`` as a process under bad input and load, on a real Zenoh router.

Malformed payloads on every key it reads (tests/fuzz.py): it drops and counts them, says
so in a few log lines, keeps running and draws the good state that follows. A flood of
states faster than it can log them: it takes the newest, counts the rest as superseded,
and holds at most one of each input (its slots are newest-wins)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slamlens.common.keys import Keys
from slamlens.common.messages import (
    CameraFrame,
    Health,
    Registration,
    ServiceStatus,
    SlamState,
    Truth,
)
from slamlens.services.harness.fuzz import bad_payloads, valid
from slamlens.services.harness.procs import Service, spawn, stop
from tests.rrd_check import read_rrd

KEYS = Keys()
ROBOT, CAMERA = "robot1", "cam1"


def _until(predicate: Callable[[], bool], timeout: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)
    return True


def _status(bus) -> ServiceStatus | None:
    replies = bus.get(f"{KEYS.prefix}/status/*/rerun/*", timeout=2.0)
    return ServiceStatus.from_bytes(replies[-1].payload) if replies else None


def _publisher(bus, key: str):
    import zenoh

    pub = bus.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    assert _until(lambda: pub.matching_status, 10.0), key
    return pub


def _final(out: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith("rerun stopped: ")][-1]
    return json.loads(line.split(": ", 1)[1])


def _sink(router_endpoint: str, path: Path) -> Service:
    proc = spawn("rerun", "--robot", ROBOT, "--camera", CAMERA, "--save", str(path),
                 "--late-join-timeout-s", "0", "--connect", router_endpoint)
    proc.wait_for_line("rerun ready")
    return proc


def test_the_sink_drops_and_counts_garbage_on_every_key_and_draws_what_follows(
        router_endpoint, make_client, tmp_path: Path) -> None:
    sink = _sink(router_endpoint, tmp_path / "fuzz.rrd")
    bus = make_client()
    inputs = [(KEYS.truth(ROBOT), Truth, "truth"), (KEYS.health(ROBOT), Health, "health"),
              (KEYS.registration(CAMERA, ROBOT), Registration, "registration"),
              (KEYS.frame(CAMERA), CameraFrame, "frame"), (KEYS.state(ROBOT), SlamState, "state")]
    try:
        good_truth = valid(Truth, robot=ROBOT).to_bytes()  # the robot's clock first
        _publisher(bus, KEYS.truth(ROBOT)).put(good_truth)
        for seed, (key, kind, name) in enumerate(inputs):
            pub = _publisher(bus, key)
            payloads = list(bad_payloads(kind, np.random.default_rng(seed), 60, robot=ROBOT,
                                         camera=CAMERA))
            before = _status(bus).dropped  # type: ignore[union-attr]
            # the sink keeps only the newest of each input, so most of a burst is superseded
            # before it is taken; at least one is taken and counted (put more until the
            # status, rebuilt once a second, says so)
            for payload in payloads:
                pub.put(payload)
            i = 0
            while not _until(lambda before=before: _status(bus).dropped > before,  # type: ignore
                             3.0):
                pub.put(payloads[i % len(payloads)])
                i += 1
                assert i < 30, f"nothing bad on {name} was counted"
            pub.undeclare()
        good = valid(SlamState, robot=ROBOT, seq=500)
        _publisher(bus, KEYS.state(ROBOT)).put(good.to_bytes())
        assert _until(lambda: _status(bus).counts["seq"] == 500)  # type: ignore[union-attr]
        assert sink.poll() is None
    finally:
        out, err = stop(sink)
    assert sink.returncode == 0, err
    summary = _final(out)
    assert set(summary["bad_by_kind"]) == {name for _, _, name in inputs}, summary
    said = [line for line in err.splitlines() if "dropped bad" in line]
    assert 5 <= len(said) <= 5 * 6, said  # a few lines per kind, not one per payload
    state = [r for r in read_rrd(tmp_path / "fuzz.rrd")[f"/world/{ROBOT}/features"]
             if r.get("seq") == 500]
    assert len(state) == 1 and state[0]["Points3D:labels"] == ["1", "2"]


def test_a_flood_of_states_is_taken_newest_first_and_never_queued(
        router_endpoint, make_client, tmp_path: Path) -> None:
    """2000 states of 60 features put as fast as Zenoh takes them: the sink draws what it
    can, newest first, ends on the last one, and every state it did not draw is counted
    superseded (received = drawn + superseded: nothing waits in a queue)."""
    sink = _sink(router_endpoint, tmp_path / "flood.rrd")
    bus = make_client()
    n = 60
    rng = np.random.default_rng(1)
    A = rng.normal(0, 0.05, (3 + 2 * n, 3 + 2 * n))
    base = dict(robot=ROBOT, step="update", pose=np.zeros(3), landmark_ids=np.arange(n),
                landmarks=rng.uniform(0, 10, (n, 2)), covariance=A @ A.T + 1e-3 * np.eye(3 + 2 * n),
                epoch=3)
    count = 2000
    payloads = [SlamState(seq=seq, stamp=0.05 * seq, **base).to_bytes() for seq in range(count)]
    pub = _publisher(bus, KEYS.state(ROBOT))
    try:
        for payload in payloads:
            pub.put(payload)
        assert _until(lambda: _status(bus).counts["seq"] == count - 1, 120)  # type: ignore
    finally:
        out, err = stop(sink)
    summary = _final(out)
    received, drawn = summary["received"]["state"], summary["drawn"]
    assert received == drawn + summary["superseded"]["state"], summary
    assert drawn < count and summary["superseded"]["state"] > 0, summary
    assert summary["bad"] == 0
    rows = read_rrd(tmp_path / "flood.rrd")[f"/world/{ROBOT}/ellipsoids"]
    seqs = [r["seq"] for r in rows]
    assert seqs == sorted(seqs) and seqs[-1] == count - 1
    assert len(rows[-1]["Ellipsoids3D:centers"]) == n * (n - 1) // 2
