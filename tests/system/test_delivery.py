"""Delivery under faults (docs/delivery.md), with real processes on loopback.

Flood at full speed, SIGKILL and restart with and without a checkpoint, a router killed
and restarted, SIGTERM in the middle of a flood: every input applied exactly once, every
state published, the monitor checks or counts every state, every service exits cleanly.
"""

from __future__ import annotations

import json
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState, peek_fields
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.collect import StateCollector
from slamlens.services.harness.procs import REPO, Service, spawn, stop

KEYS = Keys()
ROBOT = "robot1"


def final(proc: Service, out: str, name: str) -> dict:
    """The JSON of a service's final line ``"{name} stopped: {...}"``."""
    lines = [ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: ")]
    assert lines, f"{name} printed no final line; stdout:\n{out[-800:]}\nstderr:\n" \
                  f"{''.join(proc.err[-20:])}"
    return json.loads(lines[-1].split(": ", 1)[1])


def driver_counts(out: str, name: str) -> dict:
    line = next(ln for ln in out.splitlines() if ln.startswith(f"{name} done: "))
    return json.loads(line.split(": ", 1)[1].split(" in ")[0])


class States(StateCollector):
    """Every state on the robot's key (as a recorder): its seq, epoch and step, and the last."""

    def __init__(self, endpoint: str) -> None:
        self.heads: list[dict] = []
        self.last: bytes | None = None
        super().__init__(endpoint, KEYS.state(ROBOT), history_s=30.0)

    def take(self, payload: bytes) -> None:
        self.heads.append(peek_fields(payload, ("seq", "epoch", "step")))
        self.last = payload

    def max_seq(self) -> int:
        return max((h["seq"] for h in self.heads), default=-1)


@pytest.fixture
def router() -> Service:
    endpoint = free_tcp_endpoint()
    proc = spawn("router", "--listen", endpoint)
    proc.wait_for_line("router ready")
    proc.endpoint = endpoint  # type: ignore[attr-defined]
    yield proc
    stop(proc)


def _estimator(endpoint: str, *extra: str) -> Service:
    proc = spawn("estimator", "--robot", ROBOT, "--connect", endpoint, *extra)
    proc.wait_for_line("estimator ready")
    return proc


def _flood(ep: str, states: States, *, seed: int) -> int:
    """Eight paper loops at rate 0 (paced on the estimator): every input applied, and the
    recovering subscriber has every state. Returns the number of inputs."""
    sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", "8", "--seed", str(seed),
                "--connect", ep)
    out, err = sim.communicate(timeout=300)
    assert sim.returncode == 0, err
    assert "all applied by the estimator" in out, out
    counts = driver_counts(out, "sim")
    inputs = counts["Odometry"] + counts["Observations"]
    assert states.wait(lambda s: s.max_seq() >= inputs)
    return inputs


def test_flood_at_full_speed_every_input_applied_every_state_checked(router) -> None:
    ep = router.endpoint
    est = _estimator(ep)
    mon = spawn("monitor", "--robot", ROBOT, "--connect", ep)
    mon.wait_for_line("monitor ready")
    states = States(ep)
    try:
        inputs = _flood(ep, states, seed=2)
        # the monitor checks every state, however far behind it fell: wait for the last
        assert _wait(lambda: _health_seq(ep) >= inputs, timeout=120), _health_seq(ep)
    finally:
        est_out, _ = stop(est)
        mon_out, _ = stop(mon, sig=signal.SIGINT)
        states.close()
    e = final(est, est_out, "estimator")
    assert e["seq"] == inputs and e["odometry"] + e["observation_batches"] == inputs
    assert e["lost"] == 0 and e["refused"] == 0
    seqs = [h["seq"] for h in states.heads]
    assert sorted(set(seqs)) == list(range(0, inputs + 1)), "a state never arrived"
    m = final(mon, mon_out, "monitor")
    assert m["checked"] + m["lost"] >= inputs, m
    assert m["violations"] == 0 and m["suspects"] == [], m


def _probe(endpoint: str, *extra: str) -> Service:
    probe = Service([sys.executable, "-m", "tests.bus_probe", KEYS.state(ROBOT),
                     "--connect", endpoint, *extra], cwd=REPO)
    probe.wait_for_line("probe ready")
    return probe


def _probe_counts(probe: Service) -> int:
    out, _ = stop(probe)
    line = next(ln for ln in out.splitlines() if ln.startswith("probe done: "))
    return sum(json.loads(line.split(": ", 1)[1]).values())


def test_a_stalled_subscriber_and_ten_more_cost_the_flood_nothing(router) -> None:
    """docs/delivery.md: a client whose callback sits 1 s per state (a paused debugger) and ten
    more subscribers: the estimator still applies every input and publishes every state,
    the recovering subscriber gets them all, the stalled client is dropped for."""
    ep = router.endpoint
    est = _estimator(ep)
    stalled = _probe(ep, "--stall", "1.0")
    crowd = _probe(ep, "--subscribers", "10")
    states = States(ep)
    try:
        inputs = _flood(ep, states, seed=3)
    finally:
        est_out, _ = stop(est)
        got_stalled = _probe_counts(stalled)
        got_crowd = _probe_counts(crowd)
        states.close()
    e = final(est, est_out, "estimator")
    assert e["seq"] == inputs and e["lost"] == 0 and e["refused"] == 0, e
    assert sorted({h["seq"] for h in states.heads}) == list(range(0, inputs + 1))
    # the stalled client saw some (Zenoh runs its callbacks on a few threads: 263 of 2930
    # here), nowhere near all of them: it was dropped for, not waited for
    assert 1 <= got_stalled < inputs // 2, (got_stalled, inputs)
    # the ten others were served too (each counts; drops under load are allowed for them)
    assert got_crowd >= 10, got_crowd


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.2)
    return predicate()


def _health_seq(ep: str) -> int:
    """The seq of the state the monitor checked last (its Health, by ``get``)."""
    bus = open_bus(BusSettings(connect=(ep,)))
    try:
        replies = bus.get(KEYS.health(ROBOT), timeout=2.0)
        return int(peek_fields(replies[0].payload, ("seq",))["seq"]) if replies else -1
    finally:
        bus.close()


def _sim(ep: str, *extra: str) -> Service:
    return spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", "12", "--seed", "5",
                 "--connect", ep, *extra)


def _final_state(ep: str) -> SlamState:
    bus = open_bus(BusSettings(connect=(ep,)))
    try:
        replies = bus.get(KEYS.state(ROBOT), timeout=5.0)
        assert len(replies) == 1
        return SlamState.from_bytes(replies[0].payload)
    finally:
        bus.close()


def test_sigkill_and_restart_from_a_checkpoint_equals_an_uninterrupted_run(
        router, tmp_path: Path) -> None:
    ep = router.endpoint
    # the uninterrupted run
    est = _estimator(ep)
    sim = _sim(ep)
    out, err = sim.communicate(timeout=300)
    assert sim.returncode == 0 and "all applied" in out, out + err
    reference = _final_state(ep)
    stop(est)

    # the same run, the estimator killed in the middle and started again
    checkpoints = tmp_path / "ckpt"
    est = _estimator(ep, "--checkpoint", str(checkpoints))
    states = States(ep)
    sim = _sim(ep)
    try:
        ckpt_file = checkpoints / f"estimator-{ROBOT}.ckpt"
        assert states.wait(lambda s: s.max_seq() >= reference.seq // 3 and ckpt_file.exists())
        est.kill()
        est.wait(10)
        restarted = time.monotonic()
        est = _estimator(ep, "--checkpoint", str(checkpoints))
        out, err = sim.communicate(timeout=300)
        assert sim.returncode == 0 and "all applied" in out, out + err
        assert time.monotonic() - restarted < 60
        resumed = _final_state(ep)
    finally:
        est_out, _ = stop(est)
        states.close()
    summary = final(est, est_out, "estimator")
    assert summary["resumed"] is True and summary["lost"] == 0
    assert resumed.seq == reference.seq
    assert len({h["epoch"] for h in states.heads}) == 1  # one map, one epoch
    np.testing.assert_array_equal(resumed.landmark_ids, reference.landmark_ids)
    np.testing.assert_array_equal(resumed.covariance, reference.covariance)
    np.testing.assert_array_equal(resumed.pose, reference.pose)


def test_restart_without_checkpoint_is_a_new_epoch_the_monitor_says_so(router) -> None:
    ep = router.endpoint
    est = _estimator(ep)
    mon = spawn("monitor", "--robot", ROBOT, "--connect", ep)
    mon.wait_for_line("monitor ready")
    states = States(ep)
    sim = spawn("sim", "--robot", ROBOT, "--rate", "4", "--seed", "5", "--connect", ep)
    try:
        assert states.wait(lambda s: s.max_seq() >= 40)
        first_epoch = states.heads[-1]["epoch"]
        est.kill()
        est.wait(10)
        est = _estimator(ep)
        assert states.wait(lambda s: any(h["epoch"] != first_epoch and h["seq"] >= 20
                                         for h in s.heads))
    finally:
        stop(sim)
        est_out, _ = stop(est)
        mon_out, mon_err = stop(mon)
        states.close()
    assert "map restarted" in mon_err
    m = final(mon, mon_out, "monitor")
    assert m["restarts"] == 1 and m["violations"] == 0, m
    assert final(est, est_out, "estimator")["resumed"] is False


def test_a_router_killed_and_back_after_5_s_loses_nothing(tmp_path: Path) -> None:
    ep = free_tcp_endpoint()
    router = spawn("router", "--listen", ep)
    router.wait_for_line("router ready")
    est = _estimator(ep)
    sim = spawn("sim", "--robot", ROBOT, "--rate", "2", "--seed", "1", "--connect", ep)
    states = States(ep)
    try:
        assert states.wait(lambda s: s.max_seq() >= 30)
        router.kill()
        router.wait(10)
        time.sleep(5.0)  # the fault itself: the router is down for 5 s
        router = spawn("router", "--listen", ep)
        router.wait_for_line("router ready")
        out, err = sim.communicate(timeout=120)
        assert sim.returncode == 0, err
        counts = driver_counts(out, "sim")
        inputs = counts["Odometry"] + counts["Observations"]
        assert states.wait(lambda s: s.max_seq() >= inputs, timeout=30)
    finally:
        est_out, _ = stop(est)
        states.close()
        stop(router)
    e = final(est, est_out, "estimator")
    assert e["odometry"] + e["observation_batches"] == inputs, e
    assert e["lost"] == 0 and e["duplicates"] >= 0


def test_sigterm_in_the_middle_of_a_flood_every_service_exits_within_2_s(router) -> None:
    ep = router.endpoint
    est = _estimator(ep)
    mon = spawn("monitor", "--robot", ROBOT, "--connect", ep)
    mon.wait_for_line("monitor ready")
    states = States(ep)
    sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", "200", "--seed", "4",
                "--connect", ep)
    try:
        assert states.wait(lambda s: s.max_seq() >= 2000)
    finally:
        states.close()
    for proc, name in ((sim, "sim"), (est, "estimator"), (mon, "monitor")):
        started = time.monotonic()
        out, _ = stop(proc, timeout=10)
        took = time.monotonic() - started
        assert proc.returncode == 0, f"{name} exited {proc.returncode}"
        assert took < 2.0, f"{name} took {took:.1f} s to exit"
        assert f"{name} stopped" in out, f"{name}: {out[-300:]}"
