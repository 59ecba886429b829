"""Drivers of several robots at once, as real processes on loopback:
`slamlens sim --robot r1,r2,r3` in one arena and `slamlens replay --robots all`. Each robot
has its own estimator (and, for the simulator, its own monitor checking it against the
arena's truth, re-expressed in that robot's map frame)."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

from slamlens.common.keys import Keys
from slamlens.common.messages import Health
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.procs import REPO, Service, slamlens_cmd, spawn, stop

FIXTURE = REPO / "tests" / "fixtures" / "mrclam_small"


def _final(out: str, name: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: ")][-1]
    return json.loads(line.split(": ", 1)[1])


def _counts(out: str, name: str) -> dict:
    return json.loads(out.split(f"{name} done: ", 1)[1].split(" in ")[0])


def _wait_for_health(endpoint: str, robot: str, *, seq: int, timeout: float = 120.0) -> None:
    bus = open_bus(BusSettings(connect=(endpoint,)))
    try:
        deadline = time.monotonic() + timeout
        last = -1
        while last < seq:
            assert time.monotonic() < deadline, f"{robot}'s monitor stopped at seq {last}"
            replies = bus.get(Keys().health(robot))
            last = Health.from_bytes(replies[0].payload).seq if replies else -1
            if last < seq:
                time.sleep(0.2)
    finally:
        bus.close()


def _group(endpoint: str, robots: list[str], *, monitors: bool) -> list[tuple[str, Service]]:
    procs: list[tuple[str, Service]] = []
    router = spawn("router", "--listen", endpoint)
    procs.append(("router", router))
    router.wait_for_line("router ready")
    for robot in robots:
        est = spawn("estimator", "--robot", robot, "--connect", endpoint)
        procs.append((f"estimator {robot}", est))
        if monitors:
            mon = spawn("monitor", "--robot", robot, "--connect", endpoint)
            procs.append((f"monitor {robot}", mon))
    for _, proc in procs[1:]:
        proc.wait_for_line(" ready", timeout=90)
    return procs


def test_three_simulated_robots_each_estimated_and_checked(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    robots = ["r1", "r2", "r3"]
    procs = _group(endpoint, robots, monitors=True)
    try:
        sim = subprocess.run(slamlens_cmd("sim", "--robot", ",".join(robots), "--marker-ids",
                                          "0,1,2", "--rate", "0", "--connect", endpoint),
                             cwd=REPO, capture_output=True, text=True, timeout=300)
        assert sim.returncode == 0, sim.stderr
        assert "all applied by the estimator" in sim.stdout
        counts = _counts(sim.stdout, "sim")
        assert counts == {"Odometry": 3 * 545, "Observations": 3 * 545, "Truth": 3 * 546}
        for robot in robots:  # each monitor checks at its own pace: wait for its last state
            _wait_for_health(endpoint, robot, seq=1090)
    finally:
        outputs = {name: stop(proc)[0] for name, proc in reversed(procs)}
    assert [p.returncode for _, p in procs] == [0] * len(procs)
    for robot in robots:
        e = _final(outputs[f"estimator {robot}"], "estimator")
        assert (e["odometry"], e["observation_batches"], e["landmarks"]) == (545, 545, 15), e
        assert e["foreign_robot"] == 0 and e["lost"] == 0
        m = _final(outputs[f"monitor {robot}"], "monitor")
        # the truth of robots 2 and 3 is said in the arena frame; the monitor re-expresses
        # it in their own map frames, so a correct run raises nothing for any of them
        assert m["checked"] >= 1090 and m["violations"] == 0 and m["verdict"] == "ok", m


def test_replay_publishes_every_robot_of_a_dataset(tmp_path: Path) -> None:
    dataset = tmp_path / "two_robots"
    dataset.mkdir()
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat"):
        (dataset / name).symlink_to(FIXTURE / name)
    for k in (1, 2):  # robot 2 replays robot 1's real files under its own name
        for kind in ("Odometry", "Measurement", "Groundtruth"):
            (dataset / f"Robot{k}_{kind}.dat").symlink_to(FIXTURE / f"Robot1_{kind}.dat")
    endpoint = free_tcp_endpoint()
    procs = _group(endpoint, ["robot1", "robot2"], monitors=False)
    try:
        replay = subprocess.run(slamlens_cmd("replay", str(dataset), "--robots", "all",
                                             "--duration", "10", "--rate", "0", "--connect",
                                             endpoint),
                                cwd=REPO, capture_output=True, text=True, timeout=300)
        assert replay.returncode == 0, replay.stderr
        assert "all applied by the estimator" in replay.stdout
        counts = _counts(replay.stdout, "replay")
    finally:
        outputs = {name: stop(proc)[0] for name, proc in reversed(procs)}
    one = _final(outputs["estimator robot1"], "estimator")
    two = _final(outputs["estimator robot2"], "estimator")
    for e in (one, two):
        assert e["foreign_robot"] == 0 and e["lost"] == 0 and e["odometry"] > 100
    assert (one["odometry"], one["observation_batches"]) == \
        (two["odometry"], two["observation_batches"])
    assert counts["Odometry"] == one["odometry"] + two["odometry"]
    assert counts["Observations"] == one["observation_batches"] + two["observation_batches"]
