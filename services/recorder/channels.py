"""The Foxglove channels of a recording or a live server, from the bus's samples (pure).

:class:`FoxgloveTranslator` takes the samples one by one (``feed(key, payload,
log_time_ns)``) and returns the Foxglove messages they make (docs/recording.md):

* a robot's ``state`` → its ``scene`` (``foxglove.SceneUpdate``, see :mod:`.scene`) and
  ``covariance`` (JSON for plots: n, min / mean / max P_d size, each pair's size), at most
  ``scene_hz`` per second of robot time (the newest state is always shown by ``finish``);
  a state not drawn is only peeked at (its pose, for the path), never decoded in full;
* its ``health`` → ``health`` (JSON: ok, verdict, violations, suspects, and every statistic
  of the monitor: NEES, NIS, their bounds …) at the same rate, and every health that is not
  ok; the scene marks what the newest blames in magenta;
* with each scene, ``transform`` (``foxglove.FrameTransform`` ``map`` → ``R/base_link``, the
  estimated pose: a 3D panel can follow the robot) and, when the scene carries the path,
  ``path`` (``foxglove.PosesInFrame``: every estimated pose so far, thinned beyond a length);
* its ``truth`` → ``truth`` (a ``SceneUpdate`` of its own: the true robot, landmarks and
  path) at most ``scene_hz`` per robot second; a truth not drawn only adds to the path;
* a camera's ``frame`` → ``image`` (``foxglove.CompressedImage``), its ``registration`` →
  ``calibration`` (``foxglove.CameraCalibration``) and ``transform``
  (``foxglove.FrameTransform`` from ``map`` to ``camera_C``), so Foxglove's Image panel can
  draw the scene over the camera picture as the viewer does.

A malformed payload raises :class:`~slamlens.common.errors.MessageError` (the caller counts it).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from foxglove.messages import (
    CameraCalibration,
    CompressedImage,
    FrameTransform,
    Point3,
    Pose,
    PosesInFrame,
    Quaternion,
    SceneUpdate,
    Vector3,
)

from slamlens.common.arrays import decode_array
from slamlens.common.errors import MessageError
from slamlens.common.geometry import all_relative_covariances, invert_T, pd_size_m
from slamlens.common.messages import (
    CameraFrame,
    Health,
    Registration,
    SlamState,
    Truth,
    peek_fields,
)
from slamlens.services.recorder.layout import message_of_key
from slamlens.services.recorder.scene import MAP_FRAME, scene_update, timestamp, truth_update
from slamlens.services.recorder.settings import SceneSettings

PATH_PERIOD_S = 1.0  #: the path entity is sent at most once per this much robot time
MAX_PLOTTED_PAIRS = 1000  #: beyond this many pairs the covariance message has no per-pair list


@dataclass(frozen=True)
class Schema:
    name: str
    encoding: str  #: "protobuf" | "jsonschema"
    data: bytes


@dataclass(frozen=True)
class FoxgloveMessage:
    """One message of a Foxglove channel."""

    topic: str
    schema: Schema
    message_encoding: str  #: "protobuf" | "json"
    data: bytes
    log_time_ns: int


def _proto(cls: Any) -> Schema:
    s = cls.get_schema()
    return Schema(s.name, s.encoding, bytes(s.data))


COVARIANCE_SCHEMA = Schema("slamlens.Covariance", "jsonschema", json.dumps({
    "title": "slamlens.Covariance",
    "description": "sizes of the relative covariances P_d of one state (sqrt of the largest "
                   "eigenvalue, m)",
    "type": "object",
    "properties": {
        "robot": {"type": "string"}, "seq": {"type": "integer"},
        "epoch": {"type": "integer"}, "stamp": {"type": "number"},
        "n": {"type": "integer"}, "pairs_n": {"type": "integer"},
        "pd_min_m": {"type": "number"}, "pd_mean_m": {"type": "number"},
        "pd_max_m": {"type": "number"},
        "pose_sigma_m": {"type": "number"},
        "pairs": {"type": "array", "items": {"type": "object", "properties": {
            "a": {"type": "integer"}, "b": {"type": "integer"},
            "size_m": {"type": "number"}}, "required": ["a", "b", "size_m"]}},
    },
    "required": ["robot", "seq", "epoch", "stamp", "n", "pairs_n", "pd_min_m", "pd_mean_m",
                 "pd_max_m", "pose_sigma_m", "pairs"],
}).encode())

HEALTH_SCHEMA = Schema("slamlens.Health", "jsonschema", json.dumps({
    "title": "slamlens.Health",
    "description": "the monitor's verdict on one state; statistics holds NEES, NIS and their "
                   "chi-square bounds (docs/monitor.md)",
    "type": "object",
    "properties": {
        "robot": {"type": "string"}, "seq": {"type": "integer"},
        "stamp": {"type": "number"}, "ok": {"type": "boolean"},
        "verdict": {"type": "string"}, "violations": {"type": "integer"},
        "suspects": {"type": "array", "items": {"type": "integer"}},
        "statistics": {"type": "object", "additionalProperties": {"type": "number"}},
    },
    "required": ["robot", "seq", "stamp", "ok", "verdict", "violations", "suspects",
                 "statistics"],
}).encode())

SCENE_SCHEMA = _proto(SceneUpdate)
IMAGE_SCHEMA = _proto(CompressedImage)
CALIBRATION_SCHEMA = _proto(CameraCalibration)
TRANSFORM_SCHEMA = _proto(FrameTransform)
POSES_SCHEMA = _proto(PosesInFrame)


def robot_topic(robot: str, leaf: str) -> str:
    return f"/foxglove/robot/{robot}/{leaf}"


def camera_topic(camera: str, leaf: str) -> str:
    return f"/foxglove/camera/{camera}/{leaf}"


def camera_frame_id(camera: str) -> str:
    return f"camera_{camera}"


def robot_frame_id(robot: str) -> str:
    """The robot's frame, child of ``map`` by its estimated pose."""
    return f"{robot}/base_link"


def planar_pose(x: float, y: float, theta: float) -> Pose:
    """A pose on the floor of the map, heading ``theta`` about z."""
    return Pose(position=Vector3(x=x, y=y, z=0.0), orientation=_heading(theta))


def _heading(theta: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * theta), w=math.cos(0.5 * theta))


def robot_transform(robot: str, pose: np.ndarray, log_time_ns: int) -> bytes:
    """``FrameTransform`` ``map`` → ``R/base_link`` at the estimated pose (x, y, θ)."""
    x, y, theta = (float(v) for v in np.asarray(pose).reshape(3))
    return FrameTransform(timestamp=timestamp(log_time_ns), parent_frame_id=MAP_FRAME,
                          child_frame_id=robot_frame_id(robot),
                          translation=Vector3(x=x, y=y, z=0.0),
                          rotation=_heading(theta)).encode()


def path_poses(poses: list[Pose], log_time_ns: int) -> bytes:
    """``PosesInFrame`` of the estimated path in ``map``."""
    return PosesInFrame(timestamp=timestamp(log_time_ns), frame_id=MAP_FRAME,
                        poses=poses).encode()


def covariance_summary(state: SlamState) -> dict[str, Any]:
    """The plottable numbers of one state's P_d (every pair, whatever the mode)."""
    n = state.n
    out: dict[str, Any] = {"robot": state.robot, "seq": state.seq, "epoch": state.epoch,
                           "stamp": state.stamp, "n": n}
    P = state.covariance
    out["pose_sigma_m"] = float(math.sqrt(max(0.0, 0.5 * (P[0, 0] + P[1, 1]))))
    if n >= 2:
        first, second, Pd = all_relative_covariances(P, n)
        sizes = pd_size_m(Pd)
        out.update(pairs_n=int(sizes.size), pd_min_m=float(sizes.min()),
                   pd_mean_m=float(sizes.mean()), pd_max_m=float(sizes.max()))
        ids = state.landmark_ids
        out["pairs"] = [] if sizes.size > MAX_PLOTTED_PAIRS else [
            {"a": int(a), "b": int(b), "size_m": float(s)} for a, b, s in
            zip(ids[first].tolist(), ids[second].tolist(), sizes.tolist(), strict=True)]
    else:
        out.update(pairs_n=0, pd_min_m=0.0, pd_mean_m=0.0, pd_max_m=0.0, pairs=[])
    return out


def health_summary(health: Health) -> dict[str, Any]:
    return {"robot": health.robot, "seq": health.seq, "stamp": health.stamp,
            "ok": bool(health.ok), "verdict": health.verdict,
            "violations": len(health.violations),
            "suspects": [int(s) for s in health.suspects.tolist()],
            "statistics": {k: float(v) for k, v in health.statistics.items()}}


def calibration_messages(reg: Registration, log_time_ns: int) -> tuple[bytes, bytes]:
    """``CameraCalibration`` and ``FrameTransform`` (map → camera) of one registration."""
    K = np.asarray(reg.K, dtype=float)
    dist = [float(d) for d in np.asarray(reg.dist).reshape(-1).tolist()]
    model = "rational_polynomial" if len(dist) > 5 else "plumb_bob"
    P = np.zeros((3, 4))
    P[:, :3] = K
    frame = camera_frame_id(reg.camera)
    calibration = CameraCalibration(
        timestamp=timestamp(log_time_ns), frame_id=frame, width=int(reg.width),
        height=int(reg.height), distortion_model=model, D=dist,
        K=K.reshape(-1).tolist(), R=np.eye(3).reshape(-1).tolist(), P=P.reshape(-1).tolist())
    T = invert_T(np.asarray(reg.T_camera_from_map, dtype=float))  # T_map_from_camera
    q = _quaternion(T[:3, :3])
    transform = FrameTransform(
        timestamp=timestamp(log_time_ns), parent_frame_id=MAP_FRAME, child_frame_id=frame,
        translation=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
    return calibration.encode(), transform.encode()


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method: stable for every angle)."""
    tr = float(np.trace(R))
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return ((R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s,
                0.25 * s)
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(max(1e-12, 1.0 + R[i, i] - R[j, j] - R[k, k]))
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (R[j, i] + R[i, j]) / s
    q[k] = (R[k, i] + R[i, k]) / s
    q[3] = (R[k, j] - R[j, k]) / s
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


@dataclass
class _Robot:
    path: list[tuple[float, float]] = field(default_factory=list)
    path_fx: list[Point3] = field(default_factory=list)  #: the same as Foxglove points
    poses: list[Pose] = field(default_factory=list)  #: the same with headings
    epoch: int | None = None
    last_seq: int = -1
    last_scene_stamp: float | None = None
    pending: tuple[bytes, int] | None = None  #: newest state not drawn yet (payload, log time)
    health_raw: bytes | None = None  #: newest health (decoded when a scene needs it)
    health: Health | None = None
    pending_health: tuple[bytes, int] | None = None
    last_health_stamp: float | None = None
    new_map: bool = True
    last_path_stamp: float | None = None
    truth_path: list[Point3] = field(default_factory=list)
    truth_last: tuple[float, float] | None = None  #: the last point of the true path
    last_truth_stamp: float | None = None
    pending_truth: tuple[bytes, int] | None = None  #: newest truth not drawn yet


class FoxgloveTranslator:
    """Samples in, Foxglove messages out (module docstring)."""

    def __init__(self, settings: SceneSettings, *, prefix: str, scene_hz: float = 0.0) -> None:
        self.settings = settings
        self.prefix = prefix
        self.scene_hz = scene_hz
        self._robots: dict[str, _Robot] = {}
        self.scenes = 0  #: scene updates made
        self.glyphs = 0  #: ellipsoids in the last scene

    def set_settings(self, settings: SceneSettings) -> None:
        self.settings = settings

    def feed(self, key: str, payload: bytes, log_time_ns: int) -> list[FoxgloveMessage]:
        kind = message_of_key(key, self.prefix)
        if kind == "SlamState":
            return self._state(payload, log_time_ns)
        if kind == "Health":
            return self._health(payload, log_time_ns)
        if kind == "Truth" and key.endswith("/truth"):  # a robot's truth (not a camera's
            return self._truth(payload, log_time_ns)    # tracked pose)
        if kind == "CameraFrame":
            frame = CameraFrame.from_bytes(payload)
            image = CompressedImage(timestamp=timestamp(log_time_ns),
                                    frame_id=camera_frame_id(frame.camera), data=frame.data,
                                    format=frame.encoding)
            return [FoxgloveMessage(camera_topic(frame.camera, "image"), IMAGE_SCHEMA,
                                    "protobuf", image.encode(), log_time_ns)]
        if kind == "Registration":
            reg = Registration.from_bytes(payload)
            calibration, transform = calibration_messages(reg, log_time_ns)
            return [FoxgloveMessage(camera_topic(reg.camera, "calibration"),
                                    CALIBRATION_SCHEMA, "protobuf", calibration, log_time_ns),
                    FoxgloveMessage(camera_topic(reg.camera, "transform"), TRANSFORM_SCHEMA,
                                    "protobuf", transform, log_time_ns)]
        return []

    def _robot(self, name: str) -> _Robot:
        robot = self._robots.get(name)
        if robot is None:
            robot = self._robots[name] = _Robot()
        return robot

    def _due(self, last: float | None, stamp: float) -> bool:
        return (self.scene_hz <= 0 or last is None or stamp < last
                or stamp - last >= 1.0 / self.scene_hz)

    def _health(self, payload: bytes, log_time_ns: int) -> list[FoxgloveMessage]:
        """Health is decoded when it is shown: at most ``scene_hz`` per robot second, and
        every one that is not ok (the newest is kept for the scene either way)."""
        head = peek_fields(payload, ("robot", "stamp", "ok"))
        robot = self._robot(str(head.get("robot", "")))
        stamp = head.get("stamp")
        if not isinstance(stamp, (int, float)):
            Health.from_bytes(payload)  # raises the decoder's own clear error
            stamp = 0.0
        robot.health_raw = payload
        robot.health = None
        if head.get("ok") is True and not self._due(robot.last_health_stamp, float(stamp)):
            robot.pending_health = (payload, log_time_ns)
            return []
        return self._health_message(robot, payload, log_time_ns)

    def _health_message(self, robot: _Robot, payload: bytes,
                        log_time_ns: int) -> list[FoxgloveMessage]:
        health = Health.from_bytes(payload)
        robot.pending_health = None
        robot.last_health_stamp = health.stamp
        return [FoxgloveMessage(robot_topic(health.robot, "health"), HEALTH_SCHEMA, "json",
                                json.dumps(health_summary(health)).encode(), log_time_ns)]

    def _latest_health(self, robot: _Robot) -> Health | None:
        if robot.health is None and robot.health_raw is not None:
            try:
                robot.health = Health.from_bytes(robot.health_raw)
            except MessageError:
                robot.health_raw = None
        return robot.health

    def _state(self, payload: bytes, log_time_ns: int) -> list[FoxgloveMessage]:
        """A state is decoded in full only when it is drawn; the others add to the path."""
        head = peek_fields(payload, ("robot", "seq", "stamp", "epoch", "pose"))
        try:
            name, seq, stamp = str(head["robot"]), int(head["seq"]), float(head["stamp"])
            pose = decode_array(head["pose"], message="SlamState", field="pose", dtype="<f8",
                                shape=(3,))
        except (KeyError, TypeError, ValueError, MessageError):
            SlamState.from_bytes(payload, check_symmetry=False)  # the decoder's clear error
            raise MessageError("SlamState", "<header>", "robot, seq, stamp and pose",
                               "malformed") from None
        epoch = head.get("epoch", 0)
        robot = self._robot(name)
        if robot.epoch != epoch or seq < robot.last_seq:
            robot.path, robot.path_fx, robot.poses = [], [], []
            robot.epoch, robot.new_map = epoch, True
            robot.last_scene_stamp = robot.last_path_stamp = None
            robot.health = robot.health_raw = None
        robot.last_seq = seq
        point = (float(pose[0]), float(pose[1]))
        if not robot.path or robot.path[-1] != point:
            robot.path.append(point)
            robot.path_fx.append(Point3(x=point[0], y=point[1], z=0.0))
            robot.poses.append(planar_pose(point[0], point[1], float(pose[2])))
            if len(robot.path) > 2 * self.settings.path_points:
                robot.path = robot.path[::2]  # thin the old path, keep its shape
                robot.path_fx = robot.path_fx[::2]
                robot.poses = robot.poses[::2]
        if not (robot.new_map or self._due(robot.last_scene_stamp, stamp)):
            robot.pending = (payload, log_time_ns)
            return []
        return self._draw(robot, SlamState.from_bytes(payload, check_symmetry=False),
                          log_time_ns)

    def _draw(self, robot: _Robot, state: SlamState, log_time_ns: int, *,
              final: bool = False) -> list[FoxgloveMessage]:
        robot.pending = None
        robot.last_scene_stamp = state.stamp
        with_path = (final or robot.new_map or robot.last_path_stamp is None
                     or abs(state.stamp - robot.last_path_stamp) >= PATH_PERIOD_S)
        if with_path:
            robot.last_path_stamp = state.stamp
        data, glyphs = scene_update(state, self.settings, log_time_ns=log_time_ns,
                                    path_xy=robot.path_fx if with_path else None,
                                    health=self._latest_health(robot), new_map=robot.new_map)
        robot.new_map = False
        self.scenes += 1
        self.glyphs = len(glyphs.centres)
        out = [FoxgloveMessage(robot_topic(state.robot, "scene"), SCENE_SCHEMA, "protobuf",
                               data, log_time_ns),
               FoxgloveMessage(robot_topic(state.robot, "covariance"), COVARIANCE_SCHEMA,
                               "json", json.dumps(covariance_summary(state)).encode(),
                               log_time_ns),
               FoxgloveMessage(robot_topic(state.robot, "transform"), TRANSFORM_SCHEMA,
                               "protobuf", robot_transform(state.robot, state.pose,
                                                           log_time_ns), log_time_ns)]
        if with_path:
            out.append(FoxgloveMessage(robot_topic(state.robot, "path"), POSES_SCHEMA,
                                       "protobuf", path_poses(robot.poses, log_time_ns),
                                       log_time_ns))
        return out

    def _truth(self, payload: bytes, log_time_ns: int) -> list[FoxgloveMessage]:
        """A truth is decoded when it is drawn (at most ``scene_hz`` per robot second);
        the others only add their position to the true path."""
        head = peek_fields(payload, ("robot", "stamp", "pose"))
        try:
            name, stamp = str(head["robot"]), float(head["stamp"])
            pose = decode_array(head["pose"], message="Truth", field="pose", dtype="<f8",
                                shape=(3,))
        except (KeyError, TypeError, ValueError, MessageError):
            Truth.from_bytes(payload)  # raises the decoder's own clear error
            raise MessageError("Truth", "<header>", "robot, stamp and pose",
                               "malformed") from None
        robot = self._robot(name)
        if robot.last_truth_stamp is not None and stamp < robot.last_truth_stamp:
            robot.truth_path = []  # the run started again
        point = (float(pose[0]), float(pose[1]))
        if not robot.truth_path or robot.truth_last != point:
            robot.truth_last = point
            robot.truth_path.append(Point3(x=point[0], y=point[1], z=0.0))
            if len(robot.truth_path) > 2 * self.settings.path_points:
                robot.truth_path = robot.truth_path[::2]
        if not self._due(robot.last_truth_stamp, stamp):
            robot.pending_truth = (payload, log_time_ns)
            return []
        return self._truth_message(robot, Truth.from_bytes(payload), log_time_ns)

    def _truth_message(self, robot: _Robot, truth: Truth,
                       log_time_ns: int) -> list[FoxgloveMessage]:
        robot.pending_truth = None
        robot.last_truth_stamp = truth.stamp
        return [FoxgloveMessage(robot_topic(truth.robot, "truth"), SCENE_SCHEMA, "protobuf",
                                truth_update(truth, log_time_ns=log_time_ns,
                                             path=robot.truth_path), log_time_ns)]

    def finish(self) -> list[FoxgloveMessage]:
        """The scenes of the newest states not drawn yet (at the end of a recording)."""
        out: list[FoxgloveMessage] = []
        for robot in self._robots.values():
            if robot.pending is not None:
                payload, log_time_ns = robot.pending
                out += self._draw(robot, SlamState.from_bytes(payload, check_symmetry=False),
                                  log_time_ns, final=True)
            if robot.pending_health is not None:
                out += self._health_message(robot, *robot.pending_health)
            if robot.pending_truth is not None:
                payload, log_time_ns = robot.pending_truth
                out += self._truth_message(robot, Truth.from_bytes(payload), log_time_ns)
        return out

    def redraw(self, robot_name: str, state: SlamState,
               log_time_ns: int) -> list[FoxgloveMessage]:
        """The scene of ``state`` now, whatever the rate (a live client just subscribed, or
        the settings changed)."""
        robot = self._robot(robot_name)
        return self._draw(robot, state, log_time_ns, final=True)
