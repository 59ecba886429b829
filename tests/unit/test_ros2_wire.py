"""rmw_zenoh's wire format and the bridge's CDR, against independent oracles.

Keys and tokens against the examples of rmw_zenoh's design document; type hashes against
``rosbags``' REP-2016 hashes (golden values printed by it) and zenoh-ros2-sdk's own hash
code; attachments against the SDK's parser; every payload the bridge writes is read back
by ``rosbags`` and written again by ``rosbags``' own CDR serialiser, which must give the
same bytes.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from slamlens.common.errors import ConfigError, MessageError
from slamlens.common.messages import Health, SlamState, Violation
from slamlens.services.ros2 import wire
from slamlens.services.ros2.cdr import Template, Writer, repeat
from slamlens.services.ros2.outputs import PathTrack, diagnostics, pose_with_covariance, transform
from slamlens.services.ros2.rostypes import OWN_TYPES, ros_type, typestore

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
#: printed by rosbags (Stores.ROS2_JAZZY + the shipped .msg files), held here as constants
GOLDEN = {
    "visualization_msgs/msg/MarkerArray":
        "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
    "nav_msgs/msg/Odometry":
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "slamlens_msgs/msg/SlamEstimate":
        "RIHS01_6d810c25a2ba8b910b9e566a02bc2bbe8c20863a49d55ccdff84afd2231d888b",
}


def test_keys_and_tokens_are_the_design_documents_examples() -> None:
    assert wire.topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert wire.topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    node = wire.Node(domain=2, zid="8b20917502ee955ac4476e0266340d5c", node_id=0, name="talker")
    assert node.token() == "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/talker"
    assert node.endpoint_token(10, wire.PUBLISHER, "/chatter", "std_msgs/msg/String",
                               STRING_HASH, qos="::,7:,:,:,,") == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")
    assert wire.ros_type_name("visualization_msgs::msg::dds_::MarkerArray_") == \
        "visualization_msgs/msg/MarkerArray"
    with pytest.raises(ConfigError):
        wire.topic_key(0, "no_slash", "std_msgs/msg/String", STRING_HASH)


def test_type_hashes_rosbags_golden_and_the_sdks_own() -> None:
    assert ros_type("std_msgs/msg/String", "jazzy").hash == STRING_HASH  # the design doc's
    for name, golden in GOLDEN.items():
        assert ros_type(name, "jazzy").hash == golden
        assert ros_type(name, "humble").hash == "TypeHashNotSupported"
    from zenoh_ros2_sdk.utils import get_type_hash

    store = typestore("jazzy")
    for name in OWN_TYPES:  # the SDK's own RIHS01 code on the shipped definitions
        deps = {"std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
                "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
                "geometry_msgs/msg/Pose2D": "float64 x\nfloat64 y\nfloat64 theta\n"}
        from slamlens.services.ros2.rostypes import msg_file

        assert get_type_hash(name, msg_definition=msg_file(name).read_text(),
                             dependencies=deps) == store.hash_rihs01(name)


def test_attachment_layout_and_the_sdks_parser() -> None:
    from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment

    gid = bytes(range(16))
    data = wire.attachment(7, 1_700_000_000_123456789, gid)
    assert len(data) == 33
    assert struct.unpack("<qq", data[:16]) == (7, 1_700_000_000_123456789)
    assert data[16] == 16 and data[17:] == gid
    theirs = SdkAttachment.from_bytes(data)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (7, 1_700_000_000_123456789,
                                                                     gid)
    ours = wire.parse_attachment(SdkAttachment(3, 5, gid).to_bytes())
    assert (ours.seq, ours.stamp_ns, ours.gid) == (3, 5, gid)
    for bad in (None, b"", data[:32], data + b"\0", data[:16] + b"\x08" + gid):
        with pytest.raises(MessageError, match="attachment"):
            wire.parse_attachment(bad)


def _roundtrip(payload: bytes, name: str) -> object:
    """rosbags reads ``payload`` and writes it again: the same bytes, up to the 0-3 bytes of
    trailing padding a writer may add."""
    store = typestore("jazzy")
    msg = store.deserialize_cdr(payload, name)
    again = bytes(store.serialize_cdr(msg, name))
    assert payload[:len(again)] == again and len(payload) - len(again) < 4
    assert not any(payload[len(again):])
    return msg


def test_repeat_writes_what_a_field_by_field_writer_writes() -> None:
    def element(w: Writer, k: int = 0, mark: bool = True) -> None:
        w.string("x", mark=None)
        w.i32(k, mark="id" if mark else None)
        w.f64s((k, 2.0 * k), mark="xy" if mark else None)
        w.bool(True)

    template = Template(element)
    rng = np.random.default_rng(1)
    for phase in (0, 4):
        for count in range(0, 6):
            ids = rng.integers(-5, 5, count)
            data, end = repeat(template, count, phase, {
                "id": ids.astype("<i4").reshape(-1, 1),
                "xy": np.column_stack([ids, 2.0 * ids]).astype("<f8")})
            w = Writer(phase=phase)
            for k in ids.tolist():
                element(w, k, mark=False)
                w.align(4)
            assert data == w.bytes() and end == w.offset % 8


def _state(n: int, seed: int = 0, **kw: object) -> SlamState:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    P = A @ A.T * 1e-3 + np.eye(3 + 2 * n) * 1e-3
    args = dict(robot="robot1", seq=5, stamp=1_248_273_512.25, step="update",
                pose=np.array([1.0, 2.0, 0.3]), landmark_ids=np.arange(100, 100 + n),
                landmarks=rng.uniform(-2, 2, (n, 2)), covariance=P)
    args.update(kw)
    return SlamState(**args)  # type: ignore[arg-type]


def test_pose_transform_path_and_diagnostics_read_back() -> None:
    state = _state(3)
    msg = _roundtrip(pose_with_covariance(state), "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert msg.header.frame_id == "map"  # type: ignore[attr-defined]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_248_273_512, 250_000_000)  # type: ignore[attr-defined]
    cov = np.asarray(msg.pose.covariance).reshape(6, 6)  # type: ignore[attr-defined]
    idx = np.array([0, 1, 5])
    assert np.array_equal(cov[np.ix_(idx, idx)], state.covariance[:3, :3])
    assert cov[2:5].sum() == 0 and cov[:, 2:5].sum() == 0
    q = msg.pose.pose.orientation  # type: ignore[attr-defined]
    assert np.isclose(2 * np.arctan2(q.z, q.w), 0.3)
    tf = _roundtrip(transform(state), "tf2_msgs/msg/TFMessage")
    (t,) = tf.transforms  # type: ignore[attr-defined]
    assert (t.header.frame_id, t.child_frame_id) == ("map", "robot1/base_link")
    assert (t.transform.translation.x, t.transform.translation.y) == (1.0, 2.0)
    track = PathTrack(max_points=3)
    for k in range(9):
        track.add(_state(0, seq=k, stamp=10.0 + k, pose=np.array([k, -k, 0.1 * k])))
    path = _roundtrip(track.path(20.0), "nav_msgs/msg/Path")
    xs = [p.pose.position.x for p in path.poses]  # type: ignore[attr-defined]
    assert xs[0] == 0 and xs[-1] == 8 and len(xs) <= 6 and xs == sorted(xs)
    stamps = [(p.header.stamp.sec, p.header.stamp.nanosec) for p in path.poses]  # type: ignore[attr-defined]
    assert stamps == [(int(10 + x), 0) for x in xs]
    health = Health(robot="robot1", seq=5, stamp=3.5, ok=False, suspects=np.array([3, 12]),
                    violations=(Violation(kind="pair", ids=(3, 12), step=5, value=2.0),),
                    statistics={"nees_pose": 1.5, "nis": 2.25}, verdict="fault")
    d = _roundtrip(diagnostics(health), "diagnostic_msgs/msg/DiagnosticArray")
    (status,) = d.status  # type: ignore[attr-defined]
    assert status.level == 2 and status.name == "slamlens robot1"
    values = {kv.key: kv.value for kv in status.values}
    assert values["suspects"] == "3 12" and values["verdict"] == "fault"
    assert float(values["nees_pose"]) == 1.5 and float(values["nis"]) == 2.25
