"""The registration service's bus I/O: its cameras' pipelines and their subscriptions.

:class:`RegistrationService` runs the :class:`~slamlens.services.registration.pipeline.
CameraPipeline` of each camera of one ``slamlens registration`` process (one, or a stereo
pair; with ``--source browser`` one per browser that sends frames:
:mod:`~slamlens.services.registration.browser`) and answers what concerns them all: the
robot's truth for the synthetic camera, its state (which map), re-registration requests
(``CameraControl``, put or queried) and an external tracker's ``CameraPose``. Zenoh
callbacks only decode and store.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import msgpack
import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import CameraControl, CameraPose, Truth
from slamlens.services.registration.browser import BrowserCameras
from slamlens.services.registration.markers import AnyDetector, WindowedDetector
from slamlens.services.registration.pipeline import CameraPipeline
from slamlens.services.registration.sources import SyntheticSource

log = logging.getLogger(__name__)

TRACKER_TIMEOUT_S = 1.0  #: an external CameraPose older than this is not used


def _window_counts(detector: AnyDetector | WindowedDetector) -> dict[str, int]:
    """How a camera's frames were detected: over the whole image, in windows only, and
    the windows that lost a marker (detected whole again); empty if it never windows."""
    if not isinstance(detector, WindowedDetector):
        return {}
    return {"detected_whole": detector.full_frames, "detected_in_windows":
            detector.window_frames, "window_fallbacks": detector.fallbacks}


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
                 tracker: TrackerPoses | None = None,
                 browser: Callable[[RegistrationService], BrowserCameras] | None = None
                 ) -> None:
        self.bus, self.keys = bus, keys
        self.robot = robot
        self._lock = threading.Lock()
        self._pipelines = list(pipelines)
        self.synthetic_sources = list(synthetic_sources)
        self.tracker = tracker
        self.drops = DropCounter(log)  #: malformed Truth and CameraControl messages
        #: the browser cameras (``--source browser``): pipelines added as they come
        self.browser = None if browser is None else browser(self)
        if self.synthetic_sources:
            bus.subscribe(keys.truth(robot), self._on_truth)
        bus.subscribe_lazy(keys.state(robot), self._on_state)
        if self.browser is not None:  # their names are known when they come
            bus.subscribe(keys.any_camera_control(), self._on_control)
            bus.answer(keys.any_camera_control(), self._on_control_query)
        names = {p.camera for p in self._pipelines} | {base_camera}
        for name in sorted(names) if self.browser is None else ():
            bus.subscribe(keys.camera_control(name), self._on_control)
            bus.answer(keys.camera_control(name), self._on_control_query)
        if tracker is not None:
            for p in self._pipelines:
                bus.subscribe(keys.camera_pose(p.camera), tracker.on_camera_pose)

    @property
    def pipelines(self) -> list[CameraPipeline]:
        """The cameras' pipelines now (browser cameras come and go)."""
        with self._lock:
            return list(self._pipelines)

    def add_pipeline(self, pipeline: CameraPipeline) -> None:
        with self._lock:
            self._pipelines.append(pipeline)

    def remove_pipeline(self, pipeline: CameraPipeline) -> None:
        with self._lock:
            if pipeline in self._pipelines:
                self._pipelines.remove(pipeline)

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

    def _control(self, key: str, payload: bytes) -> str | None:
        """A re-registration request; what became of it, in words (None: a request to a
        browser camera this service does not serve, left to the service that does)."""
        camera = self.keys.camera_of(key)
        if self.browser is not None and (camera is None or not self.browser.serves(camera)):
            return None
        try:
            request = CameraControl.from_bytes(payload)
        except MessageError as exc:
            self.drops.drop(CameraControl.TYPE, f"on {key}: {exc}")
            return f"refused: {exc}"
        if request.robot is not None and request.robot != self.robot:
            log.debug("reregister for robot %s ignored (serving %s)", request.robot, self.robot)
            return f"ignored: this camera service registers robot {self.robot}"
        taken = False
        for p in self.pipelines:  # a stereo pair also obeys its base name
            if camera in (p.camera, p.camera.rsplit("-", 1)[0]):
                p.request_reregister(request.requester or "")
                taken = True
        return "accepted: re-registering from the next frames" if taken else "no such camera"

    def _on_control_query(self, key: str, payload: bytes | None,
                          parameters: str) -> bytes | None:
        """The same request as a Zenoh query (a viewer may query but not publish)."""
        answer = self._control(key, payload or b"")
        if answer is None:
            return None
        return msgpack.packb({"schema": 1, "answer": answer}, use_bin_type=True)

    # -- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        for p in self.pipelines:
            p.start()
        if self.browser is not None:
            self.browser.start()
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
        if self.browser is not None:
            self.browser.stop()
        for p in self.pipelines:
            p.stop()

    def summary(self) -> dict[str, Any]:
        """What the service did (its final line)."""
        browser = self.browser
        extra = {} if browser is None else {"browser": {
            "joined": browser.joined, "left": browser.left, "cameras": browser.cameras,
            "refused": dict(browser.drops.counts)}}
        return {**extra, "cameras": {p.camera: {
            "frames": p.stats.published, "registrations": p.stats.registrations,
            "refused": p.stats.refused, "tracked": p.stats.tracked, "epoch": p.epoch,
            **_window_counts(p.parts.detector),
            "status": p.status} for p in self.pipelines},
            "dropped": self.drops.total + sum(p.read_errors.total for p in self.pipelines)
            + (self.tracker.drops.total if self.tracker is not None else 0)
            + (0 if browser is None else browser.drops.total)}

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
