"""Every Zenoh key expression slamlens uses is built here (docs/protocol.md); nowhere else.

Robot and camera names are single key segments: non-empty, without ``/`` or the Zenoh
wildcard and verbatim characters (``* $ ? #``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from slamlens.common.errors import ConfigError

DEFAULT_PREFIX = "slamlens"
#: every leaf under ``{prefix}/robot/{robot}/`` (a test holds the builders to it)
ROBOT_LEAVES = ("odometry", "observations", "truth", "state", "health", "summary",
                "alive/estimator")
#: what the input keys' leaves, and no other leaf, start with (:meth:`Keys.inputs`)
INPUT_LEAF_START = "o"
_SEGMENT = re.compile(r"^[^/*$?#\s]+$")


def check_name(kind: str, name: str) -> str:
    """Validate a robot or camera name as one key segment."""
    if not isinstance(name, str) or not _SEGMENT.match(name):
        raise ConfigError(f"{kind} name {name!r} must be one key segment: non-empty, "
                          "no '/', '*', '$', '?', '#' or spaces")
    return name


def ros_name(text: str) -> str:
    """``text`` as a ROS 2 name segment (a robot's namespace, a node name): every character
    but letters, digits and ``_`` becomes ``_``, and a leading digit gets a ``_`` before it.
    The ROS 2 bridge names a robot's topics with it; the access control of its keys too."""
    out = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return f"_{out}" if out[:1].isdigit() or not out else out


def ros_node(robot: str) -> str:
    """The ROS 2 node name of robot ``robot``'s bridge."""
    return f"slamlens_{ros_name(robot)}"


def check_prefix(prefix: str) -> str:
    """Validate a key prefix: one or more segments joined by '/'."""
    if not isinstance(prefix, str) or not prefix or not all(
            _SEGMENT.match(p) for p in prefix.split("/")):
        raise ConfigError(f"prefix {prefix!r} must be segments joined by '/', without wildcards")
    return prefix


@dataclass(frozen=True)
class Keys:
    """Key builders under one prefix (``slamlens`` unless configured)."""

    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        check_prefix(self.prefix)

    # -- robot side ---------------------------------------------------------------
    def robot(self, robot: str, leaf: str) -> str:
        return f"{self.prefix}/robot/{check_name('robot', robot)}/{leaf}"

    def odometry(self, robot: str) -> str:
        return self.robot(robot, "odometry")

    def observations(self, robot: str) -> str:
        return self.robot(robot, "observations")

    def inputs(self, robot: str) -> str:
        """Both input keys of ``robot`` (odometry, observations) in one key expression and
        nothing else: the leaves starting with "o" (:data:`ROBOT_LEAVES`). One subscriber
        on it gets one publishing session's inputs in publication order (docs/protocol.md,
        "Inputs: order and delivery")."""
        return self.robot(robot, f"{INPUT_LEAF_START}$*")

    def truth(self, robot: str) -> str:
        return self.robot(robot, "truth")

    def state(self, robot: str) -> str:
        return self.robot(robot, "state")

    def health(self, robot: str) -> str:
        return self.robot(robot, "health")

    def summary(self, robot: str) -> str:
        """The queryable of what a remote viewer draws (docs/remote_viewers.md)."""
        return self.robot(robot, "summary")

    def tracked(self, robot: str) -> str:
        """Every camera's measured pose of ``robot`` (fields as Truth): the key
        expression to subscribe to. A camera publishes on :meth:`tracked_by` — under its own
        name, the only keys a camera identity may publish on (docs/security.md)."""
        return f"{self.prefix}/camera/*/tracked/{check_name('robot', robot)}"

    def tracked_by(self, camera: str, robot: str) -> str:
        """Camera ``camera``'s measured pose of ``robot``."""
        return self.camera(camera, f"tracked/{check_name('robot', robot)}")

    def estimator_alive(self, robot: str) -> str:
        """Liveliness token of the estimator serving ``robot``."""
        return self.robot(robot, "alive/estimator")

    def any_estimator_alive(self) -> str:
        return f"{self.prefix}/robot/*/alive/estimator"

    # -- camera side --------------------------------------------------------------
    def camera(self, camera: str, leaf: str) -> str:
        return f"{self.prefix}/camera/{check_name('camera', camera)}/{leaf}"

    def frame(self, camera: str) -> str:
        return self.camera(camera, "frame")

    def registration(self, camera: str, robot: str) -> str:
        return self.camera(camera, f"registration/{check_name('robot', robot)}")

    def camera_pose(self, camera: str) -> str:
        return self.camera(camera, "pose")

    def camera_control(self, camera: str) -> str:
        """Requests to the registration service, e.g. re-register (docs/protocol.md)."""
        return self.camera(camera, "control")

    def any_camera_control(self) -> str:
        """Every camera's :meth:`camera_control` key."""
        return f"{self.prefix}/camera/*/control"

    def registrations(self, camera: str) -> str:
        """The registrations of ``camera``, for every robot it registers."""
        return self.camera(camera, "registration/*")

    def capture(self, camera: str) -> str:
        """Frames a remote capture device sends for registration (a browser through the
        viewer's ``/ar`` page): CameraFrame, to ``slamlens registration --source browser``."""
        return self.camera(camera, "capture")

    def any_capture(self) -> str:
        """Every camera's :meth:`capture` key."""
        return f"{self.prefix}/camera/*/capture"

    def any_registration(self) -> str:
        """Every camera's registration of every robot."""
        return f"{self.prefix}/camera/*/registration/*"

    def camera_alive(self, camera: str) -> str:
        return self.camera(camera, "alive/registration")

    def any_camera_alive(self) -> str:
        return f"{self.prefix}/camera/*/alive/registration"

    # -- services -----------------------------------------------------------------
    def status(self, name: str, service: str, instance: str) -> str:
        """Where one running service holds its liveliness token and answers status
        queries: under its identity ``name`` (docs/protocol.md, ``slamlens status``)."""
        return (f"{self.prefix}/status/{check_name('identity', name)}/"
                f"{check_name('service', service)}/{check_name('instance', instance)}")

    def any_status(self) -> str:
        """Every service's status key, on every host."""
        return f"{self.prefix}/status/**"

    def status_of(self, key: str) -> tuple[str, str, str] | None:
        """(name, service, instance) of a :meth:`status` key, else None."""
        prefix = self.prefix.split("/")
        parts = key.split("/")
        n = len(prefix)
        if len(parts) == n + 4 and parts[:n] == prefix and parts[n] == "status":
            return parts[n + 1], parts[n + 2], parts[n + 3]
        return None

    # -- parsing ------------------------------------------------------------------
    def leaf_of(self, key: str) -> str:
        """The last segment of a key (``odometry``, ``observations`` …)."""
        return key.rsplit("/", 1)[-1]

    def robot_of(self, key: str) -> str | None:
        """The robot segment of a ``robot/{robot}/…`` key under this prefix, else None."""
        return self._segment_after(key, "robot")

    def camera_of(self, key: str) -> str | None:
        """The camera segment of a ``camera/{camera}/…`` key under this prefix, else None."""
        return self._segment_after(key, "camera")

    def _segment_after(self, key: str, kind: str) -> str | None:
        prefix = self.prefix.split("/")
        parts = key.split("/")
        n = len(prefix)
        if len(parts) > n + 1 and parts[:n] == prefix and parts[n] == kind:
            return parts[n + 1]
        return None
