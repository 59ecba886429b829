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

Maps and re-registration requests: :class:`~slamlens.services.registration.maps.MapFollower`
decides which map each registration places and why it was made.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import SlamlensError
from slamlens.common.geometry import invert_T
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.messages import CameraPose, Registration, Truth
from slamlens.services.registration.board import MarkerBoard, camera_pose_from_board
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.capture import FrameCapture, PipelineStats
from slamlens.services.registration.maps import CameraSettings, MapFollower
from slamlens.services.registration.markers import AnyDetector, WindowedDetector
from slamlens.services.registration.sources import FrameSource
from slamlens.services.registration.tracking import (
    STATUS_WAITING,
    FrameResult,
    Registrar,
)

log = logging.getLogger("slamlens.services.registration.service")



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
        self.maps = MapFollower(settings, parts.registrar, self.stats)
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
        self.maps.inherit(epoch, camera)
        log.info("camera %s: starts from camera %s's registration of robot %s", self.camera,
                 camera, self.robot)

    def request_reregister(self, requester: str = "") -> None:
        """Re-register from the next frames (called from a Zenoh thread: only stores)."""
        self._requests.put(requester or "an anonymous request")

    def offer_state(self, fetch: Callable[[], bytes]) -> None:
        """The robot's newest state, as a function that copies it out of Zenoh's buffer
        (called from a Zenoh thread: only stores)."""
        self.maps.offer_state(fetch)

    @property
    def epoch(self) -> int | None:
        """The map epoch the current registration is for (None before a state is seen)."""
        return self.maps.epoch

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
            self.maps.request(requester)
        detections = self.parts.detector.detect(image)
        T_anchor = self._anchor_pose(detections, stamp)
        result = self.registrar.observe(stamp, detections, T_anchor_from_camera=T_anchor)
        if result.registered_now and not self.maps.registered_now():
            # refused: this frame's result was computed with the registration just undone
            T = self.registrar.T_anchor_from_map
            result = dataclasses.replace(
                result, registered_now=False, tracked_pose=None,
                T_camera_from_map=None if T is None or T_anchor is None
                else invert_T(T_anchor) @ T)
        remapped = self.maps.follow()
        if remapped is not None:  # the frame of the new map, in this frame
            result = dataclasses.replace(result, registered_now=True,
                                         T_camera_from_map=remapped)
        self._publish_registration(result, image.shape[1], image.shape[0])
        if result.tracked_pose is not None and self.settings.publish_tracked:
            msg = Truth(robot=self.robot, stamp=float(stamp), pose=result.tracked_pose,
                        landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)))
            self._tracked_pub.put(msg.to_bytes())
            self.stats.tracked += 1

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
            moved = self.maps.change
            reg = Registration(
                camera=self.camera, robot=self.robot, stamp=float(stamp),
                K=calib.K, dist=calib.dist, width=width, height=height,
                T_camera_from_map=result.T_camera_from_map,
                reprojection_error_px=self.registrar.reprojection_error_px,
                status=result.status, epoch=self.epoch, reason=self.maps.reason,
                moved_m=None if moved is None else moved[0],
                moved_deg=None if moved is None else moved[1])
        elif self._latest_registration is not None:
            # a moving camera's: stamped with this frame (whose pose it does not know: its
            # status says so), so that a consumer matching frames by stamp hears of it
            stamp = (float(result.stamp) if self.settings.moving
                     else self._latest_registration.stamp)
            reg = dataclasses.replace(self._latest_registration, status=result.status,
                                      epoch=self.epoch, reason=self.maps.reason, stamp=stamp)
        else:
            return
        due = (result.registered_now or status_changed or self.settings.moving
               or now - self._last_published >= self.settings.registration_period_s)
        payload = reg.to_bytes()
        self._latest_registration, self._latest_bytes = reg, payload
        if due:
            self._reg_pub.put(payload)
            self._last_published = now

