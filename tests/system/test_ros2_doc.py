"""docs/ros2.md, command by command: every ``sh`` block run as written.

In a network namespace of its own (its own loopback, so the document's default port 7447
is free), in a scratch folder holding a rosbag2 folder ``robot1_bag`` written by rosbags'
writer (what ``ros2 bag record`` would have made). A block's services are started in
order, each waited for until it says it is ready; commands that end (the simulator, a
replay, a listing, certificates) are waited for until they end. The router of the first
section serves the sections after it; each other section's services stop at its end.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

from slamlens.services.harness.netns import Hosts
from slamlens.services.harness.procs import REPO, Service, stop

DOC = REPO / "docs" / "ros2.md"
#: services and the line each prints when ready
READY = {"router": "router ready", "estimator": "estimator ready", "monitor": "monitor ready",
         "ros2": "ros2 ready"}


def sections(text: str) -> list[tuple[str, list[str]]]:
    """(section title, the commands of its ``sh`` blocks) in order."""
    out: list[tuple[str, list[str]]] = []
    title, inside = "", False
    for line in text.splitlines():
        if line.startswith("## "):
            title = line[3:].strip()
            out.append((title, []))
        elif line.strip() == "```sh":
            inside = True
        elif line.strip() == "```":
            inside = False
        elif inside and line.strip():
            out[-1][1].append(line.strip())
    return [(t, c) for t, c in out if c]


def test_the_documents_sections_are_the_ones_run_here() -> None:
    assert [t for t, _ in sections(DOC.read_text())] == [
        "One router for both", "See the robot in RViz", "A ROS 2 estimator",
        "A ROS 2 robot's inputs", "rosbag2", "Mutual TLS"]


def _bag(folder: Path) -> None:
    from tests.unit.test_ros2_imports import odom, rba, write_bag

    t0 = 1_700_000_000
    items = [("/robot1/odom", "nav_msgs/msg/Odometry",
              odom(t0 + k // 10, (k % 10) * 100_000_000, 0.2, 0.1),
              (t0 * 10 + k) * 100_000_000) for k in range(20)]
    items.append(("/robot1/landmarks/observations", "slamlens_msgs/msg/RangeBearingArray",
                  rba(t0 + 1, [6], [1.0], [0.5], 900_000_000), (t0 * 10 + 19) * 10 ** 8 + 1))
    write_bag(folder / "robot1_bag", "mcap", items)


class Runner:
    def __init__(self, ns: str, cwd: Path) -> None:
        self.ns, self.cwd = ns, cwd
        self.bin = Path(sys.executable).parent
        self.env = {"HOME": str(cwd), "PATH": f"{self.bin}:/usr/bin:/bin:/usr/sbin:/sbin"}

    def start(self, command: str) -> Service:
        argv = shlex.split(command)
        return Service(["ip", "netns", "exec", self.ns, str(self.bin / argv[0]), *argv[1:]],
                       env=self.env, cwd=self.cwd)

    def run(self, command: str) -> tuple[Service, str]:
        """Start ``command``; wait until it is ready (a service) or has ended."""
        proc = self.start(command)
        words = shlex.split(command)
        if words[0] == "slamlens" and words[1] in READY:
            proc.wait_for_line(READY[words[1]], timeout=60)
            return proc, ""
        assert proc.wait(timeout=240) == 0, (command, "".join(proc.err[-20:]))
        return proc, proc.output()[0]


def test_every_command_of_the_document(two_hosts: Hosts, tmp_path: Path) -> None:
    _bag(tmp_path)
    runner = Runner(two_hosts.robot, tmp_path)
    kept: list[Service] = []
    outputs: dict[str, str] = {}
    try:
        for title, commands in sections(DOC.read_text()):
            if title == "Mutual TLS":
                for proc in kept:
                    stop(proc)
                kept = []
            started: list[Service] = []
            for command in commands:
                proc, out = runner.run(command)
                outputs[command] = out
                started.append(proc)
            if title == "One router for both":
                kept += started
                continue
            for proc in reversed(started):
                if proc.poll() is None:
                    stop(proc)
    finally:
        for proc in kept:
            if proc.poll() is None:
                stop(proc)
    listing = outputs["zenoh-ros2 --router 127.0.0.1:7447 --no-daemon topic list -t"]
    for line in ("/slamlens/robot1/markers [visualization_msgs/msg/MarkerArray]",
                 "/slamlens/robot1/pose [geometry_msgs/msg/PoseWithCovarianceStamped]",
                 "/slamlens/robot1/path [nav_msgs/msg/Path]", "/tf [tf2_msgs/msg/TFMessage]",
                 "/slamlens/robot1/health [diagnostic_msgs/msg/DiagnosticArray]"):
        assert line in listing
    replay = outputs["slamlens replay robot1_bag --format rosbag2 --robot robot1 --rate 0"]
    assert '"Odometry": 20, "Observations": 1' in replay
    assert "all applied by the estimator" in replay
    assert (tmp_path / "pki" / "ros2-robot1.pem").exists()
