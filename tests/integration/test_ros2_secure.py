"""``slamlens ros2 --secure DIR --name ros2-R`` through a router enforcing the roles.

A secure router process; the bridge with its own identity; a ROS 2 robot (``robot-R``)
putting a SlamEstimate on its rmw_zenoh key with its attachment (CDR from rosbags, key and
attachment written here from rmw_zenoh's design document); a viewer identity reading the
markers and ROS 2's graph. Everything the bridge and the robot say gets through, and the
router refuses nothing of it; a bridge identity saying something else is refused.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.certs import extend_authority
from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.procs import spawn, stop
from slamlens.services.ros2.rostypes import ros_type, typestore
from tests.integration.test_security import RouterProcess

NAMES = ["router-ws", "robot-robot1", "ros2-robot1", "viewer-rviz"]
ESTIMATE = "slamlens_msgs/msg/SlamEstimate"


@pytest.fixture
def pki(tmp_path: Path) -> Path:
    extend_authority(tmp_path / "pki", NAMES)
    return tmp_path / "pki"


def _estimate() -> bytes:
    store = typestore("jazzy")
    T = store.types
    return bytes(store.serialize_cdr(T[ESTIMATE](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=7, nanosec=0), frame_id="map"), seq=np.uint64(1),
        pose=T["geometry_msgs/msg/Pose2D"](x=0.5, y=0.25, theta=0.1),
        landmark_ids=np.array([6, 7], np.int64), landmarks=np.array([1.0, 0.0, 0.0, 1.0]),
        covariance=np.eye(7).reshape(-1) * 0.01), ESTIMATE))


def test_the_bridge_under_mutual_tls_says_what_its_role_allows(pki: Path) -> None:
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    router = RouterProcess("--listen", endpoint, "--secure", str(pki), "--name", "router-ws")

    def client(name: str):  # noqa: ANN202
        return open_bus(BusSettings(connect=(endpoint,), secure=str(pki), name=name))

    viewer, robot = client("viewer-rviz"), client("robot-robot1")
    bridge = spawn("ros2", "--robot", "robot1", "--from-ros", "estimate", "--connect",
                   endpoint, "--secure", str(pki), "--name", "ros2-robot1")
    try:
        bridge.wait_for_line("ros2 ready")
        states = viewer.channel(Keys().state("robot1"))
        markers: list[bytes] = []
        got_markers = threading.Event()

        def on_markers(sample) -> None:  # noqa: ANN001
            markers.append(sample.payload.to_bytes())
            got_markers.set()

        viewer.session.declare_subscriber("0/slamlens/robot1/markers/**", on_markers)
        key = (f"0/robot1/slam/estimate/slamlens_msgs::msg::dds_::SlamEstimate_/"
               f"{ros_type(ESTIMATE, 'jazzy').hash}")
        assert robot.wait_for_subscriber(key, timeout=30)
        attachment = np.int64(1).tobytes() + np.int64(7).tobytes() + bytes([16]) + bytes(16)
        robot.session.put(key, _estimate(), attachment=attachment)
        sample = states.recv(timeout=30)
        assert sample is not None
        state = SlamState.from_bytes(sample.payload)
        assert state.landmark_ids.tolist() == [6, 7] and state.seq == 1
        assert got_markers.wait(30)  # the bridge drew its own state back to ROS 2
        names = [str(r.ok.key_expr) for r in viewer.session.liveliness().get(
            "@ros2_lv/0/**", timeout=5.0) if r.ok is not None]
        assert any(n.endswith("/NN/%/%/slamlens_robot1") for n in names)
        assert any("/MP/" in n and "%slamlens%robot1%markers" in n for n in names)
        assert any("/MS/" in n and "%robot1%slam%estimate" in n for n in names)
    finally:
        out, _ = stop(bridge)
        viewer.close()
        robot.close()
    assert '"imported": 1' in out and '"dropped": 0' in out
    assert not [line for line in router.lines if "refused" in line and "ros2-robot1" in line]
    assert not [line for line in router.lines if "refused" in line and "robot-robot1" in line]
    # the bridge's identity may not speak for the monitor
    impostor = client("ros2-robot1")
    try:
        impostor.session.put("slamlens/robot/robot1/health", b"forged")
        router.wait_log("refused: ros2-robot1 may not Put (ingress) on "
                        "slamlens/robot/robot1/health")
    finally:
        impostor.close()
        router.close()
