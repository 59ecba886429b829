"""ROS 2 messages in: rosbags writes them (CDR and rosbag2 folders), the bridge's core
reads them into slamlens messages, bit for bit, and refuses what is malformed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamlens.common.errors import MessageError, SourceError
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.services.ros2.bag import Bag
from slamlens.services.ros2.imports import (
    OdometryInput,
    decode,
    observations,
    pose_state,
    slam_state,
)
from slamlens.services.ros2.rostypes import typestore

STORE = typestore("jazzy")
T = STORE.types


def header(sec: int, nsec: int = 0) -> object:
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec,
                                                                            nanosec=nsec),
                                    frame_id="map")


def estimate(n: int, seq: int = 3, seed: int = 0, *, sec: int = 1_700_000_000) -> object:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    P = A @ A.T
    return T["slamlens_msgs/msg/SlamEstimate"](
        header=header(sec, 123), seq=np.uint64(seq),
        pose=T["geometry_msgs/msg/Pose2D"](x=rng.normal(), y=rng.normal(), theta=0.25),
        landmark_ids=rng.permutation(np.arange(1000, 1000 + n)).astype(np.int64),
        landmarks=rng.normal(size=2 * n), covariance=P.reshape(-1))


def cdr(msg: object, name: str) -> bytes:
    return bytes(STORE.serialize_cdr(msg, name))


def test_slam_estimate_becomes_the_same_numbers_bit_for_bit() -> None:
    msg = estimate(40)
    state = slam_state(decode(cdr(msg, "slamlens_msgs/msg/SlamEstimate"),
                              "slamlens_msgs/msg/SlamEstimate", "jazzy"), "robot1")
    again = SlamState.from_bytes(state.to_bytes())  # and through slamlens's own wire
    for s in (state, again):
        assert s.landmark_ids.tobytes() == msg.landmark_ids.tobytes()  # type: ignore[attr-defined]
        assert s.landmarks.tobytes() == msg.landmarks.tobytes()  # type: ignore[attr-defined]
        assert s.covariance.tobytes() == msg.covariance.tobytes()  # type: ignore[attr-defined]
        assert s.pose.tolist() == [msg.pose.x, msg.pose.y, 0.25]  # type: ignore[attr-defined]
        assert s.seq == 3 and s.step == "update" and s.epoch == 0
        assert s.stamp == 1_700_000_000 + 123e-9 == s.input_stamp


@pytest.mark.parametrize("field,value,what", [
    ("landmarks", np.zeros(5), "landmarks"), ("covariance", np.zeros(10), "covariance"),
    ("covariance", np.full(49, np.nan), "finite"), ("landmarks", np.full(4, np.inf), "finite"),
])
def test_wrong_arrays_are_refused_by_name(field: str, value: np.ndarray, what: str) -> None:
    msg = estimate(2)
    setattr(msg, field, value)
    with pytest.raises(MessageError, match=what):
        slam_state(msg, "robot1")


def test_an_asymmetric_covariance_is_passed_on_for_the_monitor_to_report() -> None:
    msg = estimate(2)
    msg.covariance = np.triu(np.ones((7, 7))).reshape(-1)  # type: ignore[attr-defined]
    state = slam_state(msg, "robot1")
    assert state.covariance.tobytes() == msg.covariance.tobytes()  # type: ignore[attr-defined]
    with pytest.raises(MessageError, match="symmetric"):  # what a viewer's decoder says
        SlamState.from_bytes(state.to_bytes())
    assert SlamState.from_bytes(state.to_bytes(), check_symmetry=False) == state


def test_malformed_cdr_is_a_message_error() -> None:
    good = cdr(estimate(3), "slamlens_msgs/msg/SlamEstimate")
    for bad in (good[:40], b"\x00\x00\x00\x00" + good[4:], b"", good[:4] + b"\xff" * 64):
        with pytest.raises(MessageError):
            decode(bad, "slamlens_msgs/msg/SlamEstimate", "jazzy")


def odom(sec: int, nsec: int, v: float, w: float) -> object:
    V3 = T["geometry_msgs/msg/Vector3"]
    twist = T["geometry_msgs/msg/TwistWithCovariance"](
        twist=T["geometry_msgs/msg/Twist"](linear=V3(x=v, y=0.0, z=0.0),
                                           angular=V3(x=0.0, y=0.0, z=w)),
        covariance=np.zeros(36))
    pose = T["geometry_msgs/msg/PoseWithCovariance"](
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(0.2),
                                                          w=np.cos(0.2))),
        covariance=np.diag([0.1, 0.2, 0, 0, 0, 0.3]).reshape(-1))
    return T["nav_msgs/msg/Odometry"](header=header(sec, nsec), child_frame_id="base_link",
                                      pose=pose, twist=twist)


def rba(sec: int, ids: list[int], ranges: list[float], bearings: list[float],
        nsec: int = 0) -> object:
    return T["slamlens_msgs/msg/RangeBearingArray"](
        header=header(sec, nsec), ids=np.array(ids, np.int64), ranges=np.array(ranges),
        bearings=np.array(bearings))


def test_odometry_dt_from_stamps_and_observations() -> None:
    conv = OdometryInput("robot1")
    got = [conv.convert(odom(10, k * 100_000_000, 0.5, -0.25)) for k in range(3)]
    assert [o.dt for o in got] == [0.0, pytest.approx(0.1), pytest.approx(0.1)]
    assert got[2] == Odometry(robot="robot1", stamp=10.2, dt=got[2].dt, v=0.5, w=-0.25)
    with pytest.raises(MessageError, match="stamp"):
        conv.convert(odom(9, 0, 0.5, 0.0))
    obs = observations(rba(11, [6, -1], [1.5, 2.0], [0.1, -0.2]), "robot1")
    assert obs == Observations(robot="robot1", stamp=11.0, ids=np.array([6, -1]),
                               ranges=np.array([1.5, 2.0]), bearings=np.array([0.1, -0.2]))
    with pytest.raises(MessageError, match="bearings"):
        observations(rba(11, [6, 7], [1.5, 2.0], [0.1]), "robot1")
    with pytest.raises(MessageError, match="ranges"):
        observations(rba(11, [6], [-1.0], [0.1]), "robot1")


def test_pose_only_estimator() -> None:
    state = pose_state(odom(5, 0, 0.0, 0.0), "nav_msgs/msg/Odometry", "robot1", 1)
    assert state.n == 0 and state.pose[:2].tolist() == [1.0, 2.0]
    assert np.isclose(state.pose[2], 0.4)
    assert np.array_equal(state.covariance, np.diag([0.1, 0.2, 0.3]))


def write_bag(path: Path, storage: str, items: list[tuple[str, str, object, int]]) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns: dict[str, object] = {}
        for topic, name, msg, t_ns in items:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, name, typestore=STORE)
            writer.write(conns[topic], t_ns, cdr(msg, name))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_rosbag2_of_inputs_and_one_of_estimates(tmp_path: Path, storage: str) -> None:
    t0 = 1_700_000_000_000_000_000
    items = [("/robot1/odom", "nav_msgs/msg/Odometry", odom(1_700_000_000, 0, 0.1, 0.0), t0),
             ("/robot1/landmarks/observations", "slamlens_msgs/msg/RangeBearingArray",
              rba(1_700_000_000, [6], [1.0], [0.5]), t0 + 1),
             ("/robot1/odom", "nav_msgs/msg/Odometry",
              odom(1_700_000_000, 500_000_000, 0.2, 0.1), t0 + 500_000_000),
             ("/robot1/landmarks/observations", "slamlens_msgs/msg/RangeBearingArray",
              rba(1_700_000_001, [6, 7], [1.0], [0.5]), t0 + 900_000_000),  # malformed
             ("/other/odom", "nav_msgs/msg/Odometry", odom(1, 0, 9.0, 9.0), t0 + 2)]
    write_bag(tmp_path / "inputs", storage, items)
    bag = Bag(str(tmp_path / "inputs"), robot="robot1", what="inputs")
    got = list(bag.events())
    bag.close()
    assert [type(m).__name__ for m in got] == ["Odometry", "Observations", "Odometry"]
    assert got[2].v == 0.2 and got[2].dt == pytest.approx(0.5)  # type: ignore[attr-defined]
    assert bag.stats.total_skipped == 1 and bag.stats.read == 4
    msgs = [estimate(3, seq=k, seed=k, sec=1_700_000_000 + k) for k in range(3)]
    write_bag(tmp_path / "est", storage, [
        ("/robot1/slam/estimate", "slamlens_msgs/msg/SlamEstimate", m, t0 + k)
        for k, m in enumerate(msgs)])
    bag = Bag(str(tmp_path / "est"), robot="robot1", what="estimate")
    states = list(bag.events())
    bag.close()
    assert [s.seq for s in states] == [0, 1, 2]  # type: ignore[attr-defined]
    for s, m in zip(states, msgs, strict=True):
        assert s.covariance.tobytes() == m.covariance.tobytes()  # type: ignore[attr-defined]
    with pytest.raises(SourceError, match="none of"):
        Bag(str(tmp_path / "est"), robot="robot1", what="inputs")
    with pytest.raises(SourceError, match="not a rosbag2"):
        Bag(str(tmp_path), robot="robot1", what="inputs")


def test_an_imported_state_is_gettable_as_soon_as_a_subscriber_has_it() -> None:
    """The bridge's states on the bus: a get made as a state is received answers that very
    state, never the previous one."""
    from slamlens.common.inprocess_bus import InProcessBus
    from slamlens.common.keys import Keys
    from slamlens.services.ros2.states import StatePublisher

    keys = Keys("t")
    bus = InProcessBus()
    out = StatePublisher(bus, keys=keys, robot="r")
    seen: list[tuple[int, int]] = []  # (seq received, seq a get answers with then)

    def on_state(_key: str, payload: bytes) -> None:
        got = bus.get(keys.state("r"))[0].payload
        seen.append((SlamState.from_bytes(payload).seq, SlamState.from_bytes(got).seq))

    bus.subscribe(keys.state("r"), on_state)
    for seq in (1, 2, 3):
        out.publish(slam_state(estimate(4, seq=seq, seed=seq), "r"))
    assert seen == [(1, 1), (2, 2), (3, 3)]


def test_an_imported_states_header_names_every_count_of_the_contract() -> None:
    """``get state?header`` on the bridge's states: the state's header fields and every
    count the contract names — ``dropped`` the bridge's, the input-order counts 0."""
    import msgpack

    from slamlens.common.inprocess_bus import InProcessBus
    from slamlens.common.keys import Keys
    from slamlens.common.state_header import INPUT_COUNTS
    from slamlens.services.ros2.states import StatePublisher

    keys = Keys("t")
    bus = InProcessBus()
    out = StatePublisher(bus, keys=keys, robot="r", dropped=lambda: 7)
    for seq in (1, 2):
        out.publish(slam_state(estimate(4, seq=seq, seed=seq), "r"))
    head = msgpack.unpackb(bus.get(keys.state("r") + "?header")[0].payload)
    state = SlamState.from_bytes(bus.get(keys.state("r"))[0].payload)
    assert head["seq"] == state.seq == 2
    assert (head["robot"], head["n"], head["epoch"]) == ("r", state.n, state.epoch)
    assert head["dropped"] == 7
    assert {name: head[name] for name in INPUT_COUNTS} == dict.fromkeys(INPUT_COUNTS, 0)


def test_the_input_order_counts_every_count_a_header_names() -> None:
    from dataclasses import fields

    from slamlens.common.state_header import INPUT_COUNTS
    from slamlens.services.slam.input_order import OrderStats

    assert set(INPUT_COUNTS) <= {f.name for f in fields(OrderStats)}
