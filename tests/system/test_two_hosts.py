"""A robot and a workstation on one machine (network namespaces), the link cut for 5 s.

The robot runs its own router, linked to the workstation's, with the simulator and the
estimator behind it: driver → estimator traffic never crosses the link, so the robot
keeps estimating while the link is down. The workstation runs the monitor and the viewer.
When the link returns, the viewer shows the newest state within 2 s and the monitor has
checked (recovered from the estimator's cache) or counted every state.
"""

from __future__ import annotations

import json
import os
import subprocess
import time

import pytest

from slamlens.services.harness.netns import Hosts, available, curl_json, make_hosts
from slamlens.services.harness.procs import Started, spawn, stop

ROBOT = "robot1"
VIEWER = "http://127.0.0.1:8080"


def _final(out: str, name: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: ")][-1]
    return json.loads(line.split(": ", 1)[1])


def _viewer_state(ns: str) -> dict | None:
    status = curl_json(ns, f"{VIEWER}/api/status", timeout=2.0)
    return None if status is None else status.get("state")


def test_the_robot_keeps_estimating_through_a_link_cut(two_hosts: Hosts) -> None:
    h = two_hosts
    local = "tcp/127.0.0.1:7447"  # each host's own loopback
    started = Started()
    try:
        started.start("router", "--listen", f"tcp/{h.workstation_ip}:7447", "--listen", local,
                      ready="router ready", netns=h.workstation)
        started.start("router", "--listen", local, "--connect", f"tcp/{h.workstation_ip}:7447",
                      ready="router ready", netns=h.robot)
        est = started.start("estimator", "--robot", ROBOT, ready="estimator ready",
                            netns=h.robot)
        mon = started.start("monitor", "--robot", ROBOT, ready="monitor ready",
                            netns=h.workstation)
        viewer = started.start("viewer", "--robot", ROBOT, "--http", "127.0.0.1:8080",
                               ready="viewer ready", netns=h.workstation)
        sim = started.add(spawn("sim", "--robot", ROBOT, "--rate", "2", "--seed", "7",
                                netns=h.robot))

        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            state = _viewer_state(h.workstation)
            if state and state["seq"] >= 60:
                break
            time.sleep(0.2)
        else:
            raise AssertionError("the workstation never saw the robot's states")

        h.link(False)
        cut_at = time.monotonic()
        before = _viewer_state(h.workstation)
        assert before is not None
        time.sleep(5.0)  # the fault: 5 s without a link
        during = _viewer_state(h.workstation)
        assert during is not None and during["seq"] <= before["seq"] + 5, "link not cut"
        h.link(True)
        up_at = time.monotonic()
        # states made while the link was down: ~10 states/s of robot time × 2 × 5 s
        wanted = before["seq"] + 50
        resumed = None
        while time.monotonic() - up_at < 10:
            state = _viewer_state(h.workstation)
            if state and state["seq"] >= wanted and state["age_s"] < 0.5:
                resumed = time.monotonic() - up_at
                break
            time.sleep(0.1)
        assert resumed is not None, f"the viewer did not resume ({state})"
        assert resumed <= 2.0, f"the viewer showed the newest state {resumed:.2f} s after"
        assert up_at - cut_at >= 5.0

        out, err = sim.communicate(timeout=120)
        assert sim.returncode == 0, err
        counts = json.loads(out.split("sim done: ", 1)[1].split(" in ")[0])
        inputs = counts["Odometry"] + counts["Observations"]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # the monitor catches up
            status = curl_json(h.workstation, f"{VIEWER}/api/status", timeout=2.0)
            if status and status.get("health") and status["health"]["seq"] >= inputs:
                break
            time.sleep(0.2)
        est_out, _ = stop(est)
        mon_out, _ = stop(mon)
        stop(viewer)
    finally:
        started.stop_all()
    e = _final(est_out, "estimator")
    assert e["odometry"] + e["observation_batches"] == inputs and e["lost"] == 0, e
    m = _final(mon_out, "monitor")
    assert m["checked"] + m["lost"] >= inputs, m
    assert m["violations"] == 0, m


def test_a_killed_runs_namespaces_are_removed_by_the_next() -> None:
    """A pair left by a run that was killed (its pid gone) is deleted when the next test
    makes its hosts; a live process's pair is left alone."""
    why = available()
    if why is not None:
        pytest.skip(f"needs network namespaces: {why}")
    dead = subprocess.Popen(["true"])
    dead.wait()  # a pid that no longer runs (reaped)
    orphan, alive = f"slr-ws-{dead.pid}-0abcde", f"slr-ws-{os.getpid()}-0fedcb"
    for ns in (orphan, alive):
        subprocess.run(["ip", "netns", "add", ns], check=True)
    try:
        hosts = make_hosts()
        hosts.remove()
        names = subprocess.run(["ip", "netns", "list"], capture_output=True,
                               text=True).stdout.split()
        assert orphan not in names and alive in names
        assert hosts.robot not in names and hosts.workstation not in names
    finally:
        for ns in (orphan, alive):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
