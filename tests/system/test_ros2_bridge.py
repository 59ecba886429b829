"""``slamlens ros2`` between real slamlens processes and an independent rmw_zenoh client.

The ROS 2 side is zenoh-ros2-sdk in a child process (``tests/ros2_side.py``): its own keys,
liveliness tokens, attachments, type hashes and rosbags' CDR. Everything runs on loopback
through one router; tests wait on lines and messages, never on time.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState
from slamlens.common.scene3d import SceneSettings, pair_glyphs
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.collect import StateCollector
from slamlens.services.harness.procs import Service, spawn, stop
from tests.ros2_side import messages_dir

KEYS = Keys()
ROBOT = "robot1"
_STARTED: list[Service] = []


def start(*args: str) -> Service:
    """A slamlens process, stopped at the end of the test whatever happens."""
    proc = spawn(*args)
    _STARTED.append(proc)
    return proc


@pytest.fixture(autouse=True)
def _reap() -> Iterator[None]:
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            try:
                stop(proc)
            except AssertionError:  # it had to be killed: the test has failed already
                pass


class States(StateCollector):
    """Every state of ROBOT by seq, decoded."""

    def __init__(self, endpoint: str, key: str | None = None) -> None:
        self.states: dict[int, SlamState] = {}
        super().__init__(endpoint, key or KEYS.state(ROBOT), history_s=60.0)

    def take(self, payload: bytes) -> None:
        state = SlamState.from_bytes(payload)
        self.states[state.seq] = state


@pytest.fixture
def router() -> str:
    endpoint = free_tcp_endpoint()
    proc = spawn("router", "--listen", endpoint)
    proc.wait_for_line("router ready")
    yield endpoint
    stop(proc)


@pytest.fixture(scope="module")
def messages(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return messages_dir(tmp_path_factory.mktemp("ros2_messages"))


def ros_side(mode: str, router: str, messages: Path, *args: str) -> Service:
    proc = Service([sys.executable, "-m", "tests.ros2_side", mode, "--router", router,
                    "--messages", str(messages), *args], stdin=mode == "publish")
    _STARTED.append(proc)
    return proc


def listener(router: str, messages: Path, topics: dict[str, str], *args: str) -> Service:
    flags = [x for topic, t in topics.items() for x in ("--topic", topic, "--type", t)]
    proc = ros_side("listen", router, messages, *flags, *args)
    proc.wait_for_line("ready", timeout=60)
    return proc


def received(proc: Service, enough: Callable[[list[dict]], bool],
             timeout: float = 120.0) -> list[dict]:
    """The messages the listener printed until ``enough`` of them (waiting for them)."""
    out: list[dict] = []
    while not enough(out):
        line = proc.wait_for_line('{"n"', timeout=timeout)
        out.append(json.loads(line)["msg"])
    return out


def kinds(messages: list[dict]) -> dict[str, int]:
    """How many of each message (by its distinctive field) were received."""
    out: dict[str, int] = {}
    for m in messages:
        kind = next((k for k in ("markers", "transforms", "poses", "status", "pose",
                                 "landmark_ids", "ids") if k in m), "?")
        out[kind] = out.get(kind, 0) + 1
    return out


def final(out: str, name: str) -> dict:
    line = next(ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: "))
    return json.loads(line.split(": ", 1)[1])


def test_export_reaches_an_rmw_zenoh_client_and_its_graph(router: str, messages: Path) -> None:
    """sim → estimator → monitor → bridge → the SDK: markers equal to scene3d's picture of
    the very state, pose and covariance bit for bit, path, tf, health; `topic list` of the
    SDK's own graph cache and the node's token name everything."""
    bridge = start("ros2", "--robot", ROBOT, "--connect", router)
    estimator = start("estimator", "--robot", ROBOT, "--connect", router)
    monitor = start("monitor", "--robot", ROBOT, "--connect", router)
    for proc, line in ((bridge, "ros2 ready"), (estimator, "estimator ready"),
                       (monitor, "monitor ready")):
        proc.wait_for_line(line)
    states = States(router)
    topics = {"/slamlens/robot1/markers": "visualization_msgs/msg/MarkerArray",
              "/slamlens/robot1/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
              "/slamlens/robot1/path": "nav_msgs/msg/Path",
              "/tf": "tf2_msgs/msg/TFMessage",
              "/slamlens/robot1/health": "diagnostic_msgs/msg/DiagnosticArray"}
    ros = listener(router, messages, topics)
    sim = start("sim", "--robot", ROBOT, "--connect", router, "--rate", "0")
    try:
        sim.wait_for_line("sim done", timeout=240)
        got = received(ros, lambda m: len(kinds(m)) == 5 and min(kinds(m).values()) >= 3)
        assert states.wait(lambda c: len(c.states) > 50)
        graph = Service([str(Path(sys.executable).parent / "zenoh-ros2"), "--router",
                         router.split("/", 1)[1], "--no-daemon", "topic", "list", "-t"])
        listing, _ = graph.communicate(timeout=60)
        bus = open_bus(BusSettings(connect=(router,)))
        nodes = [k for k in (r.ok for r in bus.session.liveliness().get(
            "@ros2_lv/0/*/*/*/NN/**", timeout=5.0)) if k is not None]
        node_names = {str(k.key_expr).rsplit("/", 1)[1] for k in nodes}
        bus.close()
    finally:
        for proc in (sim, ros):
            stop(proc)
        states.close()
        monitor_out, estimator_out = stop(monitor), stop(estimator)
        bridge_out, _ = stop(bridge)
    assert monitor_out and estimator_out
    for topic, ros_type in topics.items():
        assert f"{topic} [{ros_type}]" in listing
    assert "slamlens_robot1" in node_names
    by_stamp: dict[tuple[int, int], list[SlamState]] = {}  # a predict and an update share one
    for s in states.states.values():
        whole = int(np.floor(s.stamp))
        by_stamp.setdefault((whole, int(round((s.stamp - whole) * 1e9))), []).append(s)

    def state_of(header: dict, same: Callable[[SlamState], bool]) -> SlamState:
        """The state of this stamp of which ``same`` holds (one must)."""
        (state,) = [s for s in by_stamp[(header["stamp"]["sec"], header["stamp"]["nanosec"])]
                    if same(s)][:1]
        return state

    arrays = [m for m in got if "markers" in m]
    poses = [m for m in got if "pose" in m and "covariance" in m["pose"]]
    for m in (m for m in got if "transforms" in m):
        (t,) = m["transforms"]
        assert (t["header"]["frame_id"], t["child_frame_id"]) == ("map", "robot1/base_link")
        state_of(t["header"], lambda s, t=t: t["transform"]["translation"]["x"] == s.pose[0]
                 and t["transform"]["translation"]["y"] == s.pose[1])
    for m in (m for m in got if "status" in m):
        (status,) = m["status"]
        assert status["name"] == "slamlens robot1" and status["level"] in (0, 1, 2)
    for array in arrays:
        ells = [m for m in array["markers"] if m["ns"] == "ellipsoids" and m["action"] == 0]
        centres = np.array([[m["pose"]["position"][a] for a in "xyz"]
                            for m in ells]).reshape(-1, 3)
        sizes = np.array([[m["scale"][a] for a in "xyz"] for m in ells]).reshape(-1, 3)
        state_of(array["markers"][0]["header"], lambda s, c=centres, z=sizes: np.array_equal(
            c, pair_glyphs(s, SceneSettings()).centres) and np.array_equal(
            z, 2 * pair_glyphs(s, SceneSettings()).axes))
    for pose in poses:
        cov = np.array(pose["pose"]["covariance"]).reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])]
        state_of(pose["header"], lambda s, c=cov, p=pose: np.array_equal(
            c, s.covariance[:3, :3]) and p["pose"]["pose"]["position"]["x"] == s.pose[0])
    counts = final(bridge_out, "ros2")
    assert counts["states"] >= len(arrays) and counts["dropped"] == 0
    assert counts["published"]["health"] >= 1


def _estimates(n: int, k: int) -> list[dict]:
    """SlamEstimate messages as the SDK publishes them (JSON lines), seq 0 … k−1."""
    rng = np.random.default_rng(5)
    out = []
    for seq in range(k):
        A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
        out.append({"topic": "/robot1/slam/estimate", "type": "slamlens_msgs/msg/SlamEstimate",
                    "fields": {"header": {"stamp": {"sec": 1_700_000_000 + seq,
                                                    "nanosec": 250_000_000},
                                          "frame_id": "map"},
                               "seq": seq, "pose": {"x": rng.normal(), "y": rng.normal(),
                                                    "theta": 0.5},
                               "landmark_ids": (rng.permutation(n) + 6).tolist(),
                               "landmarks": rng.normal(size=2 * n).tolist(),
                               "covariance": (A @ A.T).reshape(-1).tolist()}})
    return out


def publisher(router: str, messages: Path, items: list[dict], path: Path,
              *args: str) -> Service:
    path.write_text("".join(json.dumps(i) + "\n" for i in items))
    proc = ros_side("publish", router, messages, "--file", str(path), *args)
    proc.wait_for_line("ready", timeout=60)
    return proc


def test_a_ros2_estimator_becomes_the_robots_states(router: str, messages: Path,
                                                    tmp_path: Path) -> None:
    """SlamEstimate from the SDK → SlamState on the bus, every number bit for bit; the
    monitor checks them as it checks slamlens's own estimator."""
    bridge = start("ros2", "--robot", ROBOT, "--connect", router, "--from-ros", "estimate",
                   "--no-export")
    bridge.wait_for_line("ros2 ready")
    monitor = start("monitor", "--robot", ROBOT, "--connect", router)
    monitor.wait_for_line("monitor ready")
    states = States(router)
    healths: list[Health] = []

    class Healths(StateCollector):
        def take(self, payload: bytes) -> None:
            healths.append(Health.from_bytes(payload))

    health = Healths(router, KEYS.health(ROBOT))
    items = _estimates(12, 6)
    ros = publisher(router, messages, items, tmp_path / "estimates.jsonl")
    ros.send("go")
    for _ in items:
        ros.wait_for_line("sent")
    try:
        assert states.wait(lambda c: len(c.states) == len(items))
        assert health.wait(lambda _: any(h.seq == len(items) - 1 for h in healths))
    finally:
        ros.send("done")
        stop(ros)
        states.close()
        health.close()
        stop(monitor)
    for item in items:
        f = item["fields"]
        state = states.states[f["seq"]]
        n = len(f["landmark_ids"])
        assert state.landmark_ids.tolist() == f["landmark_ids"]
        assert state.landmarks.tobytes() == np.array(f["landmarks"]).reshape(n, 2).tobytes()
        assert state.covariance.tobytes() == np.array(f["covariance"]).reshape(
            3 + 2 * n, 3 + 2 * n).tobytes()
        assert state.pose.tolist() == [f["pose"]["x"], f["pose"]["y"], 0.5]
        assert state.stamp == f["header"]["stamp"]["sec"] + 0.25
        assert state.step == ("init" if f["seq"] == 0 else "update")
    counts = final(stop(bridge)[0], "ros2")
    assert counts["imported"] == len(items) and counts["dropped"] == 0


def test_a_ros2_robots_inputs_drive_the_estimator(router: str, messages: Path,
                                                  tmp_path: Path) -> None:
    """/R/odom and /R/landmarks/observations from the SDK → numbered inputs → slamlens's
    estimator, which ends where the EKF core fed the same inputs directly ends."""
    from slamlens.services.slam.estimator import Estimator
    from slamlens.services.slam.settings import EstimatorSettings

    bridge = start("ros2", "--robot", ROBOT, "--connect", router, "--from-ros", "inputs",
                   "--no-export")
    estimator = start("estimator", "--robot", ROBOT, "--connect", router)
    for proc, line in ((bridge, "ros2 ready"), (estimator, "estimator ready")):
        proc.wait_for_line(line)
    states = States(router)
    items, oracle = [], Estimator(EstimatorSettings())
    t0, last = 1_700_000_000.0, None
    rng = np.random.default_rng(2)
    landmarks = {6: (1.0, 0.5), 7: (-0.5, 1.5), 8: (2.0, -1.0)}
    for k in range(40):
        t = t0 + 0.1 * k
        sec, nsec = int(t0) + k // 10, (k % 10) * 100_000_000
        t = sec + nsec * 1e-9
        v, w = 0.2 + 0.01 * rng.normal(), 0.1
        items.append({"topic": "/robot1/odom", "type": "nav_msgs/msg/Odometry", "fields": {
            "header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": "odom"},
            "child_frame_id": "base_link",
            "pose": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                              "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                     "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": {"x": v, "y": 0.0, "z": 0.0},
                                "angular": {"x": 0.0, "y": 0.0, "z": w}},
                      "covariance": [0.0] * 36}}})
        oracle.predict(v=v, w=w, dt=0.0 if last is None else t - last, stamp=t)
        last = t
        if k % 5 == 4:
            ids = sorted(landmarks)
            rb = [(float(np.hypot(*landmarks[i])) + 0.01 * rng.normal(),
                   float(np.arctan2(landmarks[i][1], landmarks[i][0]))) for i in ids]
            items.append({"topic": "/robot1/landmarks/observations",
                          "type": "slamlens_msgs/msg/RangeBearingArray", "fields": {
                              "header": {"stamp": {"sec": sec, "nanosec": nsec},
                                         "frame_id": "base_link"},
                              "ids": ids, "ranges": [r for r, _ in rb],
                              "bearings": [b for _, b in rb]}})
            oracle.observe(ids=np.array(ids), ranges=np.array([r for r, _ in rb]),
                           bearings=np.array([b for _, b in rb]), stamp=t)
    ros = publisher(router, messages, items, tmp_path / "inputs.jsonl")
    ros.send("go")
    try:
        assert states.wait(lambda c: len(c.states) == len(items) + 1)  # + the init state
    finally:
        ros.send("done")
        stop(ros)
        states.close()
        stop(estimator)
    last_state = states.states[len(items)]
    assert last_state.input_stamp == last
    assert np.allclose(last_state.pose, oracle.pose, rtol=0, atol=1e-12)
    assert np.allclose(last_state.covariance, oracle.covariance, rtol=0, atol=1e-12)
    assert last_state.landmark_ids.tolist() == oracle.landmark_ids.tolist()
    counts = final(stop(bridge)[0], "ros2")
    assert counts["to_bus"] == {"Odometry": 40, "Observations": 8, "Truth": 0}


#: an rmw_zenoh publication's attachment: sequence number 1, source timestamp 5, a 16-byte
#: (all-zero) publisher GID
ATTACHMENT = np.int64(1).tobytes() + np.int64(5).tobytes() + bytes([16]) + bytes(16)


def importing_bridge(router: str) -> tuple[Service, States]:
    """A bridge importing a ROS 2 estimator's output (no export), ready; and a collector
    of the states it gives (close it)."""
    bridge = start("ros2", "--robot", ROBOT, "--connect", router, "--from-ros", "estimate",
                   "--no-export")
    bridge.wait_for_line("ros2 ready")
    return bridge, States(router)


def test_bad_input_is_dropped_counted_and_named(router: str, tmp_path: Path) -> None:
    """Malformed CDR, another type hash, no attachment, arrays of the wrong length: each
    dropped with a line naming it, counted; a good message after them still goes through."""
    from slamlens.services.ros2.rostypes import ros_type, typestore

    bridge, states = importing_bridge(router)
    store = typestore("jazzy")
    T = store.types
    name = "slamlens_msgs/msg/SlamEstimate"
    good_hash = ros_type(name, "jazzy").hash

    def estimate(n_values: int) -> bytes:
        return bytes(store.serialize_cdr(T[name](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                sec=5, nanosec=0), frame_id="map"), seq=np.uint64(1),
            pose=T["geometry_msgs/msg/Pose2D"](x=0.0, y=0.0, theta=0.0),
            landmark_ids=np.array([6], np.int64), landmarks=np.zeros(n_values),
            covariance=np.eye(5).reshape(-1)), name))

    def key(type_hash: str) -> str:
        return f"0/robot1/slam/estimate/slamlens_msgs::msg::dds_::SlamEstimate_/{type_hash}"

    bus = open_bus(BusSettings(connect=(router,)))
    session = bus.session
    try:
        session.put(key(good_hash), estimate(2)[:30], attachment=ATTACHMENT)  # malformed CDR
        session.put(key("RIHS01_" + "0" * 64), estimate(2), attachment=ATTACHMENT)  # hash
        session.put(key(good_hash), estimate(2))  # no attachment
        session.put(key(good_hash), estimate(3), attachment=ATTACHMENT)  # wrong length
        session.put(key(good_hash), estimate(2), attachment=ATTACHMENT)  # good
        assert states.wait(lambda c: 1 in c.states)
    finally:
        bus.close()
        states.close()
    out, err = stop(bridge)
    counts = final(out, "ros2")
    assert counts["dropped"] == 4 and counts["imported"] == 1
    lines = [ln for ln in err.splitlines() if "dropped bad /robot1/slam/estimate" in ln]
    assert len(lines) == 4
    for what in ("payload", "type hash", "attachment", "landmarks"):
        assert any(what in ln for ln in lines), what


def test_humble_announces_no_type_hash(router: str, messages: Path) -> None:
    bridge = start("ros2", "--robot", ROBOT, "--connect", router, "--distro", "humble")
    bridge.wait_for_line("ros2 ready")
    ros = listener(router, messages, {"/slamlens/robot1/pose":
                                      "geometry_msgs/msg/PoseWithCovarianceStamped"},
                   "--type-hash", "TypeHashNotSupported")
    estimator = start("estimator", "--robot", ROBOT, "--connect", router)
    try:
        estimator.wait_for_line("estimator ready")
        (pose,) = received(ros, lambda m: len(m) >= 1)
        assert pose["header"]["frame_id"] == "map"
    finally:
        for proc in (ros, estimator, bridge):
            stop(proc)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_replay_a_rosbag2_as_inputs_and_as_estimates(router: str, tmp_path: Path,
                                                     storage: str) -> None:
    """``slamlens replay BAG --format rosbag2``: a bag written by rosbags' writer, played as
    the robot's inputs (every one applied by the estimator) and as its states (bit for
    bit)."""
    from tests.unit.test_ros2_imports import estimate, odom, rba, write_bag

    t0 = 1_700_000_000
    items = []
    for k in range(30):
        items.append(("/robot1/odom", "nav_msgs/msg/Odometry",
                      odom(t0 + k // 10, (k % 10) * 100_000_000, 0.2, 0.1),
                      (t0 * 10 + k) * 100_000_000))
        if k % 10 == 9:
            items.append(("/robot1/landmarks/observations", "slamlens_msgs/msg/RangeBearingArray",
                          rba(t0 + k // 10, [6, 7], [1.0, 2.0], [0.5, -0.5], 900_000_000),
                          (t0 * 10 + k) * 100_000_000 + 1))
    write_bag(tmp_path / "inputs", storage, items)
    estimator = start("estimator", "--robot", ROBOT, "--connect", router)
    estimator.wait_for_line("estimator ready")
    replay = start("replay", str(tmp_path / "inputs"), "--format", "rosbag2", "--robot", ROBOT,
                   "--rate", "0", "--connect", router)
    line = replay.wait_for_line("replay done", timeout=120)
    assert '"Odometry": 30' in line and '"Observations": 3' in line
    assert "all applied by the estimator" in line
    stop(replay)
    stop(estimator)
    msgs = [estimate(4, seq=k, seed=k, sec=t0 + k) for k in range(5)]
    write_bag(tmp_path / "est", storage, [
        ("/robot1/slam/estimate", "slamlens_msgs/msg/SlamEstimate", m, (t0 + k) * 10 ** 9)
        for k, m in enumerate(msgs)])
    states = States(router)
    replay = start("replay", str(tmp_path / "est"), "--format", "rosbag2", "--robot", ROBOT,
                   "--from-ros", "estimate", "--rate", "20", "--connect", router)
    try:
        replay.wait_for_line("replay done", timeout=120)
        assert states.wait(lambda c: len(c.states) == len(msgs))
    finally:
        states.close()
        stop(replay)
    for m in msgs:
        state = states.states[int(m.seq)]  # type: ignore[attr-defined]
        assert state.covariance.tobytes() == m.covariance.tobytes()  # type: ignore[attr-defined]
        assert state.landmarks.tobytes() == m.landmarks.tobytes()  # type: ignore[attr-defined]


def test_a_pose_only_estimator_gives_states_without_landmarks(router: str) -> None:
    """PoseWithCovarianceStamped on /R/slam/pose → a SlamState with the pose and its x, y,
    yaw covariance and no landmarks (the viewer's pose ellipse and path, no pairs)."""
    from slamlens.services.ros2.rostypes import ros_type, typestore

    bridge, states = importing_bridge(router)
    store = typestore("jazzy")
    T = store.types
    name = "geometry_msgs/msg/PoseWithCovarianceStamped"
    cov = np.zeros((6, 6))
    cov[np.ix_([0, 1, 5], [0, 1, 5])] = [[0.04, 0.01, 0.0], [0.01, 0.09, 0.002],
                                         [0.0, 0.002, 0.01]]
    payload = bytes(store.serialize_cdr(T[name](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=12, nanosec=500_000_000), frame_id="map"),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=1.5, y=-0.5, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(0.25),
                                                              w=np.cos(0.25))),
            covariance=cov.reshape(-1))), name))
    key = f"0/robot1/slam/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/" \
          f"{ros_type(name, 'jazzy').hash}"
    bus = open_bus(BusSettings(connect=(router,)))
    try:
        assert bus.wait_for_subscriber(key, timeout=30)
        bus.session.put(key, payload, attachment=ATTACHMENT)
        assert states.wait(lambda c: 1 in c.states)
    finally:
        bus.close()
        states.close()
    state = states.states[1]
    assert state.n == 0 and state.stamp == 12.5
    assert state.pose[:2].tolist() == [1.5, -0.5] and np.isclose(state.pose[2], 0.5)
    assert np.array_equal(state.covariance, cov[np.ix_([0, 1, 5], [0, 1, 5])])
