"""The layout of a slamlens MCAP recording (docs/protocol.md, docs/recording.md). Pure.

* One MCAP channel per Zenoh key: the channel's topic is the key (``slamlens/robot/robot1/
  state``), its message encoding ``msgpack``, no schema (schema id 0), and its metadata
  ``{"slamlens.message": "SlamState", "slamlens.prefix": "slamlens"}``. Each message is the
  sample's payload byte for byte; its ``log_time`` is when the recorder received it (ns since
  the Unix epoch, the recorder's clock), its ``publish_time`` the sample's Zenoh timestamp
  (the publishing session's hybrid logical clock, converted from NTP64 to ns), its
  ``sequence`` a counter per channel from 1.
* Foxglove channels beside them, topics starting with ``/foxglove/`` (never a Zenoh key):
  :data:`FOXGLOVE_TOPICS`, Foxglove's own protobuf schemas plus two JSON ones for plots.
* File metadata ``slamlens`` (``prefix``, ``keys`` recorded, ``started``), written first.
"""

from __future__ import annotations

import re

from slamlens.common.errors import SourceError

MESSAGE_ENCODING = "msgpack"
METADATA_NAME = "slamlens"
PROFILE = ""  #: no MCAP profile: msgpack is not one of the well-known encodings
FOXGLOVE_PREFIX = "/foxglove/"

#: Foxglove topic templates (robot R, camera C) and what they carry
FOXGLOVE_TOPICS = {
    "/foxglove/robot/{robot}/scene": "foxglove.SceneUpdate: robot, path, features, pair "
                                     "lines, P_d ellipsoids (suspects magenta)",
    "/foxglove/robot/{robot}/covariance": "JSON (plottable): min / mean / max P_d size, n, "
                                          "per-pair sizes",
    "/foxglove/robot/{robot}/health": "JSON (plottable): ok, verdict, violations, NEES, NIS "
                                      "and the monitor's other statistics",
    "/foxglove/robot/{robot}/transform": "foxglove.FrameTransform map → R/base_link (the "
                                         "estimated pose)",
    "/foxglove/robot/{robot}/path": "foxglove.PosesInFrame: the estimated path",
    "/foxglove/robot/{robot}/truth": "foxglove.SceneUpdate: the ground truth (robot, "
                                     "landmarks, path)",
    "/foxglove/camera/{camera}/image": "foxglove.CompressedImage (JPEG frames)",
    "/foxglove/camera/{camera}/calibration": "foxglove.CameraCalibration",
    "/foxglove/camera/{camera}/transform": "foxglove.FrameTransform map → camera_C "
                                           "(from the registration)",
}

#: the message type on each leaf of a key (the last segment, or "registration")
MESSAGE_OF_LEAF = {
    "odometry": "Odometry", "observations": "Observations", "truth": "Truth",
    "tracked": "Truth", "state": "SlamState", "health": "Health", "frame": "CameraFrame",
    "pose": "CameraPose", "control": "Control",
}

_BAD_KEY = re.compile(r"(^/|/$|//|[*$?#\s])")


def message_of_key(key: str, prefix: str) -> str:
    """The slamlens message type a key carries ("" if the key is not one of docs/protocol.md's)."""
    parts = key.split("/")
    n = len(prefix.split("/"))
    if parts[:n] != prefix.split("/") or len(parts) < n + 3:
        return ""
    if parts[n] == "camera" and len(parts) == n + 4 and parts[n + 2] == "registration":
        return "Registration"
    return MESSAGE_OF_LEAF.get(parts[-1], "") if len(parts) == n + 3 else ""


def check_topic_key(topic: str) -> str:
    """A recorded channel's topic as a Zenoh key to publish on; SourceError if it is not one."""
    if not topic or _BAD_KEY.search(topic):
        raise SourceError(f"channel topic {topic!r} is not a Zenoh key")
    return topic


def ntp64_to_ns(ntp64: int) -> int:
    """An NTP64 time (Zenoh/uhlc: seconds since the Unix epoch in the high 32 bits, the
    fraction in the low 32) as integer nanoseconds since the Unix epoch."""
    seconds = ntp64 >> 32
    fraction = ntp64 & 0xFFFF_FFFF
    return seconds * 1_000_000_000 + ((fraction * 1_000_000_000) >> 32)


def record_expressions(prefix: str, *, robots: tuple[str, ...] = (),
                       cameras: tuple[str, ...] = (), keys: tuple[str, ...] = ()) -> list[str]:
    """The key expressions a recorder subscribes to: everything under the prefix unless
    robots, cameras or explicit expressions narrow it."""
    out = [f"{prefix}/robot/{r}/**" for r in robots]
    out += [f"{prefix}/camera/{c}/**" for c in cameras]
    out += list(keys)
    return out or [f"{prefix}/**"]
