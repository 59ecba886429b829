"""The ROS 2 message types the bridge speaks, their definitions and type hashes (pure).

Standard types come from ``rosbags``' type store of the distro (jazzy or humble: they differ
in ``visualization_msgs/msg/Marker``); the project's own two, ``slamlens_msgs/msg/
SlamEstimate`` and ``slamlens_msgs/msg/RangeBearingArray``, from the ``.msg`` files shipped
in ``services/ros2/msg/``. Type hashes are REP-2016's RIHS01, as ``rosbags`` computes them,
for jazzy; humble's rmw_zenoh announces ``TypeHashNotSupported`` for every type.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from slamlens.common.errors import ConfigError
from slamlens.services.ros2.wire import DISTROS, HUMBLE_HASH, dds_type_name

MSG_DIR = Path(__file__).resolve().parent / "msg"
SLAM_ESTIMATE = "slamlens_msgs/msg/SlamEstimate"
RANGE_BEARING_ARRAY = "slamlens_msgs/msg/RangeBearingArray"
OWN_TYPES = (SLAM_ESTIMATE, RANGE_BEARING_ARRAY)

MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
PATH = "nav_msgs/msg/Path"
TF = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
ODOMETRY = "nav_msgs/msg/Odometry"


def msg_file(ros_type: str) -> Path:
    """The shipped ``.msg`` file of one of the project's own types."""
    return MSG_DIR / f"{ros_type.rsplit('/', 1)[1]}.msg"


@cache
def typestore(distro: str) -> Any:
    """``rosbags``' type store of ``distro`` with the project's own types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if distro not in DISTROS:
        raise ConfigError(f"ROS 2 distro {distro!r}: expected one of {', '.join(DISTROS)}")
    store = get_typestore(Stores.ROS2_JAZZY if distro == "jazzy" else Stores.ROS2_HUMBLE)
    for name in OWN_TYPES:
        store.register(get_types_from_msg(msg_file(name).read_text(), name))
    return store


@dataclass(frozen=True)
class RosType:
    """One message type as it appears on the wire."""

    name: str  #: ``pkg/msg/Name``
    dds: str  #: ``pkg::msg::dds_::Name_``
    hash: str  #: RIHS01_… or TypeHashNotSupported


@cache
def ros_type(name: str, distro: str) -> RosType:
    store = typestore(distro)
    type_hash = HUMBLE_HASH if distro == "humble" else store.hash_rihs01(name)
    return RosType(name, dds_type_name(name), type_hash)
