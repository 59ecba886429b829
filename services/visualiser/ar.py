"""The ``/ar`` page's cameras: a browser's frames to registration, and back with the overlay.

A page (a phone's or a headset's browser, docs/viewer.md "AR on a phone") opens a
websocket as camera ``C`` (``--ar-camera`` or ``--ar-camera``-…) for robot ``R`` and sends
the JPEG frames of its rear camera. For each, :class:`ArSession`:

1. checks it (size in bytes, the JPEG header's size — read without decoding —, the rate):
   a refused frame is one counted line (:class:`ArRefused`);
2. publishes it as a ``CameraFrame`` on ``slamlens/camera/C/capture`` (latest wins), where
   ``slamlens registration --source browser`` registers it like any other camera — so a
   recorder, another viewer or the monitor see the phone's camera too;
3. keeps it (the last few) until the registration of that very frame comes back on
   ``slamlens/camera/C/registration/R`` (its ``stamp`` is the frame's), then draws R's
   newest state over it through that registration — the renderer of the main view, under
   the page's own settings — and sends the picture back. A frame whose registration
   does not come (not registered yet, the board out of view, a newer frame registered
   first, nothing within ``wait_s``) goes back as it came, with a note saying why.

Drawing runs on the session's own thread (``viewer-ar-C``), never on the web server's loop
or a Zenoh thread (the registration callback only stores). A session that ends (the page
closed) stops its thread and releases its publisher; the registration service releases the
camera when its frames stop (``--browser-idle-s``).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import cv2
import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError, MessageError, SlamlensError
from slamlens.common.jpeg import JpegError, jpeg_size
from slamlens.common.keys import Keys, check_name
from slamlens.common.messages import CameraFrame, Registration
from slamlens.services.visualiser.api import ViewerApi
from slamlens.services.visualiser.settings import ViewSettings

log = logging.getLogger("slamlens.viewer.ar")

KEPT_FRAMES = 8  #: frames a session keeps waiting for their registration
KEPT_REGISTRATIONS = 16  #: registrations waiting for the session's thread
MAX_CLIENTS = 256  #: AR pages whose settings are remembered
POSE_LOST = "camera pose lost"  #: a moving camera's Registration.status without a pose


class ArRefused(SlamlensError):
    """A frame or a camera the AR page asked for and does not get (``kind`` says which)."""

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind


@dataclasses.dataclass(frozen=True)
class ArLimits:
    """What one AR page may send (ViewerConfig's ``ar_*`` and ``max_ar_*`` settings)."""

    max_cameras: int = 4
    max_frame_bytes: int = 2 << 20
    max_frame_pixels: int = 8_294_400
    max_fps: float = 30.0
    wait_s: float = 0.5
    jpeg_quality: int = 80


@dataclasses.dataclass(frozen=True, eq=False)
class ArResult:
    """One frame answered: what the page shows (a JSON header, then the JPEG)."""

    header: dict[str, Any]
    jpeg: bytes


@dataclasses.dataclass(eq=False)
class _Sent:
    seq: int
    stamp: float  #: the frame's stamp on the bus (wall clock at receipt, unique)
    jpeg: bytes
    received: float  #: time.monotonic() at receipt
    tag: Any  #: what the page said of it (echoed back)
    #: the decoded picture, made while its registration is on its way (None: not yet, or
    #: the JPEG does not decode — then ``undecodable``)
    image: np.ndarray | None = None
    undecodable: bool = False


class ArSession:
    """One page's camera (module docstring)."""

    def __init__(self, hub: ArHub, *, client: str, camera: str, robot: str,
                 publisher: Any, deliver: Callable[[ArResult], None]) -> None:
        self.hub, self.client, self.camera, self.robot = hub, client, camera, robot
        self._publisher = publisher
        self._deliver = deliver
        self._lock = threading.Lock()
        self._frames: collections.deque[_Sent] = collections.deque()
        self._regs: collections.deque[tuple[bytes, float]] = collections.deque(
            maxlen=KEPT_REGISTRATIONS)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._tokens, self._refilled = 2.0, time.monotonic()
        self._seq = 0
        self._last_stamp = 0.0
        self.status = ""  #: the newest registration's status ("" before any)
        self.counts: collections.Counter[str] = collections.Counter()
        self._thread = threading.Thread(target=self._run, name=f"viewer-ar-{camera}",
                                        daemon=True)

    # -- the web loop: check, publish, keep ------------------------------------------
    def offer_frame(self, data: bytes, tag: Any = None) -> None:
        """A frame from the page; ArRefused (and nothing kept) if it is refused."""
        limits = self.hub.limits
        now = time.monotonic()
        self._tokens = min(max(2.0, limits.max_fps / 2),
                           self._tokens + (now - self._refilled) * limits.max_fps)
        self._refilled = now
        if len(data) > limits.max_frame_bytes:
            raise ArRefused("ar frame", f"{len(data)} bytes is more than "
                                        f"{limits.max_frame_bytes}")
        try:
            width, height = jpeg_size(data)
        except JpegError as exc:
            raise ArRefused("ar frame", str(exc)) from None
        if width * height > limits.max_frame_pixels:
            raise ArRefused("ar frame", f"{width}x{height} is more than "
                                        f"{limits.max_frame_pixels} pixels")
        if self._tokens < 1.0:
            raise ArRefused("ar rate", f"more than {limits.max_fps:g} frames a second")
        self._tokens -= 1.0
        self._seq += 1
        stamp = max(time.time(), self._last_stamp + 1e-6)  # unique: it names the frame
        self._last_stamp = stamp
        frame = CameraFrame(camera=self.camera, seq=self._seq, stamp=stamp, encoding="jpeg",
                            width=width, height=height, data=data)
        with self._lock:
            self._frames.append(_Sent(self._seq, stamp, data, now, tag))
            while len(self._frames) > KEPT_FRAMES:  # a page that ignores the flow control
                self._frames.popleft()
                self.counts["overrun"] += 1
        self._publisher.put(frame.to_bytes())
        self.counts["frames"] += 1
        self._wake.set()

    # -- a Zenoh thread: store -------------------------------------------------------
    def offer_registration(self, payload: bytes) -> None:
        with self._lock:
            self._regs.append((payload, time.monotonic()))
        self._wake.set()

    # -- the session's thread --------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(5.0)

    def _run(self) -> None:
        registered: dict[float, tuple[Registration, float]] = {}
        newest = -1.0
        while not self._stop.is_set():
            self._wake.wait(0.05)
            self._wake.clear()
            with self._lock:
                regs = list(self._regs)
                self._regs.clear()
            for payload, received in regs:
                reg = self.hub.decode_registration(payload)
                if reg is not None:
                    registered[reg.stamp] = (reg, received)
                    newest = max(newest, reg.stamp)
                    self.status = reg.status or "registered"
            while not self._stop.is_set():
                with self._lock:
                    frame = self._frames[0] if self._frames else None
                if frame is None:
                    break
                found = registered.pop(frame.stamp, None)
                late = time.monotonic() - frame.received > self.hub.limits.wait_s
                if found is None and newest < frame.stamp and not late:
                    self._decode_waiting()  # while its registration is on its way
                    break  # its registration may still come
                with self._lock:
                    if self._frames and self._frames[0] is frame:
                        self._frames.popleft()
                self._answer(frame, found)
            for stamp in [s for s in registered if s < newest]:  # frames already answered
                del registered[stamp]

    def _decode_waiting(self) -> None:
        """Decode the frames waiting for their registration (at most KEPT_FRAMES), so that
        drawing starts as soon as a registration comes."""
        with self._lock:
            waiting = [f for f in self._frames if f.image is None and not f.undecodable]
        for frame in waiting:
            frame.image = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
            frame.undecodable = frame.image is None

    def _answer(self, frame: _Sent, found: tuple[Registration, float] | None) -> None:
        t0 = time.perf_counter()
        jpeg, note, seq = frame.jpeg, self._why_not(found), None
        if found is not None and found[0].status == POSE_LOST:
            found, note = None, "the marker board is out of view: no camera pose for this frame"
        if found is not None:
            try:
                jpeg, note, seq = self._draw(frame, *found)
            except Exception as exc:  # keep the pictures flowing; say what went wrong
                self.hub.refusals.drop("ar render", f"camera {self.camera}: {exc!r:.200}")
                note = f"cannot draw: {type(exc).__name__}"
        overlay = not note
        self.counts["overlays" if overlay else "plain"] += 1
        self._deliver(ArResult({
            "seq": frame.seq, "tag": frame.tag, "overlay": overlay, "note": note,
            "state_seq": seq, "status": self.status, "camera": self.camera,
            "robot": self.robot,
            "server_ms": round((time.monotonic() - frame.received) * 1e3, 1),
            "draw_ms": round((time.perf_counter() - t0) * 1e3, 1)}, jpeg))

    def _why_not(self, found: tuple[Registration, float] | None) -> str:
        if found is not None:
            return ""
        if not self.status:
            return (f"waiting for camera {self.camera} to be registered: a registration "
                    f"service (--source browser) must see robot {self.robot}'s marker at its "
                    "map origin, and the marker board")
        if self.status == POSE_LOST:
            return "the marker board is out of view: no camera pose for this frame"
        return "this frame was not registered (a newer one was, or it came too late)"

    def _draw(self, frame: _Sent, reg: Registration, received: float
              ) -> tuple[bytes, str, int | None]:
        image = frame.image
        if image is None and not frame.undecodable:
            image = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            return frame.jpeg, "the frame does not decode", None
        picture, why = self.hub.api.draw_over(image, reg, received, self.robot,
                                              self.hub.settings_for(self.client))
        if picture is None:
            return frame.jpeg, why, None
        ok, encoded = cv2.imencode(".jpg", picture,
                                   [cv2.IMWRITE_JPEG_QUALITY, self.hub.limits.jpeg_quality])
        if not ok:
            return frame.jpeg, "JPEG encoding failed", None
        return encoded.tobytes(), "", self.hub.api.state_seq(self.robot)


class ArHub:
    """Every AR page's session, their settings, and the one registration subscription."""

    def __init__(self, bus: Bus, keys: Keys, api: ViewerApi, *, base_camera: str,
                 limits: ArLimits | None = None,
                 default_settings: ViewSettings | None = None) -> None:
        self.bus, self.keys, self.api = bus, keys, api
        self.base_camera = check_name("camera", base_camera)
        self.limits = limits or ArLimits()
        self.default_settings = default_settings or ViewSettings(legend=False)
        self.refusals = DropCounter(log)  #: refused frames, cameras, bad registrations
        self._lock = threading.Lock()
        self._sessions: dict[str, ArSession] = {}
        self._settings: collections.OrderedDict[str, ViewSettings] = collections.OrderedDict()
        self.opened = 0
        self.closed = 0
        bus.subscribe(keys.any_registration(), self._on_registration)

    # -- sessions -------------------------------------------------------------------
    def open(self, *, client: str, camera: str, robot: str | None,
             deliver: Callable[[ArResult], None]) -> ArSession:
        """A new session for the page ``client`` as ``camera`` (ArRefused if the name is
        not this viewer's, taken, or there are ``max_cameras`` already; ConfigError for a
        robot not shown)."""
        try:
            check_name("camera", camera)
        except ConfigError as exc:
            raise ArRefused("ar camera", str(exc)) from None
        base = self.base_camera
        if camera != base and not camera.startswith(base + "-"):
            raise ArRefused("ar camera", f"camera {camera!r}: AR cameras of this viewer are "
                                         f"named {base} or {base}-… (--ar-camera)")
        names = self.api.robot_names()
        name = robot or (names[0] if names else self.api.robot)
        if not name or (robot is not None and name not in names):
            raise ArRefused("ar camera", f"robot {robot!r} is not shown by this viewer; "
                                         f"shown: {', '.join(names) or 'none yet'}")
        with self._lock:
            if camera in self._sessions:
                raise ArRefused("ar camera", f"camera {camera} is in use by another page")
            if len(self._sessions) >= self.limits.max_cameras:
                raise ArRefused("ar camera", f"the viewer already serves "
                                             f"{self.limits.max_cameras} AR cameras")
            publisher = self.bus.publisher(self.keys.capture(camera), latest_wins=True)
            session = ArSession(self, client=client, camera=camera, robot=name,
                                publisher=publisher, deliver=deliver)
            self._sessions[camera] = session
            self.opened += 1
        session.start()
        log.info("AR camera %s opened (robot %s)", camera, name)
        return session

    def close(self, session: ArSession) -> None:
        """The page left: its thread stops, its publisher goes."""
        session.stop()
        with self._lock:
            if self._sessions.get(session.camera) is session:
                del self._sessions[session.camera]
                self.closed += 1
        self.bus.release(session._publisher)
        log.info("AR camera %s closed after %d frames (%d with the overlay)", session.camera,
                 session.counts["frames"], session.counts["overlays"])

    @property
    def sessions(self) -> list[ArSession]:
        with self._lock:
            return list(self._sessions.values())

    # -- a Zenoh thread -------------------------------------------------------------
    def _on_registration(self, key: str, payload: bytes) -> None:
        camera = self.keys.camera_of(key)
        session = self._sessions.get(camera) if camera is not None else None
        if session is not None and self.keys.leaf_of(key) == session.robot:
            session.offer_registration(payload)

    def decode_registration(self, payload: bytes) -> Registration | None:
        try:
            return Registration.from_bytes(payload)
        except MessageError as exc:
            self.refusals.drop("ar registration", f"malformed: {exc}")
            return None

    # -- settings -------------------------------------------------------------------
    def settings_for(self, client: str) -> ViewSettings:
        with self._lock:
            settings = self._settings.get(client)
            if settings is None:
                settings = self._settings[client] = self.default_settings
                while len(self._settings) > MAX_CLIENTS:
                    self._settings.popitem(last=False)
            self._settings.move_to_end(client)
            return settings

    def update_settings(self, client: str, changes: Mapping[str, Any]) -> ViewSettings:
        """Apply a page's changes (as the main page's); ConfigError naming a bad one."""
        if changes.get("reset"):
            settings = self.default_settings
        else:
            query = {k: (("true" if v else "false") if isinstance(v, bool) else
                         "" if v is None else str(v)) for k, v in changes.items()}
            settings = ViewSettings.from_query(query, base=self.settings_for(client))
        with self._lock:
            self._settings[client] = settings
        return settings

    def status(self) -> dict[str, Any]:
        return {"camera": self.base_camera, "opened": self.opened, "closed": self.closed,
                "refused": dict(self.refusals.counts),
                "cameras": [{"camera": s.camera, "robot": s.robot, "status": s.status,
                             **dict(s.counts)} for s in self.sessions]}
