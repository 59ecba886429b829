"""The robot's pose, path, transform and health as ROS 2 messages (pure, CDR payloads).

* ``geometry_msgs/msg/PoseWithCovarianceStamped``: the estimated pose in ``map`` and its
  3×3 covariance P_vv (x, y, θ) in the 6×6 (x, y, z, roll, pitch, yaw; the rest 0);
* ``nav_msgs/msg/Path``: the estimated poses so far (:class:`PathTrack`);
* ``tf2_msgs/msg/TFMessage``: ``map`` → ``R/base_link`` at the estimated pose;
* ``diagnostic_msgs/msg/DiagnosticArray``: the monitor's verdict as a level (ok → OK,
  tuning → WARN, fault → ERROR), its suspects, NEES and NIS as key/values.

Stamps are the state's own (``header.stamp`` = SlamState.stamp, data time).
"""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.messages import Health, SlamState
from slamlens.common.scene3d import MAP_FRAME
from slamlens.services.ros2.cdr import Template, Writer, repeat, stamp_ns

OK, WARN, ERROR = 0, 1, 2
LEVELS = {"ok": OK, "tuning": WARN, "fault": ERROR}
#: 6×6 indices of x, y and yaw
_POSE6 = np.array([0, 1, 5])


def _quaternion(theta: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(0.5 * theta), math.cos(0.5 * theta))


def base_frame(robot: str) -> str:
    return f"{robot}/base_link"


def pose_with_covariance(state: SlamState) -> bytes:
    x, y, theta = (float(v) for v in state.pose)
    cov = np.zeros((6, 6))
    cov[np.ix_(_POSE6, _POSE6)] = np.asarray(state.covariance)[:3, :3]
    w = Writer()
    w.header(stamp_ns(state.stamp), MAP_FRAME)
    w.f64s((x, y, 0.0, *_quaternion(theta)))
    w.f64s(cov.reshape(-1))
    return w.bytes()


def transform(state: SlamState) -> bytes:
    """A TFMessage with the one transform ``map`` → ``R/base_link``."""
    x, y, theta = (float(v) for v in state.pose)
    w = Writer()
    w.u32(1)
    w.header(stamp_ns(state.stamp), MAP_FRAME)
    w.string(base_frame(state.robot))
    w.f64s((x, y, 0.0, *_quaternion(theta)))
    return w.bytes()


def diagnostics(health: Health) -> bytes:
    """A DiagnosticArray with one status: the monitor's verdict on the robot."""
    stats = dict(health.statistics)
    values = [("verdict", health.verdict), ("seq", str(health.seq)),
              ("suspects", " ".join(str(i) for i in health.suspects.tolist())),
              ("violations", str(len(health.violations)))]
    values += [(name, f"{value:.6g}") for name, value in sorted(stats.items())
               if name.startswith(("nees", "nis"))]
    standing = "; ".join(f"{v.kind} {list(v.ids)}" for v in health.standing[:5])
    message = health.verdict + (f": {standing}" if standing else "")
    w = Writer()
    w.header(stamp_ns(health.stamp), "")
    w.u32(1)
    w.u8(LEVELS.get(health.verdict, ERROR))
    w.string(f"slamlens {health.robot}")
    w.string(message)
    w.string(health.robot)
    w.u32(len(values))
    for key, value in values:
        w.string(key)
        w.string(value)
    return w.bytes()


def _write_pose_stamped(w: Writer) -> None:
    w.stamp(0, mark="stamp")
    w.string(MAP_FRAME)
    w.f64s((0.0,) * 7, mark="pose")


_POSE_STAMPED = Template(_write_pose_stamped)


class PathTrack:
    """The estimated poses of one map, for ``nav_msgs/msg/Path`` and the path marker:
    one per state that moved the robot, thinned to every other one beyond
    ``2 × max_points`` (the shape kept); a new map starts it again."""

    def __init__(self, max_points: int) -> None:
        self.max_points = max_points
        #: stamp, x, y, θ of the first ``_count`` rows: an array kept, so that a state's
        #: path and markers cost O(1) conversions, not one per point
        self._rows = np.empty((2 * max_points + 1, 4))
        self._count = 0
        self._map: tuple[int, int] | None = None

    def add(self, state: SlamState) -> None:
        last, self._map = self._map, (state.epoch, state.seq)
        if last is not None and (state.epoch != last[0] or state.seq < last[1]):
            self._count = 0
        x, y, theta = (float(v) for v in state.pose)
        n = self._count
        if n and self._rows[n - 1, 1] == x and self._rows[n - 1, 2] == y:
            return
        self._rows[n] = (float(state.stamp), x, y, theta)
        self._count = n = n + 1
        if n > 2 * self.max_points:
            kept = self._rows[0:n:2].copy()
            self._rows[:len(kept)] = kept
            self._count = len(kept)

    def xy(self) -> np.ndarray:
        return self._rows[:self._count, 1:3].copy()

    def path(self, stamp: float) -> bytes:
        """The ``nav_msgs/msg/Path`` (header stamped ``stamp``)."""
        rows = self._rows[:self._count]
        w = Writer()
        w.header(stamp_ns(stamp), MAP_FRAME)
        w.u32(len(rows))
        whole = np.floor(rows[:, 0])
        nsec = np.round((rows[:, 0] - whole) * 1e9).astype(np.int64)
        sec = whole.astype(np.int64) + nsec // 1_000_000_000
        stamps = np.column_stack([sec, nsec % 1_000_000_000]).astype("<i4")
        poses = np.zeros((len(rows), 7))
        poses[:, :2] = rows[:, 1:3]
        poses[:, 5], poses[:, 6] = np.sin(0.5 * rows[:, 3]), np.cos(0.5 * rows[:, 3])
        data, _ = repeat(_POSE_STAMPED, len(rows), w.offset % 8,
                         {"stamp": stamps, "pose": poses})
        return w.bytes() + data
