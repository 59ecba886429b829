"""ROS 2 messages in, slamlens messages out (pure): decoding, checks, conversion.

A payload is decoded with ``rosbags`` (arrays as read-only views of the payload, no copy)
and checked; anything wrong raises ``MessageError`` naming what (a caller drops and counts
it):

* ``slamlens_msgs/msg/SlamEstimate`` → ``SlamState``: stamp = header.stamp (s), seq, pose
  from the Pose2D, landmark ids, ``landmarks`` (x0, y0, x1, y1 …) as [n, 2], ``covariance``
  row-major (3+2n)² as its matrix — the numbers bit for bit; step ``init`` for seq 0 and
  ``update`` otherwise; epoch 0 (unknown: consumers tell a restart by seq going back). The
  arrays must have 2n and (3+2n)² entries and everything be finite. The covariance is
  passed on as it is, as a third-party estimator's SlamState would be: a viewer refuses an
  asymmetric one, the monitor reports it (docs/protocol.md);
* ``nav_msgs/msg/Odometry`` or ``geometry_msgs/msg/PoseWithCovarianceStamped`` from a
  pose-only estimator → a ``SlamState`` without landmarks: the pose (yaw from the
  quaternion) and its 3×3 covariance (x, y, yaw of the 6×6); numbered by the caller;
* a robot's ``nav_msgs/msg/Odometry`` → ``Odometry``: v = twist.linear.x, ω =
  twist.angular.z, stamp = header.stamp and dt = the time since the previous message's
  stamp (0 for the first; a stamp going back is refused);
* ``slamlens_msgs/msg/RangeBearingArray`` → ``Observations`` (ids, ranges, bearings of one
  length).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from slamlens.common.errors import MessageError
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.services.ros2.rostypes import (
    ODOMETRY,
    POSE_COV,
    RANGE_BEARING_ARRAY,
    SLAM_ESTIMATE,
    typestore,
)
from slamlens.services.ros2.wire import check_cdr

_POSE6 = np.array([0, 1, 5])


def decode(payload: bytes, ros_type: str, distro: str) -> Any:
    """The ``rosbags`` message in ``payload``, or MessageError."""
    check_cdr(payload)
    try:  # a memoryview: rosbags slices off the header without copying 32 MB
        return typestore(distro).deserialize_cdr(memoryview(payload), ros_type)
    except Exception as exc:  # rosbags raises its own errors, and struct's, on bad bytes
        raise MessageError(ros_type, "payload", "a CDR message of this type",
                           f"{type(exc).__name__}: {str(exc)[:120]}") from None


def stamp_of(header: Any) -> float:
    """builtin_interfaces/Time as float seconds."""
    return int(header.stamp.sec) + int(header.stamp.nanosec) * 1e-9


def _finite(ros_type: str, name: str, value: float) -> float:
    if not math.isfinite(value):
        raise MessageError(ros_type, name, "a finite number", repr(value))
    return value


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def slam_state(msg: Any, robot: str) -> SlamState:
    """A ``SlamEstimate`` as the robot's SlamState (module docstring)."""
    ids = np.asarray(msg.landmark_ids)
    n = len(ids)
    if len(msg.landmarks) != 2 * n:
        raise MessageError(SLAM_ESTIMATE, "landmarks", f"2n = {2 * n} values (x, y per id)",
                           str(len(msg.landmarks)))
    size = 3 + 2 * n
    if len(msg.covariance) != size * size:
        raise MessageError(SLAM_ESTIMATE, "covariance", f"(3+2n)² = {size * size} values",
                           str(len(msg.covariance)))
    covariance = np.asarray(msg.covariance).reshape(size, size)
    seq = int(msg.seq)
    stamp = stamp_of(msg.header)
    pose = msg.pose
    return SlamState(robot=robot, seq=seq, stamp=stamp, step="init" if seq == 0 else "update",
                     pose=np.array([pose.x, pose.y, pose.theta], dtype=float),
                     landmark_ids=ids, landmarks=np.asarray(msg.landmarks).reshape(n, 2),
                     covariance=covariance, epoch=0, input_stamp=stamp)


def pose_state(msg: Any, ros_type: str, robot: str, seq: int) -> SlamState:
    """An Odometry or PoseWithCovarianceStamped of a pose-only estimator as a SlamState with
    no landmarks."""
    if ros_type not in (ODOMETRY, POSE_COV):
        raise MessageError(ros_type, "type", f"{ODOMETRY} or {POSE_COV}", ros_type)
    pose = msg.pose.pose
    cov6 = np.asarray(msg.pose.covariance, dtype=float)
    if cov6.shape != (36,):
        raise MessageError(ros_type, "pose.covariance", "36 values", str(cov6.shape))
    cov = cov6.reshape(6, 6)[np.ix_(_POSE6, _POSE6)]
    stamp = stamp_of(msg.header)
    x = _finite(ros_type, "pose.position.x", float(pose.position.x))
    y = _finite(ros_type, "pose.position.y", float(pose.position.y))
    return SlamState(robot=robot, seq=seq, stamp=stamp, step="init" if seq == 0 else "update",
                     pose=np.array([x, y, _yaw(pose.orientation)]),
                     landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)),
                     covariance=np.ascontiguousarray(cov), epoch=0, input_stamp=stamp)


class OdometryInput:
    """A robot's ``nav_msgs/msg/Odometry`` stream as slamlens ``Odometry`` (dt from the
    stamps of consecutive messages)."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.last_stamp: float | None = None

    def convert(self, msg: Any) -> Odometry:
        stamp = stamp_of(msg.header)
        dt = 0.0 if self.last_stamp is None else stamp - self.last_stamp
        if dt < 0:
            raise MessageError(ODOMETRY, "header.stamp", f"not before the previous "
                               f"{self.last_stamp:.9f} s", f"{stamp:.9f} s")
        twist = msg.twist.twist
        odometry = Odometry(robot=self.robot, stamp=stamp, dt=dt,
                            v=_finite(ODOMETRY, "twist.linear.x", float(twist.linear.x)),
                            w=_finite(ODOMETRY, "twist.angular.z", float(twist.angular.z)))
        self.last_stamp = stamp
        return odometry


def observations(msg: Any, robot: str) -> Observations:
    """A ``RangeBearingArray`` as slamlens ``Observations``."""
    k = len(msg.ids)
    for name in ("ranges", "bearings"):
        if len(getattr(msg, name)) != k:
            raise MessageError(RANGE_BEARING_ARRAY, name, f"{k} values (one per id)",
                               str(len(getattr(msg, name))))
    ranges = np.asarray(msg.ranges, dtype=float)
    if k and (not np.isfinite(ranges).all() or (ranges < 0).any()):
        raise MessageError(RANGE_BEARING_ARRAY, "ranges", "finite values ≥ 0",
                           f"{ranges[~(np.isfinite(ranges) & (ranges >= 0))][:3].tolist()}")
    return Observations(robot=robot, stamp=stamp_of(msg.header),
                        ids=np.asarray(msg.ids, dtype=np.int64), ranges=ranges,
                        bearings=np.asarray(msg.bearings, dtype=float))
