"""``slamlens ros2``: one robot between slamlens's bus and ROS 2 nodes on rmw_zenoh.

Export (unless ``--no-export``): the robot's ``state`` and ``health`` are taken newest
first (a slow RViz never delays anything: older states add to the path only) and
published on ``/slamlens/R/markers`` (:mod:`.markers`), ``/slamlens/R/pose``,
``/slamlens/R/path``, ``/tf`` and ``/slamlens/R/health`` (:mod:`.outputs`).

Import (``--from-ros``): ``estimate`` takes ``/R/slam/estimate`` (or a pose-only
``/R/slam/pose``) and publishes the robot's states as the estimator does
(:mod:`.states`); ``inputs`` takes ``/R/odom`` and ``/R/landmarks/observations`` and
publishes them as the drivers do, numbered with ``input_seq`` in arrival order
(``common/robot_inputs.py``), so the estimator applies them in that order, once.

Bad input — malformed CDR, another type or type hash, a missing or malformed attachment,
arrays of the wrong length — is dropped and counted per topic with one log line
(``DropCounter``); the bridge goes on. Every Zenoh callback only queues.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from slamlens.common.bus import Bus, Channel, Sample
from slamlens.common.channel import QueueChannel
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, Message, SlamState
from slamlens.common.robot_inputs import RobotPublisher
from slamlens.services.ros2.imports import (
    OdometryInput,
    decode,
    observations,
    pose_state,
    slam_state,
)
from slamlens.services.ros2.markers import MarkerExport
from slamlens.services.ros2.node import RosNode, RosPublisher
from slamlens.services.ros2.outputs import PathTrack, diagnostics, pose_with_covariance, transform
from slamlens.services.ros2.rostypes import (
    DIAGNOSTICS,
    MARKER_ARRAY,
    ODOMETRY,
    PATH,
    POSE_COV,
    RANGE_BEARING_ARRAY,
    SLAM_ESTIMATE,
    TF,
    RosType,
    ros_type,
)
from slamlens.services.ros2.settings import Ros2Settings
from slamlens.services.ros2.states import StatePublisher
from slamlens.services.ros2.wire import parse_topic_key

log = logging.getLogger("slamlens.ros2")
LARGE = 1 << 20  #: a state at least this big waits uncopied, newest only


class Ros2Bridge:
    """The bridge of one robot (module docstring)."""

    def __init__(self, bus: Any, *, keys: Keys, settings: Ros2Settings) -> None:
        self.bus: Bus = bus
        self.keys = keys
        self.s = settings
        self.drops = DropCounter(log)
        self.counts: dict[str, int] = {"states": 0, "health": 0, "received": 0,
                                       "imported": 0, "pose_only_ignored": 0}
        self.node = RosNode(bus.session, domain=settings.domain, name=settings.node_name())
        self._pubs: dict[str, RosPublisher] = {}
        self._exports: Channel | None = None
        if settings.export:
            self._declare_exports()
        self._imports = QueueChannel(name="ros2 imports",
                                     max_bytes=int(settings.queue_mb * 2 ** 20))
        self._expect: dict[str, list[RosType]] = {}
        self.sink: StatePublisher | RobotPublisher | None = None
        if settings.from_ros != "none":
            self._declare_imports()

    # -- declarations -----------------------------------------------------------------
    def _type(self, name: str) -> RosType:
        return ros_type(name, self.s.distro)

    def _declare_exports(self) -> None:
        s = self.s
        for leaf, topic, name in (("markers", s.export_topic("markers"), MARKER_ARRAY),
                                  ("pose", s.export_topic("pose"), POSE_COV),
                                  ("path", s.export_topic("path"), PATH),
                                  ("tf", "/tf", TF),
                                  ("health", s.export_topic("health"), DIAGNOSTICS)):
            self._pubs[leaf] = self.node.publisher(topic, self._type(name))
        self.markers = MarkerExport(s.scene_settings())
        self.path = PathTrack(s.path_points)
        self._exports = self.bus.channel(self.keys.state(s.robot),
                                         also=(self.keys.health(s.robot),),
                                         newest_above=LARGE)

    def _subscribe(self, topics: dict[str, tuple[str, ...]]) -> None:
        """One subscription for ``topics`` (topic → the types accepted, the first announced)."""
        for topic, names in topics.items():
            self._expect[topic] = [self._type(n) for n in names]
        self.node.subscription({t: types[0] for t, types in self._expect.items()},
                               self._imports, self._drop)

    def _declare_imports(self) -> None:
        s = self.s
        if s.from_ros == "estimate":
            self.sink = StatePublisher(self.bus, keys=self.keys, robot=s.robot,
                                        dropped=lambda: self.drops.total)
            self._subscribe({s.topic("slam/estimate"): (SLAM_ESTIMATE,),
                             s.topic("slam/pose"): (POSE_COV, ODOMETRY)})
        else:
            self.sink = RobotPublisher(self.bus, keys=self.keys, robot=s.robot)
            self._subscribe({s.topic("odom"): (ODOMETRY,),
                             s.topic("landmarks/observations"): (RANGE_BEARING_ARRAY,)})
        self._odometry = OdometryInput(s.robot)
        self._pose_seq = 0
        self._estimates_seen = False

    def _drop(self, topic: str, reason: str) -> None:
        self.drops.drop(topic, reason)

    # -- import -------------------------------------------------------------------------
    def _typed(self, key: str) -> tuple[str, RosType]:
        data = parse_topic_key(key, self.s.domain)
        for t in self._expect.get(data.topic, []):
            if data.dds_type == t.dds:
                if data.type_hash != t.hash:
                    raise MessageError(t.name, "type hash", t.hash, data.type_hash)
                return data.topic, t
        wanted = " or ".join(t.dds for t in self._expect.get(data.topic, [])) or "nothing"
        raise MessageError("rmw_zenoh", "type", wanted, data.dds_type)

    def convert(self, sample: Sample) -> Message | None:
        """The slamlens message of one ROS 2 sample (MessageError if bad; None: ignored)."""
        topic, t = self._typed(sample.key)
        msg = decode(sample.payload, t.name, self.s.distro)
        if t.name == SLAM_ESTIMATE:
            self._estimates_seen = True
            return slam_state(msg, self.s.robot)
        if self.s.from_ros == "estimate":
            if self._estimates_seen:
                self.counts["pose_only_ignored"] += 1
                return None
            self._pose_seq += 1
            return pose_state(msg, t.name, self.s.robot, self._pose_seq)
        if t.name == ODOMETRY:
            return self._odometry.convert(msg)
        return observations(msg, self.s.robot)

    def _import_one(self, sample: Sample) -> None:
        self.counts["received"] += 1
        try:
            message = self.convert(sample)
        except MessageError as exc:
            topic = sample.key.split("/")[1:-2]
            self.drops.drop("/" + "/".join(topic), str(exc))
            return
        if message is not None and self.sink is not None:
            self.sink.publish(message)
            self.counts["imported"] += 1

    # -- export -------------------------------------------------------------------------
    def _export(self, samples: list[Sample]) -> None:
        health_key = self.keys.health(self.s.robot)
        states = [x for x in samples if x.key != health_key]
        healths = [x for x in samples if x.key == health_key]
        for sample in healths[-1:]:
            try:
                self._health = Health.from_bytes(sample.payload)
            except MessageError as exc:
                self.drops.drop("health", str(exc))
                continue
            self._pubs["health"].put(diagnostics(self._health))
            self.counts["health"] += 1
        for k, sample in enumerate(states):
            newest = k == len(states) - 1
            if not newest and len(sample.payload) >= LARGE:
                continue
            try:
                state = SlamState.from_bytes(sample.payload, check_symmetry=False)
            except MessageError as exc:
                self.drops.drop("state", str(exc))
                continue
            self.path.add(state)
            if newest:
                self.publish_state(state)

    def publish_state(self, state: SlamState) -> None:
        """Markers, pose, path and tf of ``state`` (its pose already in the path)."""
        health = getattr(self, "_health", None)
        self._pubs["markers"].put(self.markers.update(state, health=health,
                                                      path_xy=self.path.xy()))
        self._pubs["pose"].put(pose_with_covariance(state))
        self._pubs["path"].put(self.path.path(state.stamp))
        self._pubs["tf"].put(transform(state))
        self.counts["states"] += 1

    def late_join(self) -> None:
        """The robot's latest state, by ``get`` (as a viewer joining late)."""
        if self._exports is None or self.s.late_join_timeout_s <= 0:
            return
        for reply in self.bus.get(self.keys.state(self.s.robot),
                                  timeout=self.s.late_join_timeout_s):
            self._export([reply])

    # -- running ------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Import on a thread of its own, export on this one, until ``stop``."""
        importer = threading.Thread(target=self._run_imports, args=(stop,),
                                    name="ros2-import", daemon=True)
        importer.start()
        exports = self._exports
        while not stop.is_set():
            if exports is None:
                stop.wait(0.2)
                continue
            first = exports.recv(timeout=0.2)
            if first is not None:
                self._export([first, *exports.take_all()])
        importer.join(timeout=2.0)

    def _run_imports(self, stop: threading.Event) -> None:
        while not stop.is_set():
            sample = self._imports.recv(timeout=0.2)
            if sample is not None:
                self._import_one(sample)

    def summary(self) -> dict[str, Any]:
        sink = {} if self.sink is None else dict(self.sink.counts)
        return {**self.counts, "published": {k: p.sent for k, p in self._pubs.items()},
                "to_bus": sink, "dropped": self.drops.total,
                "dropped_by_topic": dict(self.drops.counts),
                "queue_dropped": self._imports.dropped,
                "superseded": self._imports.superseded}

    def close(self) -> None:
        self.node.close()
        if self.sink is not None and hasattr(self.sink, "close"):
            self.sink.close()
