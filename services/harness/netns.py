"""Two hosts on one machine: network namespaces joined by a veth pair (tests only).

Only addresses inside the namespaces a test made itself (10.200.x.0/24) and their own
loopbacks are used; the namespaces and the pair are removed afterwards, and a pair whose
maker is gone (a run killed before its teardown) by the next run that makes hosts. Needs
root and iproute2 (CI runs as root).
"""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
from dataclasses import dataclass, field


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=10)


def available() -> str | None:
    """None if namespaces can be made here, else why not."""
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root"
    return None


@dataclass
class Hosts:
    """Two namespaces, ``robot`` and ``workstation``, and the link between them."""

    robot: str
    workstation: str
    robot_ip: str
    workstation_ip: str
    robot_dev: str
    workstation_dev: str
    _made: list[str] = field(default_factory=list)

    def link(self, up: bool) -> None:
        """Bring the link up or cut it (on the robot's side)."""
        _ip("-n", self.robot, "link", "set", self.robot_dev, "up" if up else "down")

    def shape(self, rate: str, *, burst: str = "32kb", latency: str = "50ms") -> None:
        """Limit both directions with a token bucket (``tc qdisc … tbf``), e.g. '20mbit'."""
        for ns, dev in ((self.robot, self.robot_dev), (self.workstation, self.workstation_dev)):
            subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev,
                            "root", "tbf", "rate", rate, "burst", burst, "latency", latency],
                           check=True, capture_output=True, timeout=10)

    def remove(self) -> None:
        for ns in self._made:
            _delete_namespace(ns)


def _delete_namespace(ns: str) -> None:
    """Kill what runs in ``ns`` and delete it."""
    pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True,
                          text=True).stdout.split()
    for pid in pids:
        try:
            os.kill(int(pid), 9)
        except (ProcessLookupError, ValueError):
            pass
    subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _remove_orphans() -> None:
    """Delete the namespaces of test processes that are gone: a run killed (SIGKILL, or a
    SIGTERM pytest does not turn into teardown) leaves its pair behind. A namespace's name
    carries the pid that made it; another live run's are left alone."""
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    for ns in (line.split()[0] for line in names.splitlines() if line.startswith("slr-")):
        parts = ns.split("-")  # slr-{robot|ws}-PID-TAG
        if len(parts) == 4 and parts[2].isdigit() and not os.path.exists(f"/proc/{parts[2]}"):
            _delete_namespace(ns)


def make_hosts() -> Hosts:
    _remove_orphans()
    tag = secrets.token_hex(3)
    subnet = 1 + int(tag, 16) % 250
    me = os.getpid()
    hosts = Hosts(robot=f"slr-robot-{me}-{tag}", workstation=f"slr-ws-{me}-{tag}",
                  robot_ip=f"10.200.{subnet}.1", workstation_ip=f"10.200.{subnet}.2",
                  robot_dev=f"slr{tag}r", workstation_dev=f"slr{tag}w")
    try:
        for ns in (hosts.robot, hosts.workstation):
            _ip("netns", "add", ns)
            hosts._made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        _ip("link", "add", hosts.robot_dev, "type", "veth", "peer", "name",
            hosts.workstation_dev)
        _ip("link", "set", hosts.robot_dev, "netns", hosts.robot)
        _ip("link", "set", hosts.workstation_dev, "netns", hosts.workstation)
        _ip("-n", hosts.robot, "addr", "add", f"{hosts.robot_ip}/24", "dev", hosts.robot_dev)
        _ip("-n", hosts.workstation, "addr", "add", f"{hosts.workstation_ip}/24", "dev",
            hosts.workstation_dev)
        hosts.link(True)
        _ip("-n", hosts.workstation, "link", "set", hosts.workstation_dev, "up")
    except BaseException:
        hosts.remove()
        raise
    return hosts


def own_shm(argv: list[str]) -> list[str]:
    """``argv`` with a mount namespace of its own and an empty /dev/shm (run it inside
    ``ip netns exec``). Network namespaces share the host's /dev/shm, and Zenoh hands a
    shared-memory buffer across a link by reference when both ends can map it — so a
    "remote" process would get large payloads without them crossing the link. Two real
    hosts share no memory; a workstation started this way is one."""
    return ["unshare", "--mount", "--propagation", "private", "sh", "-c",
            'mount -t tmpfs -o size=2g slamlens-shm /dev/shm && exec "$@"', "sh", *argv]


def curl_json(ns: str, url: str, timeout: float = 5.0) -> dict | None:
    """GET ``url`` from inside namespace ``ns`` (None if it does not answer)."""
    import json

    out = subprocess.run(["ip", "netns", "exec", ns, "curl", "-s", "--max-time", str(timeout),
                          url], capture_output=True, text=True, timeout=timeout + 5)
    if out.returncode != 0 or not out.stdout:
        return None
    return json.loads(out.stdout)
