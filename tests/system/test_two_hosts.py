"""Two hosts on one machine (SPEC §7b): network namespaces "robot" and "workstation" joined by
a veth pair, each with its own `slamlens router` over mutual TLS, the robot's router linked
to the workstation's. The simulator and the estimator run on the robot, the monitor and a
viewer-like subscriber on the workstation; states cross the link one way, health the other,
and neither router refuses anything the real services say.
"""

from __future__ import annotations

import json
import secrets
import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from common.certs import extend_authority
from tests.procs import REPO, Output, netns_cmd, slamlens_cmd, spawn_in

NAMES = ["router-ws", "router-robot", "robot-r1", "monitor-r1", "viewer-ws", "viewer-robot"]


@dataclass(frozen=True)
class Hosts:
    robot: str  #: namespace of the robot
    workstation: str  #: namespace of the workstation
    robot_ip: str
    workstation_ip: str


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=10)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    if shutil.which("ip") is None:
        pytest.skip("iproute2's `ip` is not installed: no network namespaces")
    tag = secrets.token_hex(3)  # unique names: other test runs may share this machine
    robot, workstation = f"robot-{tag}", f"workstation-{tag}"
    probe = subprocess.run(["ip", "netns", "add", robot], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"`ip netns` is unavailable here: {probe.stderr.strip()}")
    made = [robot]
    try:
        _ip("netns", "add", workstation)
        made.append(workstation)
        a, b = secrets.randbelow(200) + 20, secrets.randbelow(250)
        robot_ip, ws_ip = f"10.{a}.{b}.1", f"10.{a}.{b}.2"  # inside the namespaces only
        _ip("link", "add", f"vr{tag}", "type", "veth", "peer", "name", f"vw{tag}")
        _ip("link", "set", f"vr{tag}", "netns", robot)
        _ip("link", "set", f"vw{tag}", "netns", workstation)
        for ns, dev, addr in ((robot, f"vr{tag}", robot_ip), (workstation, f"vw{tag}", ws_ip)):
            _ip("-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield Hosts(robot, workstation, robot_ip, ws_ip)
    finally:
        for ns in made:  # deleting a namespace deletes its end of the veth pair, and so both
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_secure_pipeline_across_two_hosts(hosts: Hosts, tmp_path) -> None:
    pki = tmp_path / "pki"
    extend_authority(pki, NAMES, hosts=[hosts.workstation_ip])
    secure = ("--secure", str(pki))
    ws_port = f"tls/{hosts.workstation_ip}:7447"
    procs: list[Output] = []

    def start(ns: str, *args: str, module: str = "services") -> Output:
        proc = Output(spawn_in(ns, *args, module=module))
        procs.append(proc)
        return proc

    try:
        ws_router = start(hosts.workstation, "router", "--listen", "tls/127.0.0.1:7447",
                          "--listen", ws_port, *secure, "--name", "router-ws")
        ws_router.wait("router ready", timeout=30)
        robot_router = start(hosts.robot, "router", "--listen", "tls/127.0.0.1:7447",
                             "--connect", ws_port, *secure, "--name", "router-robot")
        robot_router.wait("router ready", timeout=30)

        monitor = start(hosts.workstation, "monitor", "--robot", "r1", *secure,
                        "--name", "monitor-r1")
        viewer = start(hosts.workstation, "slamlens/robot/r1/**", *secure, "--name",
                       "viewer-ws", module="tests.bus_probe")
        on_robot = start(hosts.robot, "slamlens/robot/r1/health", *secure, "--name",
                         "viewer-robot", module="tests.bus_probe")
        estimator = start(hosts.robot, "estimator", "--robot", "r1", *secure,
                          "--name", "robot-r1")
        monitor.wait("monitor ready")
        viewer.wait("probe ready")
        on_robot.wait("probe ready")
        estimator.wait("estimator ready")

        # the simulator waits for the estimator's liveliness token, then runs flat out
        sim = subprocess.run(
            netns_cmd(hosts.robot, *slamlens_cmd("sim", "--robot", "r1", "--scenario", "paper",
                                                 "--rate", "0", *secure, "--name", "robot-r1")),
            cwd=REPO, capture_output=True, text=True, timeout=180)
        assert sim.returncode == 0, sim.stderr
        assert "sim done" in sim.stdout

        # states reached the workstation; health, made there, came back to the robot
        viewer.wait("first slamlens/robot/r1/state")
        viewer.wait("first slamlens/robot/r1/health")
        on_robot.wait("first slamlens/robot/r1/health")
    finally:
        statuses = [p.stop() for p in reversed(procs)]
    counts = json.loads(viewer.wait("probe done: ").split("probe done: ", 1)[1])
    assert counts["slamlens/robot/r1/state"] > 100
    assert counts["slamlens/robot/r1/odometry"] > 100  # the inputs cross the link too
    assert statuses == [0] * len(procs), [(p.proc.args, p.stderr[-5:]) for p in procs]
    for router in (ws_router, robot_router):
        log = "\n".join(router.stderr)
        assert "mutual TLS" in log
        assert "refused" not in log, log  # the real services say nothing outside their roles
