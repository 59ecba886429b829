"""One camera's pipeline: capture (:mod:`capture`), then detect, register and publish.

Per camera (two for stereo) a :class:`CameraPipeline` runs two threads:

* capture (:class:`~slamlens.services.registration.capture.FrameCapture`): read the source
  at its rate, publish ``CameraFrame`` latest-wins, and leave the image in a keep-newest
  slot (:class:`~slamlens.common.latest.Latest`);
* processing: take the newest image (skipping any it had no time for), detect markers,
  feed the :class:`~slamlens.services.registration.tracking.Registrar`, publish ``Registration``
  (also answered to ``get``), the tracked robot pose and, head-mounted, ``CameraPose``.

Control: a :class:`~slamlens.common.messages.CameraControl` (``{"schema": 1, "command":
"reregister", "robot": R, "requester": …}``) put on ``keys.camera_control(camera)``, or
sent as the payload of a Zenoh query on that key (what a viewer may do under ``--secure``:
it may query, not publish), re-registers from the next frames. A re-registration that would
move the map frame by more than ``max_reregister_move_m`` / ``max_reregister_turn_deg``
while the robot is not at its map origin is refused, with the reason, and the old one kept.

Maps (docs/delivery.md, epochs): the pipeline watches the robot's state header (epoch, origin_stamp,
pose). The first map it sees keeps the registration made while the robot stood still; a
new map (a new epoch) is registered from the remembered frame nearest its
``origin_stamp`` — where the robot stood when that map started. Every Registration says
its ``epoch``, ``reason`` and how far it moved the frame. Only the header is read of a
state, and a state is copied out of Zenoh's buffer only when its header is read: at most
every :data:`STATE_HEAD_EVERY_S` (a 32 MB state at n = 1000 costs ~20 ms of CPU to copy,
and the estimator publishes tens a second; docs/registration.md, "Maps").
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from slamlens.common.arrays import decode_array
from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError, SlamlensError
from slamlens.common.geometry import invert_T
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.messages import CameraPose, Registration, Truth, peek_fields
from slamlens.services.registration.board import MarkerBoard, camera_pose_from_board
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.capture import FrameCapture, PipelineStats
from slamlens.services.registration.markers import AnyDetector, WindowedDetector
from slamlens.services.registration.sources import FrameSource
from slamlens.services.registration.tracking import (
    STATUS_WAITING,
    FrameResult,
    Registrar,
    frame_change,
)

log = logging.getLogger("slamlens.services.registration.service")

STATE_HEAD_EVERY_S = 0.5  #: a state's header is read (and the state copied) at most this often


@dataclasses.dataclass(frozen=True)
class CameraSettings:
    """How one camera is run: its names, rates and what it publishes."""

    camera: str  #: camera name (key segment)
    robot: str  #: robot whose marker registers the map frame
    fps: float  #: capture rate of sources that do not pace themselves, Hz
    jpeg_quality: int = 80  #: of the published frames, 1-100
    moving: bool = False  #: head-mounted: the camera's pose is found every frame
    publish_tracked: bool = True  #: publish the tracked robot pose (one camera per robot)
    registration_period_s: float = 1.0  #: a fixed camera's registration is re-published
    max_reregister_move_m: float = 0.05  #: a requested re-registration moving more is refused…
    max_reregister_turn_deg: float = 5.0  #: …or turning more, unless the robot is at its origin
    origin_tolerance_m: float = 0.05  #: the robot is at its map origin within this


@dataclasses.dataclass(frozen=True)
class MapHead:
    """What the registration needs of the robot's newest state."""

    epoch: int
    origin_stamp: float | None
    pose: np.ndarray | None  #: the estimated pose (x, y, θ) in that map


def map_head(payload: bytes) -> MapHead | None:
    """The header of a SlamState payload (the map itself is not decoded); None if it is
    not one."""
    try:
        head = peek_fields(payload, ("epoch", "origin_stamp", "pose"))
        epoch, origin = head.get("epoch", 0), head.get("origin_stamp")
        pose = head.get("pose")
        if not isinstance(epoch, int) or (origin is not None
                                          and not isinstance(origin, (int, float))):
            return None
        pose_a = None if pose is None else decode_array(pose, message="SlamState",
                                                          field="pose", dtype="<f8",
                                                          shape=(3,))
        return MapHead(epoch=epoch, origin_stamp=None if origin is None else float(origin),
                       pose=pose_a)
    except MessageError:
        return None


@dataclasses.dataclass(frozen=True, eq=False)
class CameraParts:
    """What one camera works with: its frames, intrinsics, detector and registrar.

    A moving camera's pose comes from ``tracker_pose`` if given (an external tracker),
    else from ``board`` (the marker board in view); a fixed camera needs neither.
    """

    source: FrameSource
    calib: CameraCalibration
    detector: AnyDetector | WindowedDetector
    registrar: Registrar
    board: MarkerBoard | None = None
    tracker_pose: Callable[[], np.ndarray | None] | None = None




class CameraPipeline:
    """Capture, publish and register one camera."""

    def __init__(self, bus: Bus, keys: Keys, *, settings: CameraSettings,
                 parts: CameraParts) -> None:
        self.settings = settings
        self.parts = parts
        self.camera, self.robot = settings.camera, settings.robot
        self.stats = PipelineStats()
        self._bus = bus
        self._stop = threading.Event()
        self._requests: Latest[str] = Latest()  #: who asked for a re-registration
        #: the robot's newest state, still in Zenoh's buffer: a call copies it out
        self._states: Latest[Callable[[], bytes]] = Latest()
        self._head_read_at = -math.inf  #: when _follow_map last read a state's header
        self._map: MapHead | None = None  #: the map the registration is for
        self._waiting: MapHead | None = None  #: a new map not registered yet
        self._pending_request: tuple[str, np.ndarray | None] | None = None
        self._reason = "start"
        self._change: tuple[float, float] | None = None
        self._latest_registration: Registration | None = None
        self._latest_bytes: bytes | None = None
        self._last_status = ""
        self._last_published = 0.0
        camera, robot = self.camera, self.robot
        frame_pub = bus.publisher(keys.frame(camera), latest_wins=True)
        self._reg_pub = bus.publisher(keys.registration(camera, robot))
        self._tracked_pub = bus.publisher(keys.tracked_by(camera, robot), latest_wins=True)
        self._pose_pub = bus.publisher(keys.camera_pose(camera), latest_wins=True)
        #: what this camera declared on the bus (released when a browser camera leaves)
        self._entities: list[Any] = [
            frame_pub, self._reg_pub, self._tracked_pub, self._pose_pub,
            bus.serve_latest(keys.registration(camera, robot), lambda: self._latest_bytes),
            bus.declare_alive(keys.camera_alive(camera))]
        self.capture = FrameCapture(camera=camera, source=parts.source, publisher=frame_pub,
                                    fps=settings.fps, jpeg_quality=settings.jpeg_quality,
                                    stats=self.stats, stop=self._stop)
        self._frames = self.capture.frames
        self._threads = [threading.Thread(target=self.capture.run, name=f"capture-{camera}",
                                          daemon=True),
                         threading.Thread(target=self._process_loop, name=f"register-{camera}",
                                          daemon=True)]

    @property
    def source(self) -> FrameSource:
        return self.parts.source

    @property
    def registrar(self) -> Registrar:
        return self.parts.registrar

    @property
    def read_errors(self) -> DropCounter:
        """Failed reads of the source."""
        return self.capture.read_errors

    # -- lifecycle ----------------------------------------------------------------
    def start(self) -> None:
        for t in self._threads:
            t.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._frames.close()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout)
        self.source.close()

    def release(self) -> None:
        """Stop, and undeclare what this camera declared on the bus (its publishers, its
        registration's queryable, its liveliness token): a camera that left."""
        self.stop()
        for entity in self._entities:
            self._bus.release(entity)
        self._entities.clear()

    def inherit(self, T_anchor_from_map: np.ndarray, *, epoch: int | None, camera: str,
                reprojection_error_px: float) -> None:
        """Start registered as ``camera`` registered the same map (call before
        :meth:`start`): cameras anchored in the same world — head-mounted ones on one
        marker board — share the map's place in it."""
        registrar = self.registrar
        registrar.T_anchor_from_map = np.array(T_anchor_from_map, dtype=np.float64)
        registrar.collecting = False
        registrar.reprojection_error_px = reprojection_error_px
        if epoch is not None:
            self._map = MapHead(epoch=epoch, origin_stamp=None, pose=None)
        self._reason, self._change = f"from camera {camera}", None
        self.stats.registrations += 1
        log.info("camera %s: starts from camera %s's registration of robot %s", self.camera,
                 camera, self.robot)

    def request_reregister(self, requester: str = "") -> None:
        """Re-register from the next frames (called from a Zenoh thread: only stores)."""
        self._requests.put(requester or "an anonymous request")

    def offer_state(self, fetch: Callable[[], bytes]) -> None:
        """The robot's newest state, as a function that copies it out of Zenoh's buffer
        (called from a Zenoh thread: only stores)."""
        self._states.put(fetch)

    @property
    def epoch(self) -> int | None:
        """The map epoch the current registration is for (None before a state is seen)."""
        return None if self._map is None else self._map.epoch

    @property
    def latest_registration(self) -> Registration | None:
        return self._latest_registration

    @property
    def status(self) -> str:
        """What the camera is doing: the source's trouble if it has one (lost, stalled,
        ended), else the registrar's last status ("" before the first frame)."""
        return self.capture.source_state or self._last_status

    def publish_fps(self, window_s: float = 2.0) -> float:
        """Frames published per second over the last ``window_s`` seconds."""
        now = time.monotonic()
        recent = [t for t in list(self.stats.publish_times) if now - t <= window_s]
        return len(recent) / window_s

    # -- processing thread ------------------------------------------------------------
    def _process_loop(self) -> None:
        finished = False
        while not self._stop.is_set():
            item = self._frames.take(timeout=0.1)
            if item is None:
                if self.stats.ended and not finished:
                    finished = True  # a short file: register from the frames it had
                    self._finish()
                continue
            seq, stamp, image = item
            self.stats.skipped = self._frames.dropped
            try:
                self._process(stamp, image)
            except SlamlensError as exc:
                log.warning("camera %s: frame %d not processed: %s", self.camera, seq, exc)
            except Exception:  # keep registering on the next frame whatever happened
                log.exception("camera %s: processing frame %d failed", self.camera, seq)
            self.stats.processed += 1

    def _finish(self) -> None:
        result = self.registrar.finish()
        if result is not None:
            self.stats.registrations += 1
            log.info("camera %s: robot %s registered from the last frames of the source "
                     "(reprojection error %.3f px)", self.camera, self.robot,
                     self.registrar.reprojection_error_px)
            calib = self.parts.calib
            self._publish_registration(result, calib.width, calib.height)

    def _anchor_pose(self, detections: Sequence[Any], stamp: float) -> np.ndarray | None:
        """T_anchor_from_camera of this frame (identity for a fixed camera)."""
        parts = self.parts
        if not self.settings.moving:
            return np.eye(4)
        if parts.tracker_pose is not None:
            return parts.tracker_pose()
        if parts.board is None:
            return None
        found = camera_pose_from_board(detections, parts.board, parts.calib)
        if found is None:
            return None
        T_world_from_camera, _rms, _n = found
        self._pose_pub.put(CameraPose(camera=self.camera, stamp=float(stamp),
                                      T_world_from_camera=T_world_from_camera).to_bytes())
        self.stats.camera_poses += 1
        return T_world_from_camera

    def _process(self, stamp: float, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        calib = self.parts.calib
        if (w, h) != (calib.width, calib.height):
            # the intrinsics would be wrong for this frame: publish it, never register on it
            self.stats.size_mismatches += 1
            if self.stats.size_mismatches == 1:
                log.error("camera %s: frames are %dx%d but the calibration is for %dx%d; "
                          "not registering", self.camera, w, h, calib.width, calib.height)
            return
        requester = self._requests.take(timeout=0)
        if requester is not None:
            self._pending_request = (requester, None if self.registrar.T_anchor_from_map is None
                                     else self.registrar.T_anchor_from_map.copy())
            self.registrar.reset()
            log.info("camera %s: re-registering robot %s from the next frames (requested by "
                     "%s)", self.camera, self.robot, requester)
        detections = self.parts.detector.detect(image)
        T_anchor = self._anchor_pose(detections, stamp)
        result = self.registrar.observe(stamp, detections, T_anchor_from_camera=T_anchor)
        if result.registered_now and not self._registered_now():
            # refused: this frame's result was computed with the registration just undone
            T = self.registrar.T_anchor_from_map
            result = dataclasses.replace(
                result, registered_now=False, tracked_pose=None,
                T_camera_from_map=None if T is None or T_anchor is None
                else invert_T(T_anchor) @ T)
        remapped = self._follow_map()
        if remapped is not None:  # the frame of the new map, in this frame
            result = dataclasses.replace(result, registered_now=True,
                                         T_camera_from_map=remapped)
        self._publish_registration(result, image.shape[1], image.shape[0])
        if result.tracked_pose is not None and self.settings.publish_tracked:
            msg = Truth(robot=self.robot, stamp=float(stamp), pose=result.tracked_pose,
                        landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)))
            self._tracked_pub.put(msg.to_bytes())
            self.stats.tracked += 1

    # -- maps and requests ---------------------------------------------------------
    def _registered_now(self) -> bool:
        """A registration from still frames just completed (a start, or a request);
        False if it was a request refused (and undone)."""
        self.stats.registrations += 1
        request, self._pending_request = self._pending_request, None
        if request is None:
            self._reason, self._change = "start", None
            log.info("camera %s: robot %s registered (reprojection error %.3f px)",
                     self.camera, self.robot, self.registrar.reprojection_error_px)
            return True
        requester, old = request
        if old is None:
            self._reason, self._change = f"requested by {requester}", None
            return True
        assert self.registrar.T_anchor_from_map is not None
        change = frame_change(old, self.registrar.T_anchor_from_map)
        s = self.settings
        # (no estimate of the robot known — no estimator — then nothing says it moved)
        pose = None if self._map is None else self._map.pose
        away = pose is not None and (float(np.hypot(pose[0], pose[1])) > s.origin_tolerance_m
                                     or abs(math.degrees(float(pose[2])))
                                     > s.max_reregister_turn_deg)
        if (change.moved_m > s.max_reregister_move_m
                or change.moved_deg > s.max_reregister_turn_deg) and away:
            assert pose is not None
            self.registrar.T_anchor_from_map = old  # refused: keep the registration we had
            self._reason = (f"refused a re-registration requested by {requester}: it would "
                            f"move the map frame {change.moved_m:.2f} m / "
                            f"{change.moved_deg:.1f}° while the robot is "
                            f"{float(np.hypot(pose[0], pose[1])):.2f} m from its map origin")
            self._change = None
            self.stats.refused += 1
            self.stats.registrations -= 1
            log.warning("camera %s: %s", self.camera, self._reason)
            return False
        self._reason = f"requested by {requester}"
        self._change = (change.moved_m, change.moved_deg)
        log.info("camera %s: robot %s re-registered (requested by %s): the map frame moved "
                 "%.3f m / %.2f°", self.camera, self.robot, requester, change.moved_m,
                 change.moved_deg)
        return True

    def _follow_map(self) -> np.ndarray | None:
        """Register a new map at its origin instant; its T_camera_from_map if it did."""
        head = None
        now = time.monotonic()
        if now - self._head_read_at >= STATE_HEAD_EVERY_S:  # else the newest waits, uncopied
            fetch = self._states.take(timeout=0)
            if fetch is not None:
                self._head_read_at = now
                head = map_head(fetch())
        if head is None:
            head = self._waiting  # a new map still waiting for its origin frames
        if head is None:
            return None
        self._waiting = None
        if self._map is None or head.epoch == self._map.epoch:
            if self._map is None:  # the first map: registered while the robot stood still
                log.info("camera %s: registration is for map epoch %d", self.camera,
                         head.epoch)
            self._map = head
            return None
        if head.origin_stamp is None:
            self._waiting = head  # the new map has no origin instant yet: look again
            return None
        tolerance = max(2.0 / self.settings.fps, 0.1)
        span = self.registrar.history_span
        if span is not None and span[1] < head.origin_stamp - tolerance:
            self._waiting = head  # the camera lags the robot: wait for those frames
            return None
        change = self.registrar.register_at(head.origin_stamp, tolerance_s=tolerance)
        old_epoch = self._map.epoch
        self._map = head
        if change is None and not self.registrar.registered:
            return None
        if change is None:
            # no frame of that instant (the marker was not seen, or camera and robot do not
            # share a clock): register from the next still frames instead
            self._pending_request = None
            self.registrar.reset()
            self._reason = "new map (registered from the next frames: none of its origin)"
            log.warning("camera %s: map restarted (epoch %d → %d) but no frame near its "
                        "origin instant t = %.3f s; re-registering from the next frames",
                        self.camera, old_epoch, head.epoch, head.origin_stamp)
            return None
        self.stats.registrations += 1
        self._reason, self._change = "new map", (change.moved_m, change.moved_deg)
        log.info("camera %s: map restarted (epoch %d → %d): registered at its origin instant "
                 "t = %.3f s; the map frame moved %.3f m / %.1f°", self.camera, old_epoch,
                 head.epoch, head.origin_stamp, change.moved_m, change.moved_deg)
        # a fixed camera is its own anchor; a moving one gets it right from the next frame
        return None if self.settings.moving else self.registrar.T_anchor_from_map

    def _publish_registration(self, result: FrameResult, width: int, height: int) -> None:
        status_changed = result.status != self._last_status
        if status_changed:
            level = logging.INFO if result.status != STATUS_WAITING else logging.WARNING
            log.log(level, "camera %s: %s (robot %s, marker %d)", self.camera, result.status,
                    self.robot, self.registrar.settings.marker_id)
            self._last_status = result.status
        if not self.registrar.registered:
            return
        now = time.monotonic()
        if result.T_camera_from_map is not None:
            stamp = result.stamp if self.settings.moving or self.registrar.stamp is None \
                else self.registrar.stamp
            calib = self.parts.calib
            moved = self._change
            reg = Registration(
                camera=self.camera, robot=self.robot, stamp=float(stamp),
                K=calib.K, dist=calib.dist, width=width, height=height,
                T_camera_from_map=result.T_camera_from_map,
                reprojection_error_px=self.registrar.reprojection_error_px,
                status=result.status, epoch=self.epoch, reason=self._reason,
                moved_m=None if moved is None else moved[0],
                moved_deg=None if moved is None else moved[1])
        elif self._latest_registration is not None:
            # a moving camera's: stamped with this frame (whose pose it does not know: its
            # status says so), so that a consumer matching frames by stamp hears of it
            stamp = (float(result.stamp) if self.settings.moving
                     else self._latest_registration.stamp)
            reg = dataclasses.replace(self._latest_registration, status=result.status,
                                      epoch=self.epoch, reason=self._reason, stamp=stamp)
        else:
            return
        due = (result.registered_now or status_changed or self.settings.moving
               or now - self._last_published >= self.settings.registration_period_s)
        payload = reg.to_bytes()
        self._latest_registration, self._latest_bytes = reg, payload
        if due:
            self._reg_pub.put(payload)
            self._last_published = now

