"""Settings of ``slamlens ros2``, the bridge to ROS 2 robots over rmw_zenoh (docs/ros2.md).

One frozen dataclass, its fields declared once with :func:`slamlens.common.config.setting`
(TOML key, flag, help and docs/cli.md row in one). It inherits
:class:`~slamlens.common.scene3d.SceneSettings`: the markers show what the viewer draws, in
the same modes with the same clustering and glyph. :class:`BagReplay` is what
``slamlens replay --format rosbag2`` hands the bridge's bag player (its flags are
``replay``'s own).
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.common.config import setting
from slamlens.common.errors import ConfigError
from slamlens.common.keys import check_name, ros_node
from slamlens.common.scene3d import SceneSettings
from slamlens.services.ros2.wire import DISTROS, check_topic, ros_name

FROM_ROS = ("none", "estimate", "inputs")


def default_topic(robot: str, leaf: str) -> str:
    """``/R/leaf`` with R as a ROS 2 name segment."""
    return f"/{ros_name(robot)}/{leaf}"


@dataclass(frozen=True)
class Ros2Settings(SceneSettings):
    """``slamlens ros2``: a robot's picture to ROS 2, and a ROS 2 robot's data in."""

    robot: str = setting("robot1", doc="robot name, a key segment (its ROS 2 topics use it "
                                       "with every character but letters, digits and _ as _)")
    domain: int = setting(0, doc="ROS_DOMAIN_ID: the first chunk of every rmw_zenoh key",
                          min=0, max=232)
    distro: str = setting("jazzy", doc="ROS 2 distribution of the other side: jazzy (and "
                                       "later) announce REP-2016 type hashes, humble "
                                       "TypeHashNotSupported", choices=DISTROS)
    from_ros: str = setting("none", doc="also take in from ROS 2: estimate = an estimator's "
                                        "/R/slam/estimate (or a pose-only /R/slam/pose) as "
                                        "the robot's states; inputs = /R/odom and "
                                        "/R/landmarks/observations as its odometry and "
                                        "observations; none = export only",
                            choices=FROM_ROS)
    export: bool = setting(True, doc="publish the robot's markers, pose, path, tf and "
                                     "health to ROS 2 (--no-export: only take in)")
    node: str = setting("", doc="ROS 2 node name (empty: slamlens_R; with --secure it must "
                                "be that one)", metavar="NAME")
    queue_mb: float = setting(512.0, doc="ROS 2 messages waiting to be converted, at most "
                                         "(then the oldest are dropped, counted)", unit="MB",
                              min=1.0)
    late_join_timeout_s: float = setting(2.0, doc="at start, ask this long for the robot's "
                                                  "latest state (0 = do not ask)", unit="s",
                                         min=0.0)

    def __post_init__(self) -> None:
        check_name("robot", self.robot)
        if self.node and ros_name(self.node) != self.node:
            raise ConfigError(f"setting 'node': {self.node!r} is not a ROS 2 node name "
                              "(letters, digits and _, not starting with a digit)")
        check_topic(self.topic("odom"))

    def node_name(self) -> str:
        return self.node or ros_node(self.robot)

    def topic(self, leaf: str) -> str:
        """The robot's ROS 2 topic ``/R/leaf`` (inputs, estimates)."""
        return default_topic(self.robot, leaf)

    def export_topic(self, leaf: str) -> str:
        """``/slamlens/R/leaf`` (what the bridge publishes)."""
        return f"/slamlens/{ros_name(self.robot)}/{leaf}"


@dataclass(frozen=True)
class BagReplay:
    """A rosbag2 folder played as robot ``robot`` (``slamlens replay --format rosbag2``)."""

    path: str
    robot: str
    what: str = "inputs"  #: inputs | estimate
    rate: float = 1.0
    start_s: float = 0.0
    duration_s: float = 0.0
    wait_for_estimator: bool = True
    wait_timeout_s: float = 60.0
    progress: str = "auto"
