"""The viewer service: bus inputs → rendered, JPEG-encoded views for any number of clients.

Threads (none of them a Zenoh callback; callbacks only store bytes, see :mod:`intake`):

* ``viewer-decode`` decodes camera frames (JPEG → BGR) as they arrive;
* ``viewer-render`` decodes state / registration / health, then renders every *active*
  view whose inputs changed, at most ``fps`` times a second, and encodes it as JPEG.

A view is one distinct :class:`ViewSettings`: clients with equal settings share one
rendering. A view is active while somebody streams or requests it (``touch``), and for
``client_ttl_s`` after that; nothing is rendered when nobody looks.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from common.bus import Bus
from common.clusters import ClusterTracker, cluster_labels
from common.drops import DropCounter
from common.keys import Keys
from common.messages import CameraFrame, Health, Registration, SlamState, Truth
from services.visualiser.camera_model import CameraModel
from services.visualiser.intake import Queue, RateMeter, Slot, decode
from services.visualiser.recording import Recorder, recording_name
from services.visualiser.render import Renderer, side_by_side
from services.visualiser.series import SeriesStore
from services.visualiser.settings import ViewerConfig, ViewSettings
from services.visualiser.views import (
    DEFAULT_BOUNDS,
    Eye,
    Rendered,
    grow_bounds,
    placeholder,
    project_features,
)

log = logging.getLogger("slamlens.viewer")

#: the newest tracked pose is compared with the estimate of the state nearest its stamp,
#: if one is within this (s): the robot moves, so only the same instant is a fair comparison
#: (the camera's pose lags the newest state by its capture and detection time)
TRACKED_MATCH_S = 0.06


def _store(offer: Callable[[bytes], None]) -> Callable[[str, bytes], None]:
    """A bus callback that only stores the payload (no decoding on Zenoh's thread)."""

    def callback(_key: str, payload: bytes) -> None:
        offer(payload)

    return callback


@dataclass
class _Camera:
    """Inputs of one camera: raw slots and their decoded values."""

    name: str
    frame_slot: Slot
    registration_slot: Slot
    image: np.ndarray | None = None  #: decoded BGR frame
    frame: CameraFrame | None = None  #: its message (data kept for the status only)
    frame_received: float | None = None
    frame_version: int = 0
    registration: Registration | None = None
    registration_received: float | None = None
    registration_version: int = 0
    rate: RateMeter = field(default_factory=RateMeter)


@dataclass
class _View:
    """One distinct settings and its last picture."""

    settings: ViewSettings
    touched: float
    rendered: Rendered | None = None
    inputs: tuple[Any, ...] | None = None  #: inputs of ``rendered``
    pending: tuple[Any, ...] | None = None  #: inputs of the picture being encoded
    rate: RateMeter = field(default_factory=RateMeter)


class ViewerService:
    """Subscribe, decode, render per distinct settings, hand JPEGs to the web layer."""

    MAX_CLIENTS = 256  # settings of the most recently seen browser tabs
    BURST = 2.0  # render cycles the fps cap lets through back to back after a pause

    def __init__(self, bus: Bus, *, keys: Keys, config: ViewerConfig,
                 default_settings: ViewSettings | None = None) -> None:
        self.bus = bus
        self.keys = keys
        self.config = config
        self.default_settings = default_settings or ViewSettings()
        self.bad = DropCounter(log)  #: malformed input messages, by input
        self.failures = DropCounter(log)  #: states that could not be drawn or plotted
        self._stop = threading.Event()
        self._render_wake = threading.Event()
        self._decode_wake = threading.Event()
        self._lock = threading.RLock()
        self._state_slot = Slot("state", self._render_wake.set)
        # the camera-tracked robot pose (issue 3): drawn beside the estimate when current
        self._tracked_slot = Slot("tracked", lambda: None)
        self.tracked: Truth | None = None
        self._estimates: deque[tuple[float, np.ndarray]] = deque(maxlen=240)
        self._health_queue = Queue("health", self._render_wake.set)
        self._cameras = {c: _Camera(c, Slot(f"frame {c}", self._decode_wake.set),
                                    Slot(f"registration {c}", self._render_wake.set))
                         for c in config.cameras}
        self.state: SlamState | None = None
        self.state_received: float | None = None
        self._state_version = 0
        self.state_rate = RateMeter()
        self.health: Health | None = None
        self._health_version = 0
        self.violations: deque[dict[str, Any]] = deque(maxlen=200)
        self.series = SeriesStore(length=config.series_length,
                                  min_interval_s=config.series_interval_s,
                                  cluster=self._series_clusters())
        self._bounds: tuple[float, float, float, float] | None = None
        # one renderer for every view: it keeps the robot's path and the cluster identities
        # (per clustering setting), so switching a tab's mode keeps the path and colours
        self.renderer = Renderer()
        self._views: dict[ViewSettings, _View] = {}
        self._clients: OrderedDict[str, ViewSettings] = OrderedDict()
        self._listeners: list[Callable[[], None]] = []
        self._recorders: dict[str, Recorder] = {}
        self._eyes: tuple[Eye, ...] = ()
        self.render_ms: deque[float] = deque(maxlen=120)
        self._threads: list[threading.Thread] = []
        self._encode_queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=2)
        self.started = time.monotonic()

    def _series_clusters(self) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """Clusters of the plots' min/mean/max: the default settings' cut, stable ids."""
        tracker = ClusterTracker()
        threshold, count = (self.default_settings.cluster_threshold_m,
                            self.default_settings.cluster_count)

        def clusters(xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
            return tracker.update(ids, cluster_labels(xy, threshold_m=threshold, count=count))

        return clusters

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, fetch the latest state and registrations (late join), start threads."""
        k, robot = self.keys, self.config.robot
        self.bus.subscribe(k.state(robot), _store(self._state_slot.offer))
        self.bus.subscribe(k.health(robot), _store(self._health_queue.offer))
        self.bus.subscribe(k.tracked(robot), _store(self._tracked_slot.offer))
        for cam in self._cameras.values():
            self.bus.subscribe(k.frame(cam.name), _store(cam.frame_slot.offer))
            self.bus.subscribe(k.registration(cam.name, robot),
                               _store(cam.registration_slot.offer))
        self._late_join()
        for name, target in (("viewer-decode", self._decode_loop),
                             ("viewer-render", self._render_loop),
                             ("viewer-encode", self._encode_loop)):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info("viewer of robot %s, %s view%s", robot, self.config.resolved_view,
                 f" over {', '.join(self._cameras)}" if self._cameras else "")

    def _late_join(self) -> None:
        """Ask the estimator and the cameras for their latest (SPEC §7), so a viewer that
        joins late shows the current picture at once."""
        timeout = self.config.late_join_timeout_s
        if timeout <= 0:
            return
        wanted = [(self.keys.state(self.config.robot), self._state_slot)]
        wanted += [(self.keys.registration(c.name, self.config.robot), c.registration_slot)
                   for c in self._cameras.values()]
        for key, slot in wanted:
            try:
                replies = self.bus.get(key, timeout=timeout)
            except Exception as exc:  # a failed get must not stop the viewer
                log.warning("late-join get on %s failed: %s", key, exc)
                continue
            if replies:
                slot.offer_if_empty(replies[-1].payload)
        health_key = self.keys.health(self.config.robot)
        try:  # the monitor may answer too; its verdict is optional for the picture
            replies = self.bus.get(health_key, timeout=min(timeout, 0.5))
        except Exception as exc:
            log.debug("late-join get on %s failed: %s", health_key, exc)
            replies = []
        if replies and self._health_queue.received_count == 0:
            self._health_queue.offer(replies[-1].payload)

    def stop(self) -> None:
        self._stop.set()
        self._render_wake.set()
        self._decode_wake.set()
        for recorder in list(self._recorders.values()):
            recorder.stop()
        for thread in self._threads:
            thread.join(timeout=5.0)

    # -- listeners (the web layer) -------------------------------------------------
    def add_listener(self, listener: Callable[[], None]) -> None:
        """Called (on the encoding thread) after each new picture of any view."""
        self._listeners.append(listener)

    # -- clients and views ----------------------------------------------------------
    def settings_for(self, client: str | None) -> ViewSettings:
        if client is None:
            return self.default_settings
        with self._lock:
            settings = self._clients.get(client)
            if settings is None:
                settings = self._clients[client] = self.default_settings
                while len(self._clients) > self.MAX_CLIENTS:
                    self._clients.popitem(last=False)
            self._clients.move_to_end(client)
            return settings

    def update_settings(self, client: str, changes: Mapping[str, Any]) -> ViewSettings:
        """Apply web-page changes (strings, numbers, booleans); ConfigError if bad."""
        query = {k: (("true" if v else "false") if isinstance(v, bool) else
                     "" if v is None else str(v)) for k, v in changes.items()}
        with self._lock:
            settings = ViewSettings.from_query(query, base=self.settings_for(client))
            self._clients[client] = settings
        self.touch(settings)
        return settings

    def touch(self, settings: ViewSettings) -> None:
        """Keep rendering ``settings`` for the next ``client_ttl_s`` seconds."""
        now = time.monotonic()
        with self._lock:
            view = self._views.get(settings)
            if view is None:
                view = self._views[settings] = _View(settings, now)
                self._render_wake.set()
            view.touched = now

    def latest(self, settings: ViewSettings) -> Rendered | None:
        with self._lock:
            view = self._views.get(settings)
            return None if view is None else view.rendered

    def fresh(self, settings: ViewSettings) -> bool:
        """True when the view's picture reflects the newest inputs."""
        with self._lock:
            view = self._views.get(settings)
            return view is not None and view.rendered is not None and \
                view.inputs == self._inputs()

    # -- decoding -----------------------------------------------------------------
    def _decode_loop(self) -> None:
        # decode no faster than the render cap: a 60 Hz camera under a 30 fps cap would
        # otherwise spend half its decoding on frames nobody draws (latest wins meanwhile)
        min_interval = 0.9 / self.config.fps
        last = -float("inf")
        while not self._stop.is_set():
            self._decode_wake.wait(0.5)
            wait = last + min_interval - time.monotonic()
            if wait > 0:
                self._stop.wait(wait)
            self._decode_wake.clear()
            for cam in self._cameras.values():
                raw = cam.frame_slot.take()
                if raw is None:
                    continue
                last = time.monotonic()
                frame = decode(f"frame {cam.name}", raw, CameraFrame.from_bytes, self.bad)
                if frame is None:
                    continue
                try:
                    image = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
                except cv2.error:  # e.g. empty data
                    image = None
                if image is None or image.shape[:2] != (frame.height, frame.width):
                    got = "undecodable JPEG" if image is None else f"{image.shape[1]}×" \
                        f"{image.shape[0]} pixels"
                    self.bad.drop(f"frame {cam.name}", f"CameraFrame.data: expected a "
                                  f"{frame.width}×{frame.height} JPEG, got {got}")
                    continue
                with self._lock:
                    cam.image, cam.frame, cam.frame_received = image, frame, raw.received
                    cam.frame_version = raw.version
                cam.rate.tick()
                self._render_wake.set()

    def _ingest(self) -> None:
        """Decode whatever state, registration and health arrived since the last cycle."""
        now = time.monotonic()
        raw = self._state_slot.take()
        if raw is not None:
            # symmetry is the monitor's business: the viewer shows what the estimator sent
            state = decode("state", raw, lambda b: SlamState.from_bytes(
                b, check_symmetry=False), self.bad)
            if state is not None and state.robot != self.config.robot:
                self.bad.drop("state", f"SlamState.robot: expected {self.config.robot!r}, "
                              f"got {state.robot!r}")
            elif state is not None:
                with self._lock:
                    if self.state is not None and state.seq < self.state.seq:
                        self._bounds = None  # a new run: the map view starts over
                    self.state, self.state_received = state, raw.received
                    self._state_version = raw.version
                # the path remembers every state taken in, drawn or not: views render
                # only on demand, and a path started at the first render would be short
                self.renderer.track(state.robot, state.seq, state.pose[:2])
                with self._lock:
                    self._estimates.append((state.stamp, state.pose))
                self.state_rate.tick()
                try:
                    self.series.add_state(state, now=now)
                except Exception as exc:  # the plots are optional; the picture is not
                    self.failures.drop("plots", f"state seq {state.seq}: {exc!r}")
        raw_tracked = self._tracked_slot.take()
        if raw_tracked is not None:
            tracked = decode("tracked", raw_tracked, Truth.from_bytes, self.bad)
            if tracked is not None:
                with self._lock:
                    self.tracked = tracked
        for raw in self._health_queue.drain():
            health = decode("health", raw, Health.from_bytes, self.bad)
            if health is None:
                continue
            with self._lock:
                self.health, self._health_version = health, raw.version
                for v in health.violations:
                    self.violations.append({"seq": health.seq, "stamp": health.stamp,
                                            **v.to_dict()})
            self.series.add_health(health, now=now)
        for cam in self._cameras.values():
            raw = cam.registration_slot.take()
            if raw is None:
                continue
            reg = decode(f"registration {cam.name}", raw, Registration.from_bytes, self.bad)
            if reg is not None:
                with self._lock:
                    cam.registration, cam.registration_received = reg, raw.received
                    cam.registration_version = raw.version

    def _inputs(self) -> tuple[Any, ...]:
        """Signature of everything a picture depends on (besides its settings)."""
        return (self._state_version, self._health_version,
                tuple((c.frame_version, c.registration_version)
                      for c in self._cameras.values()), self._bounds)

    # -- rendering ------------------------------------------------------------------
    def _render_loop(self) -> None:
        # The fps cap is a token bucket (refilled at fps, holding BURST): on average at most
        # fps pictures per view set, but a camera's timing jitter is absorbed instead of
        # piling up behind a rigid 1/fps spacing (which drops frames at an equal input rate)
        rate, burst = self.config.fps, self.BURST
        tokens, refilled = burst, time.monotonic()
        while not self._stop.is_set():
            self._render_wake.wait(0.5)
            if self._stop.is_set():
                break
            now = time.monotonic()
            tokens, refilled = min(burst, tokens + (now - refilled) * rate), now
            if tokens < 1.0:  # newer inputs keep arriving meanwhile (latest wins)
                self._stop.wait((1.0 - tokens) / rate)
                now = time.monotonic()
                tokens, refilled = min(burst, tokens + (now - refilled) * rate), now
            self._render_wake.clear()
            try:
                self._ingest()
                if self._render_active():
                    tokens -= 1.0
            except Exception:  # a rendering bug must not kill the viewer
                log.exception("render cycle failed")

    def _active_views(self) -> list[_View]:
        now = time.monotonic()
        ttl = self.config.client_ttl_s
        with self._lock:
            for recorder in self._recorders.values():
                self.touch(recorder.settings())
            for key in [k for k, v in self._views.items() if now - v.touched > 12 * ttl]:
                del self._views[key]  # forget renderers nobody asked for in a while
            return [v for v in self._views.values() if now - v.touched <= ttl]

    def _render_active(self) -> bool:
        """Render every active view whose inputs changed; hand the pictures to encoding."""
        views = self._active_views()
        if not views:
            return False
        with self._lock:  # one consistent snapshot of the inputs and their versions
            state, health = self.state, self.health
            cams = [(c.name, c.registration, c.image) for c in self._cameras.values()]
            versions = (self._state_version, self._health_version,
                        tuple((c.frame_version, c.registration_version)
                              for c in self._cameras.values()))
        eyes = self._scene(state, cams)
        inputs = (*versions, self._bounds)
        produced = False
        for view in views:
            if view.rendered is not None and inputs in (view.inputs, view.pending):
                continue
            t0 = time.perf_counter()
            image = self._compose(view, eyes, state, health)
            image.setflags(write=False)
            view.pending = inputs
            # encoding runs on its own thread, overlapping the next render (throughput);
            # a full queue makes this thread wait: the encoder sets the pace then
            while not self._stop.is_set():
                try:
                    self._encode_queue.put((view, image, inputs, state, t0), timeout=0.5)
                    break
                except queue.Full:
                    continue
            produced = True
        return produced

    def _encode_loop(self) -> None:
        while not self._stop.is_set():
            try:
                view, image, inputs, state, t0 = self._encode_queue.get(timeout=0.5)
            except queue.Empty:
                continue
            ok, jpeg = cv2.imencode(".jpg", image,
                                    [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
            if not ok:
                log.error("JPEG encoding failed")
                continue
            with self._lock:
                rendered = Rendered(
                    version=(view.rendered.version + 1) if view.rendered else 1,
                    seq=None if state is None else state.seq,
                    stamp=None if state is None else state.stamp,
                    image=image, jpeg=jpeg.tobytes(), rendered_at=time.monotonic())
                view.rendered, view.inputs = rendered, inputs
            view.rate.tick()
            self.render_ms.append((time.perf_counter() - t0) * 1e3)
            for listener in list(self._listeners):
                try:
                    listener()
                except Exception:  # a broken listener must not stop the pictures
                    log.exception("viewer listener failed")

    def _scene(self, state: SlamState | None,
               cams: list[tuple[str, Registration | None, np.ndarray | None]]
               ) -> tuple[Eye, ...]:
        """The camera model and background picture of each eye (one, or two for stereo)."""
        view = self.config.resolved_view
        eyes: list[Eye] = []
        if cams and all(reg is not None for _, reg, _ in cams):
            for name, reg, image in cams:
                assert reg is not None
                model = CameraModel.from_registration(reg)
                if image is not None and image.shape[:2] != (reg.height, reg.width):
                    # frames of another size than calibrated: scale the intrinsics to them
                    model = model.resized(image.shape[1], image.shape[0])
                eyes.append(Eye(name, model, image, ""))
        elif view == "camera":
            name, _, image = cams[0]
            eyes.append(Eye(name, None, image,
                            f"waiting for the registration of camera {name} "
                            f"for robot {self.config.robot}"))
        else:
            if state is not None:
                with self._lock:
                    self._bounds = grow_bounds(self._bounds, state)
            bounds = self._bounds or DEFAULT_BOUNDS
            model = CameraModel.top_down(bounds_xy=bounds, width=self.config.map_width,
                                         height=self.config.map_height)
            if view == "stereo":
                left, right = model.stereo_pair(self.config.stereo_baseline_m)
                eyes += [Eye("map-left", left, None, ""), Eye("map-right", right, None, "")]
            else:
                eyes.append(Eye("map", model, None, ""))
        with self._lock:
            self._eyes = tuple(eyes)
        return self._eyes

    def _reference(self) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
        """(newest tracked pose, the estimate of the state nearest its stamp), if any."""
        with self._lock:
            tracked, estimates = self.tracked, list(self._estimates)
        if tracked is None or not estimates:
            return None, None
        stamp, pose = min(estimates, key=lambda e: abs(e[0] - tracked.stamp))
        if abs(stamp - tracked.stamp) > TRACKED_MATCH_S:
            return None, None
        return tracked.pose, pose

    def _compose(self, view: _View, eyes: tuple[Eye, ...], state: SlamState | None,
                 health: Health | None) -> np.ndarray:
        pictures = []
        reference, estimate = self._reference()
        for eye in eyes:
            if state is None or eye.camera is None:
                text = eye.note or f"waiting for the state of robot {self.config.robot}"
                pictures.append(placeholder(eye, text, view.settings))
            else:
                try:
                    pictures.append(self.renderer.render(
                        eye.image, state=state, camera=eye.camera, settings=view.settings,
                        health=health, reference_pose=reference,
                        reference_estimate=estimate))
                except Exception as exc:  # keep the picture flowing, say what went wrong
                    self.failures.drop("render", f"state seq {state.seq}: {exc!r}")
                    pictures.append(placeholder(
                        eye, f"cannot draw state seq {state.seq}: {type(exc).__name__}",
                        view.settings))
        if len(pictures) == 2:
            return side_by_side(pictures[0], pictures[1])
        return np.ascontiguousarray(pictures[0])

    # -- what the web layer asks ----------------------------------------------------
    def features(self, settings: ViewSettings) -> dict[str, Any]:
        """Feature ids, map positions and pixel positions in this view (click to select)."""
        with self._lock:
            state, eyes = self.state, self._eyes
        if state is None:
            return {"seq": None, "ids": [], "xy": [], "uv": [], "selected":
                    settings.selected_feature}
        return {"seq": state.seq, "ids": [int(i) for i in state.landmark_ids],
                "xy": [[float(x), float(y)] for x, y in state.landmarks],
                "uv": project_features(eyes, np.asarray(state.landmarks)),
                "selected": settings.selected_feature}

    def health_json(self) -> dict[str, Any]:
        with self._lock:
            health, recent = self.health, list(self.violations)
        latest = None
        if health is not None:
            latest = {"seq": health.seq, "stamp": health.stamp, "ok": health.ok,
                      "suspects": [int(s) for s in health.suspects],
                      "violations": [v.to_dict() for v in health.violations],
                      "statistics": dict(health.statistics)}
        return {"latest": latest, "recent": recent[::-1]}

    def series_json(self, settings: ViewSettings,
                    pairs: list[tuple[int, int]] | None = None) -> dict[str, Any]:
        if not pairs:
            with self._lock:
                flagged = [] if self.health is None else [
                    (v.ids[0], v.ids[1]) for v in self.health.violations
                    if v.kind == "pair" and len(v.ids) == 2]
            pairs = self.series.default_pairs(selected=settings.selected_feature,
                                              flagged=flagged)
        return self.series.to_json(pairs)

    def status(self) -> dict[str, Any]:
        now = time.monotonic()
        with self._lock:
            state, health = self.state, self.health
            cams = list(self._cameras.values())
            views = list(self._views.values())
        ttl = self.config.client_ttl_s
        active = [v for v in views if now - v.touched <= ttl]
        return {
            "robot": self.config.robot, "view": self.config.resolved_view,
            "camera": self.config.camera,
            "state": None if state is None else {
                "seq": state.seq, "stamp": state.stamp, "step": state.step, "n": state.n,
                "age_s": None if self.state_received is None else now - self.state_received,
                "rate_hz": self.state_rate.rate(now)},
            "cameras": [{
                "name": c.name,
                "frame": None if c.frame is None else {
                    "seq": c.frame.seq, "stamp": c.frame.stamp, "width": c.frame.width,
                    "height": c.frame.height, "rate_hz": c.rate.rate(now),
                    "age_s": None if c.frame_received is None else now - c.frame_received},
                "registration": None if c.registration is None else {
                    "status": c.registration.status, "stamp": c.registration.stamp,
                    "reprojection_error_px": c.registration.reprojection_error_px},
            } for c in cams],
            "health": None if health is None else {
                "seq": health.seq, "ok": health.ok, "violations": len(health.violations),
                "suspects": [int(s) for s in health.suspects]},
            "fps": max((v.rate.rate(now) for v in active), default=0.0),
            "render_ms_median": float(np.median(self.render_ms)) if self.render_ms else None,
            "views_active": len(active), "clients": len(self._clients),
            "bad_messages": dict(self.bad.counts),
            "failures": dict(self.failures.counts),
            "recording": sorted(self._recorders),
        }

    # -- recording ------------------------------------------------------------------
    def record_start(self, client: str) -> dict[str, Any]:
        with self._lock:
            if client in self._recorders:
                return self._recorders[client].info()

            def settings() -> ViewSettings:
                return self.settings_for(client)

            def source() -> np.ndarray | None:
                rendered = self.latest(settings())
                return None if rendered is None else rendered.image

            recorder = Recorder(directory=self.config.recordings_dir,
                                name=recording_name(self.config.robot, client,
                                                    self.config.record_codec),
                                fps=self.config.fps, codec=self.config.record_codec,
                                source=source, settings=settings)
            self._recorders[client] = recorder
        self.touch(settings())
        recorder.start()
        return recorder.info()

    def record_stop(self, client: str) -> dict[str, Any] | None:
        with self._lock:
            recorder = self._recorders.pop(client, None)
        if recorder is None:
            return None
        recorder.stop()
        return recorder.info()
