"""What the viewer receives: subscriptions, late join, decoding, and the newest of each input.

A Zenoh callback only stores the raw payload and its receipt time and wakes the viewer
(O(1), no decoding), so a slow viewer never slows the estimator or the camera. State,
frames and registrations are kept latest-wins (:class:`~common.latest.Latest`); health
verdicts in a bounded FIFO (:class:`Queue`: every verdict feeds the plots). Frames are
decoded on the ``viewer-decode`` thread as they arrive; everything else when the render
thread calls :meth:`Intake.ingest`. A bad payload is logged (the first few of each kind,
then one line in a hundred: :class:`~common.drops.DropCounter`), counted and dropped; so
is a frame whose JPEG header (read without decoding) claims another size than its message
or more pixels than allowed (a decode bomb).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import cv2
import numpy as np

from common.bus import Bus
from common.drops import DropCounter
from common.keys import Keys
from common.latest import Latest
from common.messages import CameraFrame, Health, Registration, SlamState, Truth
from services.visualiser.jpeg import JpegError, jpeg_size

log = logging.getLogger("slamlens.viewer")

T = TypeVar("T")


@dataclass(frozen=True)
class Raw:
    """One payload as it arrived."""

    payload: bytes
    received: float  #: time.monotonic() at receipt, s


def _store(slot: Latest[Raw]) -> Callable[[str, bytes], None]:
    """A bus callback that only stores the payload (no decoding on Zenoh's thread)."""

    def callback(_key: str, payload: bytes) -> None:
        slot.put(Raw(payload, time.monotonic()))

    return callback


class Queue:
    """A bounded FIFO of payloads (health: every verdict counts for the time series)."""

    def __init__(self, name: str, wake: Callable[[], None], *, maxlen: int = 512) -> None:
        self.name = name
        self._wake = wake
        self._items: deque[Raw] = deque(maxlen=maxlen)  # oldest dropped when the viewer lags
        self._lock = threading.Lock()
        self.received_count = 0

    def offer(self, payload: bytes) -> None:
        with self._lock:
            self.received_count += 1
            self._items.append(Raw(payload, time.monotonic()))
        self._wake()

    def drain(self) -> list[Raw]:
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


def decode(source: str, raw: Raw, decoder: Callable[[bytes], T], drops: DropCounter) -> T | None:
    """``decoder(raw.payload)``, or None (counted and logged) when it is malformed."""
    try:
        return decoder(raw.payload)
    except Exception as exc:  # any decoder failure is a bad message, never a crash
        drops.drop(source, str(exc))
        return None


class RateMeter:
    """Events per second over a sliding window (frame rates in the status line)."""

    def __init__(self, window_s: float = 2.0) -> None:
        self._window = window_s
        self._times: deque[float] = deque()
        self._lock = threading.Lock()

    def tick(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._times.append(now)
            self._trim(now)

    def rate(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._trim(now)
            if len(self._times) < 2:
                return 0.0
            # (count − 1) intervals over the span between first and last event in the window
            return (len(self._times) - 1) / max(self._times[-1] - self._times[0], 1e-6)

    def _trim(self, now: float) -> None:
        while self._times and now - self._times[0] > self._window:
            self._times.popleft()


@dataclass
class _Camera:
    """Inputs of one camera: raw slots and their decoded values."""

    name: str
    frame_slot: Latest[Raw]
    registration_slot: Latest[Raw]
    image: np.ndarray | None = None  #: decoded BGR frame
    frame: CameraFrame | None = None  #: its message (data kept for the status only)
    frame_received: float | None = None
    frame_version: int = 0  #: +1 per frame decoded
    registration: Registration | None = None
    registration_version: int = 0  #: +1 per registration decoded
    rate: RateMeter = field(default_factory=RateMeter)


@dataclass(frozen=True, eq=False)
class CameraInputs:
    """One camera's newest decoded inputs."""

    name: str
    image: np.ndarray | None  #: BGR frame
    frame: CameraFrame | None
    frame_received: float | None  #: time.monotonic() at receipt, s
    registration: Registration | None
    rate: RateMeter  #: frames decoded per second


@dataclass(frozen=True, eq=False)
class Inputs:
    """The newest decoded inputs at one instant; ``versions`` changes whenever one does."""

    state: SlamState | None
    state_received: float | None  #: time.monotonic() at receipt, s
    health: Health | None
    cameras: tuple[CameraInputs, ...]
    versions: tuple[Any, ...]


@dataclass(frozen=True, eq=False)
class Arrivals:
    """What one :meth:`Intake.ingest` took in, for the parts that keep a history."""

    state: SlamState | None = None  #: a new state
    restarted: bool = False  #: its seq went backwards: a new run
    tracked: Truth | None = None  #: a new camera-tracked pose
    healths: tuple[Health, ...] = ()  #: new verdicts, oldest first


class Intake:
    """Subscribes to one robot's state, health and tracked pose and to its cameras.

    ``on_input`` is called (on a Zenoh thread or the decode thread, so it must only wake
    somebody) when a state, health, registration or decoded frame arrives; the tracked
    pose wakes nobody: it is drawn with the next state.
    """

    def __init__(self, bus: Bus, *, keys: Keys, robot: str, cameras: tuple[str, ...],
                 fps: float, late_join_timeout_s: float, on_input: Callable[[], None],
                 drops: DropCounter, max_frame_pixels: int = 16_777_216) -> None:
        self.bus = bus
        self.max_frame_pixels = max_frame_pixels  #: frames claiming more are not decoded
        self.keys = keys
        self.robot = robot
        self.bad = drops  #: malformed input messages, by input
        self._fps = fps
        self._late_join_timeout_s = late_join_timeout_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._decode_wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._state_slot: Latest[Raw] = Latest(on_put=on_input)
        self._tracked_slot: Latest[Raw] = Latest()
        self._health_queue = Queue("health", on_input)
        self._cameras = {c: _Camera(c, Latest(on_put=self._decode_wake.set),
                                    Latest(on_put=on_input)) for c in cameras}
        self._on_input = on_input
        self.state: SlamState | None = None
        self.state_received: float | None = None
        self._state_version = 0
        self.state_rate = RateMeter()  #: states taken in per second
        self.health: Health | None = None
        self._health_version = 0
        self._violations: deque[dict[str, Any]] = deque(maxlen=200)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(self._cameras)

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, fetch the latest state and registrations (late join), start decoding."""
        k, robot = self.keys, self.robot
        self.bus.subscribe(k.state(robot), _store(self._state_slot))
        self.bus.subscribe(k.health(robot), lambda _key, p: self._health_queue.offer(p))
        self.bus.subscribe(k.tracked(robot), _store(self._tracked_slot))
        for cam in self._cameras.values():
            self.bus.subscribe(k.frame(cam.name), _store(cam.frame_slot))
            self.bus.subscribe(k.registration(cam.name, robot), _store(cam.registration_slot))
        self._late_join()
        self._thread = threading.Thread(target=self._decode_loop, name="viewer-decode",
                                        daemon=True)
        self._thread.start()

    def _late_join(self) -> None:
        """Ask the estimator and the cameras for their latest (SPEC §7), so a viewer that
        joins late shows the current picture at once."""
        timeout = self._late_join_timeout_s
        if timeout <= 0:
            return
        wanted = [(self.keys.state(self.robot), self._state_slot)]
        wanted += [(self.keys.registration(c.name, self.robot), c.registration_slot)
                   for c in self._cameras.values()]
        for key, slot in wanted:
            try:
                replies = self.bus.get(key, timeout=timeout)
            except Exception as exc:  # a failed get must not stop the viewer
                log.warning("late-join get on %s failed: %s", key, exc)
                continue
            if replies and slot.count == 0:  # a live sample that came first is newer
                slot.put(Raw(replies[-1].payload, time.monotonic()))
        health_key = self.keys.health(self.robot)
        try:  # the monitor may answer too; its verdict is optional for the picture
            replies = self.bus.get(health_key, timeout=min(timeout, 0.5))
        except Exception as exc:
            log.debug("late-join get on %s failed: %s", health_key, exc)
            replies = []
        if replies and self._health_queue.received_count == 0:
            self._health_queue.offer(replies[-1].payload)

    def stop(self) -> None:
        self._stop.set()
        self._decode_wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    # -- decoding -----------------------------------------------------------------
    def _decode_loop(self) -> None:
        # decode no faster than the render cap: a 60 Hz camera under a 30 fps cap would
        # otherwise spend half its decoding on frames nobody draws (latest wins meanwhile)
        min_interval = 0.9 / self._fps
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
                if self._decode_frame(cam, raw):
                    cam.rate.tick()
                    self._on_input()

    def _decode_frame(self, cam: _Camera, raw: Raw) -> bool:
        frame = decode(f"frame {cam.name}", raw, CameraFrame.from_bytes, self.bad)
        if frame is None:
            return False
        refused = self._refuse_size(cam, frame)  # before decoding: a bomb never allocates
        if refused:
            self.bad.drop(f"frame {cam.name}", refused)
            return False
        try:
            image = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error:  # e.g. empty data
            image = None
        if image is None or image.shape[:2] != (frame.height, frame.width):
            got = "undecodable JPEG" if image is None else f"{image.shape[1]}×" \
                f"{image.shape[0]} pixels"
            self.bad.drop(f"frame {cam.name}", f"CameraFrame.data: expected a "
                          f"{frame.width}×{frame.height} JPEG, got {got}")
            return False
        with self._lock:
            cam.image, cam.frame, cam.frame_received = image, frame, raw.received
            cam.frame_version += 1
        return True

    def _refuse_size(self, cam: _Camera, frame: CameraFrame) -> str:
        """Why the frame must not be decoded (its JPEG header's size), or ""."""
        try:
            width, height = jpeg_size(frame.data)
        except JpegError as exc:
            return f"CameraFrame.data: {exc}"
        if (width, height) != (frame.width, frame.height):
            return (f"CameraFrame.data: the JPEG header says {width}×{height} pixels, the "
                    f"message {frame.width}×{frame.height} (not decoded)")
        limit, why = self.max_frame_pixels, "max_frame_pixels"
        with self._lock:
            reg = cam.registration
        if reg is not None and 4 * reg.width * reg.height < limit:
            limit, why = 4 * reg.width * reg.height, f"4 × the registered {reg.width}×{reg.height}"
        if width * height > limit:
            return (f"CameraFrame.data: a {width}×{height} JPEG has more pixels than {limit} "
                    f"({why}; not decoded)")
        return ""

    def ingest(self) -> Arrivals:
        """Decode whatever state, tracked pose, health and registration arrived since the
        last call (on the render thread); returns what is new."""
        state, restarted = self._ingest_state()
        tracked = None
        raw_tracked = self._tracked_slot.take()
        if raw_tracked is not None:
            tracked = decode("tracked", raw_tracked, Truth.from_bytes, self.bad)
        healths = []
        for raw in self._health_queue.drain():
            health = decode("health", raw, Health.from_bytes, self.bad)
            if health is None:
                continue
            with self._lock:
                self.health = health
                self._health_version += 1
                for v in health.violations:
                    self._violations.append({"seq": health.seq, "stamp": health.stamp,
                                             **v.to_dict()})
            healths.append(health)
        for cam in self._cameras.values():
            raw_reg = cam.registration_slot.take()
            if raw_reg is None:
                continue
            reg = decode(f"registration {cam.name}", raw_reg, Registration.from_bytes, self.bad)
            if reg is not None:
                with self._lock:
                    cam.registration = reg
                    cam.registration_version += 1
        return Arrivals(state=state, restarted=restarted, tracked=tracked,
                        healths=tuple(healths))

    def _ingest_state(self) -> tuple[SlamState | None, bool]:
        raw = self._state_slot.take()
        if raw is None:
            return None, False
        # symmetry is the monitor's business: the viewer shows what the estimator sent
        state = decode("state", raw, lambda b: SlamState.from_bytes(
            b, check_symmetry=False), self.bad)
        if state is None:
            return None, False
        if state.robot != self.robot:
            self.bad.drop("state", f"SlamState.robot: expected {self.robot!r}, "
                          f"got {state.robot!r}")
            return None, False
        with self._lock:
            restarted = self.state is not None and state.seq < self.state.seq
            self.state, self.state_received = state, raw.received
            self._state_version += 1
        self.state_rate.tick()
        return state, restarted

    # -- what the other parts read ------------------------------------------------
    def versions(self) -> tuple[Any, ...]:
        """Changes whenever a decoded input does (a picture of older versions is stale)."""
        with self._lock:
            return self._versions()

    def _versions(self) -> tuple[Any, ...]:
        return (self._state_version, self._health_version,
                tuple((c.frame_version, c.registration_version)
                      for c in self._cameras.values()))

    def snapshot(self) -> Inputs:
        """One consistent view of the newest inputs and their versions."""
        with self._lock:
            return Inputs(
                state=self.state, state_received=self.state_received, health=self.health,
                cameras=tuple(CameraInputs(c.name, c.image, c.frame, c.frame_received,
                                           c.registration, c.rate)
                              for c in self._cameras.values()),
                versions=self._versions())

    def recent_violations(self) -> list[dict[str, Any]]:
        """The last 200 violations the monitor reported, oldest first."""
        with self._lock:
            return list(self._violations)
