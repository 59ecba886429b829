"""The registration service's bus I/O: frames out, registration / tracked pose / camera pose out.

Per camera (two for stereo) a :class:`CameraPipeline` runs two threads:

* capture: read the source at its rate, JPEG-encode, publish ``CameraFrame`` latest-wins
  (congestion *drop*: a slow subscriber gets the newest frame and never slows the camera),
  and leave the raw image in a keep-newest slot (:class:`~slamlens.common.latest.Latest`);
* processing: take the newest image (skipping any it had no time for), detect markers,
  feed the :class:`~slamlens.services.registration.tracking.Registrar`, publish ``Registration``
  (also answered to ``get``), the tracked robot pose and, head-mounted, ``CameraPose``.

Control: a :class:`~slamlens.common.messages.CameraControl` (``{"schema": 1, "command":
"reregister", "robot": R, "requester": …}``) put on ``keys.camera_control(camera)``, or
sent as the payload of a Zenoh query on that key (what a viewer may do under ``--secure``:
it may query, not publish), re-registers from the next frames. A re-registration that would
move the map frame by more than ``max_reregister_move_m`` / ``max_reregister_turn_deg``
while the robot is not at its map origin is refused, with the reason, and the old one kept.

Maps (SPEC §7a): the service watches the robot's state header (epoch, origin_stamp,
pose). The first map it sees keeps the registration made while the robot stood still; a
new map (a new epoch) is registered from the remembered frame nearest its
``origin_stamp`` — where the robot stood when that map started. Every Registration says
its ``epoch``, ``reason`` and how far it moved the frame. Only the header is read of a
state, and a state is copied out of Zenoh's buffer only when its header is read: at most
every :data:`STATE_HEAD_EVERY_S` (a 32 MB state at n = 1000 costs ~20 ms of CPU to copy,
and the estimator publishes tens a second; docs/registration.md, "Maps").
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import msgpack
import numpy as np

from slamlens.common.arrays import decode_array
from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError, SlamlensError
from slamlens.common.geometry import invert_T
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.messages import (
    CameraControl,
    CameraFrame,
    CameraPose,
    Registration,
    Truth,
    peek_fields,
)
from slamlens.services.registration.board import MarkerBoard, camera_pose_from_board
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.markers import MarkerDetector, WindowedDetector
from slamlens.services.registration.sources import FrameSource, SourceEnded, SyntheticSource
from slamlens.services.registration.tracking import (
    STATUS_WAITING,
    FrameResult,
    Registrar,
    frame_change,
)

log = logging.getLogger(__name__)

TRACKER_TIMEOUT_S = 1.0  #: an external CameraPose older than this is not used
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
    detector: MarkerDetector | WindowedDetector
    registrar: Registrar
    board: MarkerBoard | None = None
    tracker_pose: Callable[[], np.ndarray | None] | None = None


@dataclasses.dataclass
class PipelineStats:
    """Counters of one camera (read by tests, benchmarks and the status log)."""

    captured: int = 0
    published: int = 0
    processed: int = 0
    skipped: int = 0  #: frames the processing thread had no time for (replaced unseen)
    registrations: int = 0
    tracked: int = 0
    camera_poses: int = 0
    size_mismatches: int = 0  #: frames of another size than the calibration's
    refused: int = 0  #: re-registration requests refused (they would move the frame too far)
    ended: bool = False
    publish_times: collections.deque = dataclasses.field(
        default_factory=lambda: collections.deque(maxlen=600))


def _window_counts(detector: MarkerDetector | WindowedDetector) -> dict[str, int]:
    """How a camera's frames were detected: over the whole image, in windows only, and
    the windows that lost a marker (detected whole again); empty if it never windows."""
    if not isinstance(detector, WindowedDetector):
        return {}
    return {"detected_whole": detector.full_frames, "detected_in_windows":
            detector.window_frames, "window_fallbacks": detector.fallbacks}


class CameraPipeline:
    """Capture, publish and register one camera."""

    def __init__(self, bus: Bus, keys: Keys, *, settings: CameraSettings,
                 parts: CameraParts) -> None:
        self.settings = settings
        self.parts = parts
        self.camera, self.robot = settings.camera, settings.robot
        self.stats = PipelineStats()
        self.read_errors = DropCounter(log, burst=1)  #: failed reads of the source
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
        self._frames: Latest[tuple[int, float, np.ndarray]] = Latest()
        self._latest_registration: Registration | None = None
        self._latest_bytes: bytes | None = None
        self._last_status = ""
        self._last_published = 0.0
        camera, robot = self.camera, self.robot
        self._frame_pub = bus.publisher(keys.frame(camera), latest_wins=True)
        self._reg_pub = bus.publisher(keys.registration(camera, robot))
        self._tracked_pub = bus.publisher(keys.tracked_by(camera, robot), latest_wins=True)
        self._pose_pub = bus.publisher(keys.camera_pose(camera), latest_wins=True)
        bus.serve_latest(keys.registration(camera, robot), lambda: self._latest_bytes)
        bus.declare_alive(keys.camera_alive(camera))
        self._threads = [threading.Thread(target=self._capture_loop, name=f"capture-{camera}",
                                          daemon=True),
                         threading.Thread(target=self._process_loop, name=f"register-{camera}",
                                          daemon=True)]

    @property
    def source(self) -> FrameSource:
        return self.parts.source

    @property
    def registrar(self) -> Registrar:
        return self.parts.registrar

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
        """The registrar's last status ("" before the first frame)."""
        return self._last_status

    def publish_fps(self, window_s: float = 2.0) -> float:
        """Frames published per second over the last ``window_s`` seconds."""
        now = time.monotonic()
        recent = [t for t in list(self.stats.publish_times) if now - t <= window_s]
        return len(recent) / window_s

    # -- capture thread -------------------------------------------------------------
    def _capture_loop(self) -> None:
        period = 1.0 / self.settings.fps
        next_t = time.monotonic()
        seq = 0
        while not self._stop.is_set():
            if not getattr(self.source, "live", False):
                delay = next_t - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    break
            try:
                frame = self.source.read()
            except SourceEnded as exc:
                self.stats.ended = True
                log.warning("camera %s: %s; no more frames, still serving the last "
                            "registration", self.camera, exc)
                return
            except Exception as exc:  # an unexpected source failure: count, keep going
                self.read_errors.drop(f"frame of camera {self.camera}", f"reading failed: {exc}")
                self._stop.wait(period)
                continue
            now = time.monotonic()
            if frame is None:
                self._stop.wait(min(period, 0.02))
                continue
            # keep the cadence, but after a stall restart it instead of bursting to catch up
            next_t = next_t + period if next_t + period > now - period else now + period
            stamp, image = frame
            self.stats.captured += 1
            seq += 1
            self._publish_frame(seq, stamp, image)
            self._frames.put((seq, stamp, image))

    def _publish_frame(self, seq: int, stamp: float, image: np.ndarray) -> None:
        ok, jpeg = cv2.imencode(".jpg", image,
                                [cv2.IMWRITE_JPEG_QUALITY, self.settings.jpeg_quality])
        if not ok:
            log.error("camera %s: JPEG encoding of frame %d failed", self.camera, seq)
            return
        h, w = image.shape[:2]
        msg = CameraFrame(camera=self.camera, seq=seq, stamp=float(stamp), encoding="jpeg",
                          width=w, height=h, data=jpeg.tobytes())
        self._frame_pub.put(msg.to_bytes())
        self.stats.published += 1
        self.stats.publish_times.append(time.monotonic())

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
            reg = dataclasses.replace(self._latest_registration, status=result.status,
                                      epoch=self.epoch, reason=self._reason)
        else:
            return
        due = (result.registered_now or status_changed or self.settings.moving
               or now - self._last_published >= self.settings.registration_period_s)
        payload = reg.to_bytes()
        self._latest_registration, self._latest_bytes = reg, payload
        if due:
            self._reg_pub.put(payload)
            self._last_published = now


class TrackerPoses:
    """Latest CameraPose per camera from an external tracker (head-mounted, "tracker")."""

    def __init__(self, *, timeout_s: float = TRACKER_TIMEOUT_S,
                 drops: DropCounter | None = None) -> None:
        self.timeout_s = timeout_s
        self.drops = drops or DropCounter(log)  #: malformed CameraPose messages
        self._poses: dict[str, tuple[float, np.ndarray]] = {}
        self._lock = threading.Lock()

    def on_camera_pose(self, key: str, payload: bytes) -> None:
        try:
            pose = CameraPose.from_bytes(payload)
        except MessageError as exc:
            self.drops.drop(CameraPose.TYPE, f"on {key}: {exc}")
            return
        with self._lock:
            self._poses[pose.camera] = (time.monotonic(), np.array(pose.T_world_from_camera))

    def pose_of(self, camera: str) -> np.ndarray | None:
        """The latest pose of ``camera`` if received within ``timeout_s``."""
        with self._lock:
            entry = self._poses.get(camera)
        if entry is None or time.monotonic() - entry[0] > self.timeout_s:
            return None
        return entry[1]


class RegistrationService:
    """The cameras of one ``slamlens registration`` process and their subscriptions."""

    def __init__(self, bus: Bus, keys: Keys, *, robot: str, base_camera: str,
                 pipelines: Sequence[CameraPipeline],
                 synthetic_sources: Sequence[SyntheticSource] = (),
                 tracker: TrackerPoses | None = None) -> None:
        self.bus, self.keys = bus, keys
        self.robot = robot
        self.pipelines = list(pipelines)
        self.synthetic_sources = list(synthetic_sources)
        self.tracker = tracker
        self.drops = DropCounter(log)  #: malformed Truth and CameraControl messages
        if self.synthetic_sources:
            bus.subscribe(keys.truth(robot), self._on_truth)
        bus.subscribe_lazy(keys.state(robot), self._on_state)
        names = {p.camera for p in self.pipelines} | {base_camera}
        for name in sorted(names):
            bus.subscribe(keys.camera_control(name), self._on_control)
            bus.answer(keys.camera_control(name), self._on_control_query)
        if tracker is not None:
            for p in self.pipelines:
                bus.subscribe(keys.camera_pose(p.camera), tracker.on_camera_pose)

    # -- subscriptions (zenoh threads: decode, store, return) ---------------------------
    def _on_truth(self, key: str, payload: bytes) -> None:
        try:
            truth = Truth.from_bytes(payload)
        except MessageError as exc:
            self.drops.drop(Truth.TYPE, f"on {key}: {exc}")
            return
        for source in self.synthetic_sources:
            source.set_truth(truth)

    def _on_state(self, key: str, fetch: Callable[[], bytes]) -> None:
        for p in self.pipelines:
            p.offer_state(fetch)

    def _on_control(self, key: str, payload: bytes) -> None:
        self._control(key, payload)

    def _control(self, key: str, payload: bytes) -> str:
        """A re-registration request; what became of it, in words."""
        try:
            request = CameraControl.from_bytes(payload)
        except MessageError as exc:
            self.drops.drop(CameraControl.TYPE, f"on {key}: {exc}")
            return f"refused: {exc}"
        if request.robot is not None and request.robot != self.robot:
            log.debug("reregister for robot %s ignored (serving %s)", request.robot, self.robot)
            return f"ignored: this camera service registers robot {self.robot}"
        camera = self.keys.camera_of(key)
        taken = False
        for p in self.pipelines:  # a stereo pair also obeys its base name
            if camera in (p.camera, p.camera.rsplit("-", 1)[0]):
                p.request_reregister(request.requester or "")
                taken = True
        return "accepted: re-registering from the next frames" if taken else "no such camera"

    def _on_control_query(self, key: str, payload: bytes | None, parameters: str) -> bytes:
        """The same request as a Zenoh query (a viewer may query but not publish)."""
        answer = self._control(key, payload or b"")
        return msgpack.packb({"schema": 1, "answer": answer}, use_bin_type=True)

    # -- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        for p in self.pipelines:
            p.start()
        threading.Thread(target=self._late_join, name="registration-late-join",
                         daemon=True).start()

    def _late_join(self) -> None:
        """Ask for the robot's current state: which map (epoch) the camera registers for,
        even if the estimator published nothing since this service started."""
        try:
            replies = self.bus.get(self.keys.state(self.robot), timeout=2.0)
        except Exception as exc:  # the session closing under us at shutdown
            log.debug("late join of the state failed: %s", exc)
            return
        for reply in replies[:1]:
            self._on_state(reply.key, functools.partial(bytes, reply.payload))

    def stop(self) -> None:
        for p in self.pipelines:
            p.stop()

    def summary(self) -> dict[str, Any]:
        """What the service did (its final line)."""
        return {"cameras": {p.camera: {
            "frames": p.stats.published, "registrations": p.stats.registrations,
            "refused": p.stats.refused, "tracked": p.stats.tracked, "epoch": p.epoch,
            **_window_counts(p.parts.detector),
            "status": p.status} for p in self.pipelines},
            "dropped": self.drops.total + sum(p.read_errors.total for p in self.pipelines)
            + (self.tracker.drops.total if self.tracker is not None else 0)}

    def run(self, stop: threading.Event, *, status_period_s: float = 10.0) -> None:
        """Run until ``stop`` is set, logging a status line every ``status_period_s``."""
        self.start()
        try:
            while not stop.wait(status_period_s):
                for p in self.pipelines:
                    s = p.stats
                    log.info("camera %s: %.1f fps published, %d processed, %d skipped, "
                             "status %s", p.camera, p.publish_fps(), s.processed, s.skipped,
                             p.status or "starting")
        finally:
            self.stop()
