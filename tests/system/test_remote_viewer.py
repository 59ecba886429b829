"""A viewer on the far side of a 20 Mbit/s link draws from the robot's summary stream
(docs/remote_viewers.md).

Two network namespaces joined by a veth pair shaped to 20 Mbit/s both ways (``tbf``); the
workstation's processes get a /dev/shm of their own (``harness.netns.own_shm``), as a real
second host has. The robot runs its router, the simulator, the estimator and ``slamlens
summary``; the workstation its router and ``slamlens viewer --source summary``, which pulls
the clustered summary instead of subscribing to the state. The viewer's picture follows
the robot, and every service exits cleanly.
"""

from __future__ import annotations

import subprocess
import time

from slamlens.services.harness.netns import Hosts, curl_json, own_shm
from slamlens.services.harness.procs import Service, Started, slamlens_cmd, spawn, stop

ROBOT = "robot1"
VIEWER = "http://127.0.0.1:8080"


def _status(ns: str) -> dict | None:
    return curl_json(ns, f"{VIEWER}/api/status", timeout=2.0)


def test_a_remote_viewer_draws_the_summary_behind_a_slow_link(two_hosts: Hosts) -> None:
    h = two_hosts
    h.shape("20mbit", burst="32kbit", latency="400ms")
    local = "tcp/127.0.0.1:7447"
    started = Started()

    def start(ns: str, *args: str, ready: str, isolated: bool = False) -> Service:
        if not isolated:
            return started.start(*args, ready=ready, netns=ns)
        argv = ["ip", "netns", "exec", ns, *own_shm(slamlens_cmd(*args))]
        return started.add(Service(argv), ready=ready)

    try:
        start(h.workstation, "router", "--listen", f"tcp/{h.workstation_ip}:7447",
              "--listen", local, ready="router ready", isolated=True)
        start(h.robot, "router", "--listen", local, "--connect",
              f"tcp/{h.workstation_ip}:7447", ready="router ready")
        est = start(h.robot, "estimator", "--robot", ROBOT, ready="estimator ready")
        summary = start(h.robot, "summary", "--robot", ROBOT, ready="summary ready")
        viewer = start(h.workstation, "viewer", "--robot", ROBOT, "--source", "summary",
                       "--http", "127.0.0.1:8080", ready="viewer ready", isolated=True)
        sim = started.add(spawn("sim", "--robot", ROBOT, "--rate", "2", "--seed", "7",
                                netns=h.robot))

        seen: list[int] = []
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            state = (_status(h.workstation) or {}).get("state")
            if state and (not seen or state["seq"] > seen[-1]):
                seen.append(state["seq"])
                assert state["age_s"] < 2.0, state
            if len(seen) >= 5 and seen[-1] >= 60 and state and state["n"] >= 3:
                break
            time.sleep(0.2)
        else:
            logs = "\n".join(f"{p.args[-6:]}: {''.join(p.err[-8:])}" for p in started.procs)
            raise AssertionError(f"the remote viewer did not follow the robot: {seen}\n{logs}")
        shot = subprocess.run(["ip", "netns", "exec", h.workstation, "curl", "-s", "-D", "-",
                               "-o", "/dev/null", f"{VIEWER}/snapshot.png"],
                              capture_output=True, text=True, timeout=30).stdout
        assert "200 OK" in shot and "X-State-Seq" in shot, shot
        stop(sim)
        stop(viewer)  # (exit timing is the business of the services' own tests)
        summary_out, _ = stop(summary)
        stop(est)
    finally:
        started.stop_all()
    assert viewer.returncode == 0 and summary.returncode == 0
    assert "summary stopped:" in summary_out
    answered = int(summary_out.split('"answered": ', 1)[1].split(",")[0])
    assert answered >= 5
