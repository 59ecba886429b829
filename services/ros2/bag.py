"""A rosbag2 folder as a robot's messages (pure: files in, slamlens messages out).

``rosbags`` reads the folder (``metadata.yaml`` and its MCAP or sqlite3 storage). For robot
R the bag holds either

* the robot's inputs: ``/R/odom`` (nav_msgs/msg/Odometry) and ``/R/landmarks/observations``
  (slamlens_msgs/msg/RangeBearingArray), converted as the live bridge converts them
  (:mod:`.imports`) into ``Odometry`` and ``Observations``, or
* an estimator's output: ``/R/slam/estimate`` (slamlens_msgs/msg/SlamEstimate) as
  ``SlamState``; a bag with only ``/R/slam/pose`` (Odometry or PoseWithCovarianceStamped)
  gives pose-only states.

Messages come in the bag's order (its receive time); malformed ones are skipped and
counted, with one log line naming the first.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from slamlens.common.errors import MessageError, SourceError
from slamlens.common.messages import Message
from slamlens.services.ros2.imports import (
    OdometryInput,
    decode,
    observations,
    pose_state,
    slam_state,
)
from slamlens.services.ros2.rostypes import (
    ODOMETRY,
    POSE_COV,
    RANGE_BEARING_ARRAY,
    SLAM_ESTIMATE,
)
from slamlens.services.ros2.wire import ros_name

log = logging.getLogger("slamlens.ros2")
WHATS = ("inputs", "estimate")


@dataclass(frozen=True)
class Topics:
    """The ROS 2 topics of robot R (the bridge's defaults; R as a ROS name segment)."""

    robot: str

    @property
    def odom(self) -> str:
        return f"/{self.robot}/odom"

    @property
    def observations(self) -> str:
        return f"/{self.robot}/landmarks/observations"

    @property
    def estimate(self) -> str:
        return f"/{self.robot}/slam/estimate"

    @property
    def pose(self) -> str:
        return f"/{self.robot}/slam/pose"


@dataclass
class BagStats:
    read: int = 0  #: messages read from the chosen topics
    skipped: Counter[str] = field(default_factory=Counter)  #: malformed, per topic
    first_error: str = ""

    @property
    def total_skipped(self) -> int:
        return sum(self.skipped.values())


class Bag:
    """The messages of robot ``robot`` in the rosbag2 folder ``path`` (module docstring)."""

    def __init__(self, path: str, *, robot: str, what: str, distro: str = "jazzy") -> None:
        from rosbags.rosbag2 import Reader

        if what not in WHATS:
            raise SourceError(f"rosbag2: what {what!r}, expected one of {', '.join(WHATS)}")
        self.path, self.robot, self.what, self.distro = path, robot, what, distro
        self.topics = Topics(ros_name(robot))
        if not (Path(path) / "metadata.yaml").is_file():
            raise SourceError(f"{path} is not a rosbag2 folder (no metadata.yaml)")
        try:
            self._reader = Reader(path)
            self._reader.open()
        except Exception as exc:  # rosbags' own errors: a bad or unsupported bag
            raise SourceError(f"cannot read the rosbag2 folder {path}: {exc}") from None
        choices: dict[str, dict[str, str | None]] = {
            "inputs": {self.topics.odom: ODOMETRY, self.topics.observations: RANGE_BEARING_ARRAY},
            "estimate": {self.topics.estimate: SLAM_ESTIMATE, self.topics.pose: None}}
        wanted = choices[what]
        self.connections = [c for c in self._reader.connections if c.topic in wanted
                            and wanted[c.topic] in (None, c.msgtype)]
        if not self.connections:
            present = sorted({f"{c.topic} ({c.msgtype})" for c in self._reader.connections})
            self._reader.close()
            raise SourceError(f"rosbag2 {path} has none of {', '.join(wanted)} as {what} "
                              f"for robot {self.topics.robot}; it holds: "
                              f"{', '.join(present) or 'nothing'}")
        self.stats = BagStats()
        self.start_ns = int(self._reader.start_time)
        self.duration_s = max(0.0, (self._reader.end_time - self._reader.start_time) / 1e9)

    def close(self) -> None:
        self._reader.close()

    def _convert(self, topic: str, msgtype: str, raw: bytes, odometry: OdometryInput,
                 pose_seq: list[int]) -> Message:
        msg = decode(raw, msgtype, self.distro)
        if msgtype == SLAM_ESTIMATE:
            return slam_state(msg, self.robot)
        if topic == self.topics.pose and msgtype in (ODOMETRY, POSE_COV):
            pose_seq[0] += 1
            return pose_state(msg, msgtype, self.robot, pose_seq[0])
        if msgtype == ODOMETRY:
            return odometry.convert(msg)
        return observations(msg, self.robot)

    def events(self, *, start_s: float = 0.0, end_s: float | None = None) -> Iterator[Message]:
        """The converted messages between ``start_s`` and ``end_s`` seconds after the bag's
        start (its receive clock)."""
        odometry = OdometryInput(self.robot)
        pose_seq = [0]
        estimates = any(c.msgtype == SLAM_ESTIMATE for c in self.connections)
        for connection, log_ns, raw in self._reader.messages(connections=self.connections):
            t = (log_ns - self.start_ns) / 1e9
            if t < start_s:
                continue
            if end_s is not None and t > end_s:
                break
            if estimates and connection.topic == self.topics.pose:
                continue  # a full estimate is there: pose-only messages are not needed
            self.stats.read += 1
            try:
                yield self._convert(connection.topic, connection.msgtype, bytes(raw),
                                    odometry, pose_seq)
            except MessageError as exc:
                self.stats.skipped[connection.topic] += 1
                if not self.stats.first_error:
                    self.stats.first_error = f"{connection.topic} at {t:.3f} s: {exc}"
                    log.warning("rosbag2: skipped a malformed message (counted): %s",
                                self.stats.first_error)
