"""Codec round trips, and malformed or random payloads rejected with the right reason."""

from __future__ import annotations

import random

import msgpack
import numpy as np
import pytest

from slamlens.common.errors import MessageError
from slamlens.common.messages import (
    MESSAGE_TYPES,
    CameraControl,
    CameraFrame,
    CameraPose,
    Health,
    Observations,
    Odometry,
    Registration,
    ServiceStatus,
    SlamState,
    StateSummary,
    Truth,
    Violation,
)


def _state(n: int = 3, seed: int = 0) -> SlamState:
    rng = np.random.default_rng(seed)
    N = 3 + 2 * n
    A = rng.normal(size=(N, N))
    return SlamState(robot="r1", seq=7, stamp=1.5, step="update", pose=rng.normal(size=3),
                     landmark_ids=np.arange(n) + 10, landmarks=rng.normal(size=(n, 2)),
                     covariance=A @ A.T, observed_ids=[10], new_ids=[11],
                     innovation_ids=[10], innovations=[[0.1, -0.02]],
                     innovation_covariances=[[[0.01, 0.0], [0.0, 0.002]]])


SAMPLES = [
    Odometry(robot="r1", stamp=0.1, dt=0.1, v=0.25, w=-0.1),
    Observations(robot="r1", stamp=0.2, ids=[1, -1], ranges=[1.0, 2.5], bearings=[0.3, -1.2]),
    Truth(robot="r1", stamp=0.3, pose=[0.0, 1.0, 0.5], landmark_ids=[1, 2],
          landmarks=[[1.0, 2.0], [3.0, 4.0]]),
    _state(),
    Health(robot="r1", seq=3, stamp=0.4, ok=False, suspects=[4],
           violations=(Violation("pair", (4, 5), 3, 0.01, bound=1e-9, detail="P_d grew"),
                       Violation("nees", (), 3, 25.0, bound=12.8)),
           statistics={"nees_pose": 2.5}),
    CameraFrame(camera="c", seq=1, stamp=0.5, encoding="jpeg", width=4, height=2,
                data=b"\xff\xd8jpeg"),
    Registration(camera="c", robot="r1", stamp=0.6, K=np.eye(3), dist=np.zeros(5), width=640,
                 height=480, T_camera_from_map=np.eye(4), reprojection_error_px=0.2),
    CameraPose(camera="c", stamp=0.7, T_world_from_camera=np.eye(4)),
    CameraControl(command="reregister", robot="r1"),
    ServiceStatus(service="monitor", name="monitor-r1", host="lab", pid=42, version="0.1.0",
                  started=1.7e9, uptime_s=12.5, state="ok", robot="r1", epoch=3,
                  counts={"checked": 120.0, "violations": 0.0}, rates={"checked": 9.5},
                  dropped=1, lost=2),
    StateSummary(robot="r1", seq=7, stamp=1.5, step="update", pose=[0.1, 0.2, 0.3],
                 pose_covariance=np.eye(3) * 0.01, landmark_ids=[10, 11, 12],
                 landmarks=[[0.0, 0.0], [0.1, 0.0], [2.0, 2.0]],
                 landmark_covariances=np.stack([np.eye(2) * 0.02] * 3), epoch=3,
                 input_stamp=1.5, what="pairs", cluster_threshold_m=0.6, cluster_count=0,
                 groups=[0, 0, 1], selected_cluster=0, pairs=[[0, 1]],
                 pairs_Pd=[[[0.01, 0.0], [0.0, 0.02]]], pairs_total=1, compute_s=0.002),
]


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(msg) -> None:
    back = type(msg).from_bytes(msg.to_bytes())
    assert back == msg
    assert back.to_bytes() == msg.to_bytes()


def test_every_message_type_is_sampled() -> None:
    assert {type(m) for m in SAMPLES} == set(MESSAGE_TYPES)


def test_arrays_are_read_only_and_copied() -> None:
    source = np.array([0.0, 1.0, 2.0])
    truth = Truth(robot="r", stamp=0.0, pose=source, landmark_ids=[], landmarks=np.zeros((0, 2)))
    source[0] = 99.0
    assert truth.pose[0] == 0.0
    with pytest.raises(ValueError):
        truth.pose[0] = 1.0


def test_wire_format_is_the_spec() -> None:
    """docs/protocol.md by hand: schema 1, arrays as {dtype, shape, data} little-endian."""
    state = _state(n=2)
    raw = msgpack.unpackb(state.to_bytes(), raw=False)
    assert raw["schema"] == 1
    assert raw["pose"]["dtype"] == "<f8" and raw["pose"]["shape"] == [3]
    assert raw["landmark_ids"]["dtype"] == "<i8"
    assert raw["covariance"]["shape"] == [49]
    cov = np.frombuffer(raw["covariance"]["data"], "<f8").reshape(7, 7)
    np.testing.assert_array_equal(cov, state.covariance)


def test_decoder_accepts_square_covariance_lists_and_ignores_unknown_fields() -> None:
    state = _state(n=1)
    raw = state.to_dict()
    raw["covariance"] = {"dtype": "<f8", "shape": [5, 5], "data": state.covariance.tobytes()}
    raw["pose"] = state.pose.tolist()
    raw["future_field"] = {"anything": [1, 2, 3]}
    back = SlamState.from_bytes(msgpack.packb(raw, use_bin_type=True))
    assert back == state


def _corrupt(raw: dict, field: str, value) -> bytes:
    raw = dict(raw)
    if value is KeyError:
        del raw[field]
    else:
        raw[field] = value
    return msgpack.packb(raw, use_bin_type=True)


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("schema", 2, "expected 1"),
        ("robot", KeyError, "expected present, got missing"),
        ("seq", "seven", "expected an integer"),
        ("stamp", float("nan"), "expected a finite number"),
        ("step", "wander", "one of ['init', 'predict', 'update']"),
        ("pose", {"dtype": "<f8", "shape": [4], "data": b"\0" * 32}, "expected shape [3]"),
        ("pose", {"dtype": ">f8", "shape": [3], "data": b"\0" * 24}, "little-endian dtype"),
        ("pose", {"dtype": "<f8", "shape": [3], "data": b"\0" * 23}, "24 data bytes"),
        ("pose", [0.0, float("inf"), 0.0], "finite values"),
        ("landmarks", {"dtype": "<f8", "shape": [2, 2], "data": b"\0" * 32},
         "3 entries (one per landmark id)"),
        ("covariance", {"dtype": "<f8", "shape": [80], "data": b"\0" * 640}, "not a square"),
        ("covariance", {"dtype": "<f8", "shape": [7, 7], "data": b"\0" * 392}, "[9, 9] for n = 3"),
        ("landmark_ids", [1, 1, 2], "distinct ids"),
    ],
)
def test_malformed_state_rejected_naming_field(field: str, value, reason: str) -> None:
    raw = _state().to_dict()
    with pytest.raises(MessageError) as info:
        SlamState.from_bytes(_corrupt(raw, field, value))
    assert info.value.field == field
    assert reason in str(info.value)


def test_asymmetric_covariance_rejected_unless_disabled() -> None:
    state = _state(n=1)
    raw = state.to_dict()
    cov = state.covariance.copy()
    cov[0, 4] += 1.0
    raw["covariance"] = {"dtype": "<f8", "shape": [25], "data": cov.tobytes()}
    payload = msgpack.packb(raw, use_bin_type=True)
    with pytest.raises(MessageError, match="symmetric"):
        SlamState.from_bytes(payload)
    assert SlamState.from_bytes(payload, check_symmetry=False).covariance[0, 4] == cov[0, 4]


def test_observations_consistency() -> None:
    with pytest.raises(MessageError, match="ranges: expected 2 entries"):
        Observations(robot="r", stamp=0.0, ids=[1, 2], ranges=[1.0], bearings=[0.0, 0.0])
    with pytest.raises(MessageError, match="non-negative"):
        Observations(robot="r", stamp=0.0, ids=[1], ranges=[-1.0], bearings=[0.0])
    with pytest.raises(MessageError, match="ids: expected integers"):
        Observations.from_dict({"schema": 1, "robot": "r", "stamp": 0.0, "ids": [1.5],
                                "ranges": [1.0], "bearings": [0.0]})


def test_camera_control_is_the_documented_map() -> None:
    """docs/protocol.md: {"schema": 1, "command": "reregister", "robot": R}, robot optional."""
    assert CameraControl.from_bytes(msgpack.packb({"schema": 1, "command": "reregister"})) \
        == CameraControl(command="reregister", robot=None)
    assert msgpack.unpackb(CameraControl(command="reregister").to_bytes()) == {
        "schema": 1, "command": "reregister"}
    with pytest.raises(MessageError, match="command: expected one of \\['reregister'\\]"):
        CameraControl.from_dict({"schema": 1, "command": "reboot"})
    with pytest.raises(MessageError, match="robot: expected a string, got int"):
        CameraControl.from_dict({"schema": 1, "command": "reregister", "robot": 7})


def test_odometry_negative_dt_rejected() -> None:
    with pytest.raises(MessageError, match="dt"):
        Odometry(robot="r", stamp=0.0, dt=-0.1, v=0.0, w=0.0)


@pytest.mark.parametrize("cls", MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_random_payloads_raise_only_message_error(cls) -> None:
    """Fuzz: random bytes and random msgpack values never raise anything but MessageError."""
    rng = random.Random(1234)
    good = next(m for m in SAMPLES if type(m) is cls).to_dict()
    for i in range(300):
        if i % 3 == 0:
            payload = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 64)))
        else:
            raw = dict(good)
            key = rng.choice(sorted(raw))
            raw[key] = rng.choice([None, 1, -1.5, "x", b"\x00", [1, "a"], {"dtype": "<f8"},
                                   {"dtype": "<f8", "shape": [1], "data": b"\0" * 8},
                                   [[1.0, 2.0], [3.0]], True])
            payload = msgpack.packb(raw, use_bin_type=True)
        try:
            cls.from_bytes(payload)
        except MessageError:
            pass


def test_camera_control_is_the_documented_map_and_robot_is_optional() -> None:
    assert CameraControl(command="reregister").to_dict() == {"schema": 1,
                                                              "command": "reregister"}
    hand_made = msgpack.packb({"schema": 1, "command": "reregister", "robot": "robot1"})
    assert CameraControl.from_bytes(hand_made) == CameraControl(command="reregister",
                                                                robot="robot1")
    with pytest.raises(MessageError, match="command"):
        CameraControl(command="explode")


def test_truth_may_say_the_robots_marker() -> None:
    plain = Truth(robot="r", stamp=0.0, pose=[0, 0, 0], landmark_ids=[],
                  landmarks=np.zeros((0, 2)))
    assert "marker_id" not in plain.to_dict() and plain.marker_id is None
    marked = Truth.from_bytes(Truth(robot="r", stamp=0.0, pose=[0, 0, 0], landmark_ids=[],
                                    landmarks=np.zeros((0, 2)), marker_id=3).to_bytes())
    assert marked.marker_id == 3
    with pytest.raises(MessageError, match="marker_id"):
        Truth(robot="r", stamp=0.0, pose=[0, 0, 0], landmark_ids=[],
              landmarks=np.zeros((0, 2)), marker_id=-1)


def test_wire_parts_join_to_the_msgpack_encoding_with_large_arrays_not_copied() -> None:
    """A large state's encoding in parts (the covariance its own part, its own memory):
    joined, the same bytes msgpack would write, and the message decodes back equal."""
    from slamlens.common.arrays import bytes_backed_array

    n = 200  # covariance 403² · 8 B = 1.3 MB, above BIG_BINARY
    N = 3 + 2 * n
    rng = np.random.default_rng(5)
    A = rng.standard_normal((N, N))
    cov = bytes_backed_array((N, N), "<f8")
    cov[...] = A @ A.T
    cov.flags.writeable = False
    state = SlamState(robot="r", seq=3, stamp=1.5, step="update", pose=[1.0, 2.0, 0.5],
                      landmark_ids=np.arange(n), landmarks=rng.standard_normal((n, 2)),
                      covariance=cov, observed_ids=[1, 2], new_ids=[], epoch=7,
                      diagnostics={"gated": 0.0})
    assert state.covariance is cov  # a frozen array of the right dtype is kept, not copied
    parts = state.wire_parts()
    assert len(parts) == 3 and parts[1] is not None and len(parts[1]) == N * N * 8
    reference = msgpack.packb(state.to_dict(), use_bin_type=True)
    assert b"".join(parts) == reference == state.to_bytes()
    assert np.shares_memory(np.frombuffer(parts[1], dtype="<f8"), cov)
    assert SlamState.from_bytes(state.to_bytes()) == state
    # a small message is one part, msgpack's own encoding
    small = SlamState(robot="r", seq=1, stamp=0.0, step="init", pose=[0, 0, 0],
                      landmark_ids=[], landmarks=np.zeros((0, 2)), covariance=np.zeros((3, 3)))
    assert small.wire_parts() == [msgpack.packb(small.to_dict(), use_bin_type=True)]


@pytest.mark.parametrize("message,field,value", [
    (SAMPLES[3], "seq", -2), (SAMPLES[3], "seq", -(2 ** 63)), (SAMPLES[3], "epoch", -1),
    (SAMPLES[0], "input_seq", -5), (SAMPLES[4], "seq", -1), (SAMPLES[4], "verdict_since", -3),
    (SAMPLES[5], "seq", -1), (SAMPLES[5], "width", -4), (SAMPLES[5], "height", -2),
    (SAMPLES[6], "width", -640), (SAMPLES[6], "height", -1), (SAMPLES[10], "seq", -7),
], ids=lambda v: str(v) if not hasattr(v, "TYPE") else v.TYPE)
def test_negative_sequence_numbers_epochs_and_sizes_are_refused_naming_the_field(
        message, field, value) -> None:
    raw = msgpack.unpackb(message.to_bytes(), raw=False)
    raw[field] = value
    with pytest.raises(MessageError) as err:
        type(message).from_bytes(msgpack.packb(raw, use_bin_type=True))
    assert f"{message.TYPE}.{field}" in str(err.value) and str(value) in str(err.value)


def test_a_violation_with_a_negative_step_or_count_is_refused() -> None:
    for key in ("step", "first_step", "count"):
        raw = Violation("pair", (4, 5), 3, 0.01, first_step=2, count=1).to_dict()
        raw[key] = -1
        with pytest.raises(MessageError, match=key):
            Violation.from_dict(raw)
