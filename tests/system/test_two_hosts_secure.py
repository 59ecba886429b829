"""Two hosts on one machine over mutual TLS (docs/security.md): network namespaces "robot" and
"workstation" joined by a veth pair (the `two_hosts` fixture), each with its own
`slamlens router --secure`, the robot's linked to the workstation's. The simulator and the
estimator run on the robot, the monitor and a viewer-like subscriber on the workstation;
states cross the link one way, health the other, and neither router refuses anything the
real services say.
"""

from __future__ import annotations

import json
import sys

from slamlens.common.certs import extend_authority
from slamlens.services.harness.netns import Hosts
from slamlens.services.harness.procs import REPO, Service, slamlens_cmd, spawn, stop

NAMES = ["router-ws", "router-robot", "robot-r1", "monitor-r1", "viewer-ws", "viewer-robot"]


def _probe(ns: str, key: str, *flags: str) -> Service:
    """``tests/bus_probe.py`` subscribed to ``key`` inside namespace ``ns``."""
    return Service(["ip", "netns", "exec", ns, sys.executable, "-m", "tests.bus_probe", key,
                    *flags], cwd=REPO)


def test_secure_pipeline_across_two_hosts(two_hosts: Hosts, tmp_path) -> None:
    h = two_hosts
    pki = tmp_path / "pki"
    # clients check the router's certificate against the address they dial
    extend_authority(pki, NAMES, hosts=[h.workstation_ip])
    secure = ("--secure", str(pki))
    local, ws_port = "tls/127.0.0.1:7447", f"tls/{h.workstation_ip}:7447"
    procs: list[Service] = []

    def start(proc: Service, ready: str) -> Service:
        procs.append(proc)
        proc.wait_for_line(ready)
        return proc

    try:
        ws_router = start(spawn("router", "--listen", local, "--listen", ws_port, *secure,
                                "--name", "router-ws", netns=h.workstation), "router ready")
        robot_router = start(spawn("router", "--listen", local, "--connect", ws_port, *secure,
                                   "--name", "router-robot", netns=h.robot), "router ready")
        start(spawn("monitor", "--robot", "r1", *secure, "--name", "monitor-r1",
                    netns=h.workstation), "monitor ready")
        viewer = start(_probe(h.workstation, "slamlens/robot/r1/**", *secure,
                              "--name", "viewer-ws"), "probe ready")
        on_robot = start(_probe(h.robot, "slamlens/robot/r1/health", *secure,
                                "--name", "viewer-robot"), "probe ready")
        start(spawn("estimator", "--robot", "r1", *secure, "--name", "robot-r1",
                    netns=h.robot), "estimator ready")

        # the simulator waits for the estimator's liveliness token, then runs flat out
        sim = Service(["ip", "netns", "exec", h.robot,
                       *slamlens_cmd("sim", "--robot", "r1", "--scenario", "paper", "--rate",
                                     "0", *secure, "--name", "robot-r1")])
        out, err = sim.communicate(timeout=180)
        assert sim.returncode == 0, err
        assert "sim done" in out

        # states reached the workstation; health, made there, came back to the robot
        viewer.wait_for_line("first slamlens/robot/r1/health")
        on_robot.wait_for_line("first slamlens/robot/r1/health")
        assert "first slamlens/robot/r1/state\n" in viewer.out
    finally:
        outputs = [stop(p) for p in reversed(procs)]
    viewer_out = "".join(viewer.out)
    counts = json.loads(viewer_out.split("probe done: ", 1)[1].splitlines()[0])
    assert counts["slamlens/robot/r1/state"] > 100
    assert counts["slamlens/robot/r1/odometry"] > 100  # the inputs cross the link too
    assert [p.returncode for p in procs] == [0] * len(procs), outputs
    for router in (ws_router, robot_router):
        log = "".join(router.err)
        assert "mutual TLS" in log
        assert "refused" not in log, log  # the real services say nothing outside their roles
