"""The registration service's bus I/O: frames out, registration / tracked pose / camera pose out.

Per camera (two for stereo) a :class:`CameraPipeline` runs two threads:

* capture: read the source at its rate, JPEG-encode, publish ``CameraFrame`` latest-wins
  (congestion *drop*: a slow subscriber gets the newest frame and never slows the camera),
  and leave the raw image in a one-slot mailbox;
* processing: take the newest image (skipping any it had no time for), detect markers,
  feed the :class:`~services.registration.tracking.Registrar`, publish ``Registration``
  (also answered to ``get``), the tracked robot pose and, head-mounted, ``CameraPose``.

Control: a msgpack map ``{"schema": 1, "command": "reregister", "robot": R}`` on
``keys.camera_control(camera)`` re-registers from the next frames ("robot" optional).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import msgpack
import numpy as np

from common.bus import Bus
from common.errors import MessageError, SlamlensError
from common.keys import Keys
from common.messages import CameraFrame, CameraPose, Registration, Truth
from services.registration.board import MarkerBoard, camera_pose_from_board
from services.registration.calibration import CameraCalibration
from services.registration.markers import MarkerDetector
from services.registration.sources import FrameSource, SourceEnded, SyntheticSource
from services.registration.tracking import (
    STATUS_WAITING,
    FrameResult,
    Registrar,
)

log = logging.getLogger(__name__)

TRACKER_TIMEOUT_S = 1.0  #: an external CameraPose older than this is not used


class _Mailbox:
    """One slot holding the newest item: a put replaces what was not taken yet."""

    def __init__(self) -> None:
        self._item: Any = None
        self._cond = threading.Condition()
        self.replaced = 0

    def put(self, item: Any) -> None:
        with self._cond:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout: float) -> Any:
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item


@dataclasses.dataclass
class PipelineStats:
    """Counters of one camera (read by tests, benchmarks and the status log)."""

    captured: int = 0
    published: int = 0
    processed: int = 0
    skipped: int = 0  #: frames the processing thread had no time for
    registrations: int = 0
    tracked: int = 0
    camera_poses: int = 0
    read_errors: int = 0
    size_mismatches: int = 0  #: frames of another size than the calibration's
    ended: bool = False
    publish_times: collections.deque = dataclasses.field(
        default_factory=lambda: collections.deque(maxlen=600))


class CameraPipeline:
    """Capture, publish and register one camera."""

    def __init__(self, bus: Bus, keys: Keys, *, camera: str, robot: str, source: FrameSource,
                 calib: CameraCalibration, detector: MarkerDetector, registrar: Registrar,
                 fps: float, jpeg_quality: int = 80, moving: bool = False,
                 board: MarkerBoard | None = None,
                 tracker_pose: Callable[[], np.ndarray | None] | None = None,
                 publish_tracked: bool = True, registration_period_s: float = 1.0) -> None:
        self.bus, self.keys = bus, keys
        self.camera, self.robot = camera, robot
        self.source = source
        self.calib = calib
        self.detector = detector
        self.registrar = registrar
        self.fps = fps
        self.jpeg_quality = jpeg_quality
        self.moving = moving
        self.board = board
        self.tracker_pose = tracker_pose
        self.publish_tracked = publish_tracked
        self.registration_period_s = registration_period_s
        self.stats = PipelineStats()
        self._stop = threading.Event()
        self._reregister = threading.Event()
        self._mailbox = _Mailbox()
        self._latest_registration: Registration | None = None
        self._latest_bytes: bytes | None = None
        self._last_status = ""
        self._last_published = 0.0
        self._frame_pub = bus.publisher(keys.frame(camera), latest_wins=True)
        self._reg_pub = bus.publisher(keys.registration(camera, robot))
        self._tracked_pub = bus.publisher(keys.tracked(robot), latest_wins=True)
        self._pose_pub = bus.publisher(keys.camera_pose(camera), latest_wins=True)
        bus.serve_latest(keys.registration(camera, robot), lambda: self._latest_bytes)
        bus.declare_alive(keys.camera_alive(camera))
        self._threads = [threading.Thread(target=self._capture_loop, name=f"capture-{camera}",
                                          daemon=True),
                         threading.Thread(target=self._process_loop, name=f"register-{camera}",
                                          daemon=True)]

    # -- lifecycle ----------------------------------------------------------------
    def start(self) -> None:
        for t in self._threads:
            t.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout)
        self.source.close()

    def request_reregister(self) -> None:
        self._reregister.set()

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
        period = 1.0 / self.fps
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
                self.stats.read_errors += 1
                if self.stats.read_errors == 1 or self.stats.read_errors % 100 == 0:
                    log.error("camera %s: reading a frame failed (%d so far): %s",
                              self.camera, self.stats.read_errors, exc)
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
            self._mailbox.put((seq, stamp, image))

    def _publish_frame(self, seq: int, stamp: float, image: np.ndarray) -> None:
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
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
        last_seq = 0
        finished = False
        while not self._stop.is_set():
            item = self._mailbox.take(timeout=0.1)
            if item is None:
                if self.stats.ended and not finished:
                    finished = True  # a short file: register from the frames it had
                    self._finish()
                continue
            seq, stamp, image = item
            if last_seq and seq > last_seq + 1:
                self.stats.skipped += seq - last_seq - 1
            last_seq = seq
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
            h, w = self.calib.height, self.calib.width
            self._publish_registration(result, w, h)

    def _anchor_pose(self, detections: Sequence[Any], stamp: float) -> np.ndarray | None:
        """T_anchor_from_camera of this frame (identity for a fixed camera)."""
        if not self.moving:
            return np.eye(4)
        if self.tracker_pose is not None:
            return self.tracker_pose()
        if self.board is None:
            return None
        found = camera_pose_from_board(detections, self.board, self.calib)
        if found is None:
            return None
        T_world_from_camera, _rms, _n = found
        self._pose_pub.put(CameraPose(camera=self.camera, stamp=float(stamp),
                                      T_world_from_camera=T_world_from_camera).to_bytes())
        self.stats.camera_poses += 1
        return T_world_from_camera

    def _process(self, stamp: float, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        if (w, h) != (self.calib.width, self.calib.height):
            # the intrinsics would be wrong for this frame: publish it, never register on it
            self.stats.size_mismatches += 1
            if self.stats.size_mismatches == 1:
                log.error("camera %s: frames are %dx%d but the calibration is for %dx%d; "
                          "not registering", self.camera, w, h, self.calib.width,
                          self.calib.height)
            return
        if self._reregister.is_set():
            self._reregister.clear()
            self.registrar.reset()
            log.info("camera %s: re-registering robot %s from the next frames",
                     self.camera, self.robot)
        detections = self.detector.detect(image)
        T_anchor = self._anchor_pose(detections, stamp)
        result = self.registrar.observe(stamp, detections, T_anchor_from_camera=T_anchor)
        if result.registered_now:
            self.stats.registrations += 1
            log.info("camera %s: robot %s registered (reprojection error %.3f px)",
                     self.camera, self.robot, self.registrar.reprojection_error_px)
        self._publish_registration(result, image.shape[1], image.shape[0])
        if result.tracked_pose is not None and self.publish_tracked:
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
            stamp = result.stamp if self.moving or self.registrar.stamp is None \
                else self.registrar.stamp
            reg = Registration(
                camera=self.camera, robot=self.robot, stamp=float(stamp),
                K=self.calib.K, dist=self.calib.dist, width=width, height=height,
                T_camera_from_map=result.T_camera_from_map,
                reprojection_error_px=self.registrar.reprojection_error_px,
                status=result.status)
        elif self._latest_registration is not None:
            reg = dataclasses.replace(self._latest_registration, status=result.status)
        else:
            return
        due = (result.registered_now or status_changed or self.moving
               or now - self._last_published >= self.registration_period_s)
        payload = reg.to_bytes()
        self._latest_registration, self._latest_bytes = reg, payload
        if due:
            self._reg_pub.put(payload)
            self._last_published = now


class TrackerPoses:
    """Latest CameraPose per camera from an external tracker (head-mounted, "tracker")."""

    def __init__(self, *, timeout_s: float = TRACKER_TIMEOUT_S) -> None:
        self.timeout_s = timeout_s
        self.bad = 0
        self._poses: dict[str, tuple[float, np.ndarray]] = {}
        self._lock = threading.Lock()

    def on_camera_pose(self, key: str, payload: bytes) -> None:
        try:
            pose = CameraPose.from_bytes(payload)
        except MessageError as exc:
            self.bad += 1
            log.warning("dropped a bad CameraPose on %s (%d so far): %s", key, self.bad, exc)
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
        self.bad_truth = 0
        self.bad_control = 0
        if self.synthetic_sources:
            bus.subscribe(keys.truth(robot), self._on_truth)
        names = {p.camera for p in self.pipelines} | {base_camera}
        for name in sorted(names):
            bus.subscribe(keys.camera_control(name), self._on_control)
        if tracker is not None:
            for p in self.pipelines:
                bus.subscribe(keys.camera_pose(p.camera), tracker.on_camera_pose)

    # -- subscriptions (zenoh threads: decode, store, return) ---------------------------
    def _on_truth(self, key: str, payload: bytes) -> None:
        try:
            truth = Truth.from_bytes(payload)
        except MessageError as exc:
            self.bad_truth += 1
            if self.bad_truth == 1 or self.bad_truth % 100 == 0:
                log.warning("dropped a bad Truth on %s (%d so far): %s", key, self.bad_truth, exc)
            return
        for source in self.synthetic_sources:
            source.set_truth(truth)

    def _on_control(self, key: str, payload: bytes) -> None:
        try:
            msg = msgpack.unpackb(payload, raw=False)
            if not isinstance(msg, dict) or msg.get("schema") != 1:
                raise ValueError("expected a msgpack map with schema 1")
            if msg.get("command") != "reregister":
                raise ValueError(f"unknown command {msg.get('command')!r}; known: reregister")
            robot = msg.get("robot")
            if robot is not None and not isinstance(robot, str):
                raise ValueError(f"robot must be a string, got {robot!r}")
        except Exception as exc:  # msgpack raises several unrelated types
            self.bad_control += 1
            log.warning("dropped a bad control message on %s (%d so far): %s",
                        key, self.bad_control, exc)
            return
        if robot is not None and robot != self.robot:
            log.debug("reregister for robot %s ignored (serving %s)", robot, self.robot)
            return
        camera = key.rsplit("/", 2)[-2]
        for p in self.pipelines:
            if camera in (p.camera, p.camera.rsplit("-", 1)[0]):
                p.request_reregister()

    # -- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        for p in self.pipelines:
            p.start()

    def stop(self) -> None:
        for p in self.pipelines:
            p.stop()

    def run(self, stop: threading.Event, *, status_period_s: float = 10.0) -> None:
        """Run until ``stop`` is set, logging a status line every ``status_period_s``."""
        self.start()
        try:
            while not stop.wait(status_period_s):
                for p in self.pipelines:
                    s = p.stats
                    log.info("camera %s: %.1f fps published, %d processed, %d skipped, "
                             "status %s", p.camera, p.publish_fps(), s.processed, s.skipped,
                             p._last_status or "starting")
        finally:
            self.stop()
