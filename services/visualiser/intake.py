"""What the viewer receives: subscriptions, late join, decoding, and the newest of each input.

A Zenoh callback only stores the raw payload and its receipt time and wakes the viewer
(O(1), no decoding), so a slow viewer never slows the estimator or the camera. State,
frames and registrations are kept latest-wins (:class:`~slamlens.common.latest.Latest`); health
verdicts in a bounded FIFO (:class:`Queue`: every verdict feeds the plots). Frames are
decoded on the ``viewer-decode`` thread as they arrive; states on ``viewer-prepare``
(newest first), which hands each to ``prepare`` (the viewer computes its scenes) and then
to the render thread — a state's callback keeps only a getter of its payload
(``Bus.subscribe_lazy``), so only the newest is copied out of Zenoh's buffer when that
thread takes it, and the states it skips are never copied; everything else when the
render thread calls :meth:`Intake.ingest`. A bad payload is logged (the first few of
each kind, then one line in a hundred: :class:`~slamlens.common.drops.DropCounter`), counted and
dropped; so is a registration no camera model can be made of (or larger than
``max_frame_pixels``), and a frame whose JPEG header (read without decoding) claims another
size than its message or more pixels than allowed (a decode bomb).

Several robots: each has its own state, health and tracked pose, and one registration
per camera (``camera/C/registration/R``). Robots are named, or discovered: with
``discover`` every robot whose estimator is alive (liveliness
``robot/*/alive/estimator``) is added as it appears, by the ``viewer-discover`` thread
(subscriptions and the late-join ``get`` never run on a Zenoh thread or the render thread).

Maps and epochs (SPEC §7a): a state whose ``epoch`` differs from the robot's previous one
(or, with epoch 0 = unknown, whose seq went back) starts a new map: :class:`Arrivals`
says so and the viewer drops what it holds of the old one. A registration places one
epoch's map frame: one whose ``epoch`` differs from the state's, or without an epoch and
received before the state that began the current epoch, is *stale*
(:meth:`RobotInputs.registration_usable`): the picture then shows a note, never an
overlay in the wrong frame.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import cv2
import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.messages import CameraFrame, Health, Registration, SlamState, Truth
from slamlens.common.summary import SummaryQuery
from slamlens.common.summary_pull import SummaryPuller
from slamlens.common.verdict import violation_text
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.jpeg import JpegError, jpeg_size
from slamlens.services.visualiser.summary_view import decode_summary_state

log = logging.getLogger("slamlens.viewer")

T = TypeVar("T")


@dataclass(frozen=True)
class Raw:
    """One payload as it arrived."""

    payload: bytes
    received: float  #: time.monotonic() at receipt, s


@dataclass(frozen=True)
class LazyRaw:
    """A state as it arrived, not copied yet (``Bus.subscribe_lazy``): a 32 MB state at
    n = 1000 stays in Zenoh's buffer (shared memory) until it is the newest one the
    viewer decodes; the others are dropped uncopied."""

    fetch: Callable[[], bytes]
    received: float  #: time.monotonic() at receipt, s

    def load(self) -> Raw:
        return Raw(self.fetch(), self.received)


def _store_lazy(slot: Latest[Raw | LazyRaw]) -> Callable[[str, Callable[[], bytes]], None]:
    """A lazy bus callback that only stores the payload's getter (no copy, no decoding)."""

    def callback(_key: str, fetch: Callable[[], bytes]) -> None:
        slot.put(LazyRaw(fetch, time.monotonic()))

    return callback


#: registration events kept for the page (start, new map, requested, refused)
REGISTRATION_EVENTS = 20


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


def is_new_map(previous: SlamState | None, state: SlamState) -> bool:
    """Whether ``state`` starts a new map after ``previous`` (SPEC §7a, docs/protocol.md):
    another epoch, or (epoch 0 = unknown, a third-party estimator) a seq that went back. The
    same epoch with a lower seq is an estimator resumed from its checkpoint: the same map."""
    if previous is None:
        return False
    if state.epoch != previous.epoch:
        return True
    return state.epoch == 0 and state.seq < previous.seq


@dataclass
class _RegistrationInput:
    """One camera's registration for one robot: raw slot and decoded value."""

    slot: Latest[Raw]
    registration: Registration | None = None
    received: float | None = None  #: time.monotonic() at receipt of the decoded one
    version: int = 0  #: +1 per registration decoded


@dataclass
class _Camera:
    """Inputs of one camera: raw slots and their decoded values."""

    name: str
    frame_slot: Latest[Raw]
    image: np.ndarray | None = None  #: decoded BGR frame
    frame: CameraFrame | None = None  #: its message (data kept for the status only)
    frame_received: float | None = None
    frame_version: int = 0  #: +1 per frame decoded
    registrations: dict[str, _RegistrationInput] = field(default_factory=dict)  #: by robot
    rate: RateMeter = field(default_factory=RateMeter)


@dataclass
class _Robot:
    """Inputs of one robot: raw slots, decoded values, and where its current map began."""

    name: str
    index: int  #: order of arrival (its colour)
    state_slot: Latest[Raw | LazyRaw]  #: the newest state, copied out only when decoded
    tracked_slot: Latest[Raw]
    health_queue: Queue
    #: decoded (and prepared) states for the render thread: (receipt time, state or None
    #: if bad)
    prepared: Latest[tuple[float, SlamState | None]] = field(default_factory=Latest)
    state: SlamState | None = None
    state_received: float | None = None
    state_version: int = 0
    state_rate: RateMeter = field(default_factory=RateMeter)
    health: Health | None = None
    health_version: int = 0
    violations: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=200))
    #: receipt time of the state that began the current map (−inf: the first map seen)
    epoch_started: float = -float("inf")
    restarted_at: float | None = None  #: time.monotonic() of the last new map seen
    restarts: int = 0  #: new maps seen


@dataclass(frozen=True, eq=False)
class CameraInputs:
    """One camera's newest decoded inputs."""

    name: str
    image: np.ndarray | None  #: BGR frame
    frame: CameraFrame | None
    frame_received: float | None  #: time.monotonic() at receipt, s
    #: robot → (registration, time.monotonic() at its receipt)
    registrations: dict[str, tuple[Registration, float]]
    rate: RateMeter  #: frames decoded per second

    @property
    def registration(self) -> Registration | None:
        """The registration of the first robot that has one (single-robot callers)."""
        return next((reg for reg, _ in self.registrations.values()), None)


@dataclass(frozen=True, eq=False)
class RobotInputs:
    """One robot's newest decoded inputs."""

    name: str
    index: int  #: order of arrival: 0 for the first robot (the settings' colours)
    state: SlamState | None
    state_received: float | None  #: time.monotonic() at receipt, s
    health: Health | None
    epoch_started: float  #: receipt time of the state that began the current map
    restarted_at: float | None  #: time.monotonic() of the last new map seen (None: none)
    restarts: int
    state_rate: RateMeter

    def registration_usable(self, registration: Registration, received: float) -> bool:
        """Whether ``registration`` places this robot's *current* map (module docstring)."""
        if registration.epoch is not None:
            return self.state is None or registration.epoch == self.state.epoch
        return received >= self.epoch_started


@dataclass(frozen=True, eq=False)
class Inputs:
    """The newest decoded inputs at one instant; ``versions`` changes whenever one does."""

    robots: tuple[RobotInputs, ...]
    cameras: tuple[CameraInputs, ...]
    versions: tuple[Any, ...]

    @property
    def state(self) -> SlamState | None:
        """The first robot's state (single-robot callers)."""
        return self.robots[0].state if self.robots else None

    @property
    def state_received(self) -> float | None:
        return self.robots[0].state_received if self.robots else None

    @property
    def health(self) -> Health | None:
        return self.robots[0].health if self.robots else None

    def robot(self, name: str) -> RobotInputs | None:
        return next((r for r in self.robots if r.name == name), None)


@dataclass(frozen=True, eq=False)
class RobotArrivals:
    """What one :meth:`Intake.ingest` took in for one robot."""

    robot: str
    state: SlamState | None = None  #: a new state
    restarted: bool = False  #: it began a new map (another epoch, or seq went back)
    tracked: Truth | None = None  #: a new camera-tracked pose
    healths: tuple[Health, ...] = ()  #: new verdicts, oldest first


@dataclass(frozen=True, eq=False)
class Arrivals:
    """What one :meth:`Intake.ingest` took in, per robot, for the parts that keep a history."""

    robots: tuple[RobotArrivals, ...] = ()
    added: tuple[str, ...] = ()  #: robots discovered since the last call

    def of(self, robot: str) -> RobotArrivals:
        return next((a for a in self.robots if a.robot == robot), RobotArrivals(robot))


class Intake:
    """Subscribes to the robots' state, health and tracked pose and to the cameras.

    ``robots`` are subscribed at :meth:`start`; with ``discover`` every robot whose
    estimator is alive is added as it appears. ``on_input`` is called (on a Zenoh thread or
    the decode thread, so it must only wake somebody) when a state, health, registration
    or decoded frame arrives; the tracked pose wakes nobody: it is drawn with the next state.
    """

    DISCOVER_EVERY_S = 1.0  #: how often the alive estimators are asked for (discover)

    def __init__(self, bus: Bus, *, keys: Keys, robots: tuple[str, ...],
                 cameras: tuple[str, ...], fps: float, late_join_timeout_s: float,
                 on_input: Callable[[], None], drops: DropCounter,
                 discover: bool = False, max_frame_pixels: int = 16_777_216,
                 source: str = "state", summary_query: SummaryQuery | None = None,
                 prepare: Callable[[str, SlamState], None] | None = None,
                 finish: Callable[[str, SlamState], None] | None = None) -> None:
        self.bus = bus
        #: called on the ``viewer-prepare`` thread with each decoded state before the render
        #: thread takes it in (the viewer computes its pictures' scenes there)
        self._prepare = prepare
        #: if given, the second stage: called on the ``viewer-layers`` thread with each
        #: prepared state (the viewer draws its layers there) while ``viewer-prepare``
        #: decodes the next one — a two-stage pipeline (:meth:`_prepare_loop`)
        self._finish = finish
        #: prepared states waiting for ``viewer-layers`` (one at most: the next state is
        #: taken from Zenoh only when it can go on, so it is the newest there is)
        self._handoff: queue.Queue[tuple[_Robot, float, SlamState | None] | None] = \
            queue.Queue(maxsize=1)
        self._handed = threading.Event()  #: ``viewer-layers`` took a state from the handoff
        self._prepare_wake = threading.Event()
        #: "state": subscribe to each robot's full state; "summary": pull its summary
        #: stream instead (docs/remote_viewers.md); either fills the robot's state slot
        self.source = source
        self._summary_query = summary_query or SummaryQuery(what="clusters")
        self._puller_of: dict[str, SummaryPuller] = {}  #: by robot
        self.max_frame_pixels = max_frame_pixels  #: frames claiming more are not decoded
        self.keys = keys
        self.bad = drops  #: malformed input messages, by input
        self._fps = fps
        self._late_join_timeout_s = late_join_timeout_s
        self._discover = discover
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._decode_wake = threading.Event()
        self._threads: list[threading.Thread] = []
        self._on_input = on_input
        self._named = tuple(robots)
        self._robots: dict[str, _Robot] = {}
        self._added: list[str] = []
        self._cameras = {c: _Camera(c, Latest(on_put=self._decode_wake.set)) for c in cameras}
        #: every registration made (start, new map, requested, refused), newest last
        self._reg_events: deque[dict[str, Any]] = deque(maxlen=REGISTRATION_EVENTS)
        self._reg_last: dict[tuple[str, str], tuple[Any, ...]] = {}

    @property
    def robot(self) -> str:
        """The first robot (named first, or discovered first; "" before any)."""
        with self._lock:
            names = list(self._robots)
        return names[0] if names else (self._named[0] if self._named else "")

    @property
    def robot_names(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._robots)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(self._cameras)

    @property
    def discovering(self) -> bool:
        return self._discover

    def summary_selection(self, robot: str | None, *, feature: int | None = None,
                          cluster: int | None = None) -> None:
        """``--source summary``: ask ``robot``'s summary (None: every robot's) for the pairs
        of a selected feature or cluster (``what=pairs``, docs/protocol.md) from its next
        query on; neither: for the clusters again. The other robots keep the clusters."""
        base = self._summary_query
        if feature is not None or cluster is not None:
            wanted = dataclasses.replace(base, what="pairs", feature=feature,
                                         cluster=None if feature is not None else cluster)
        else:
            wanted = base
        with self._lock:
            pullers = dict(self._puller_of)
        for name, puller in pullers.items():
            puller.set_query(wanted if robot in (None, name) else base)

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, fetch the latest state and registrations (late join), start decoding
        (and discovering robots)."""
        for cam in self._cameras.values():
            self.bus.subscribe(self.keys.frame(cam.name), _store(cam.frame_slot))
        for robot in self._named:
            self.add_robot(robot)
        self._start_thread("viewer-decode", self._decode_loop)
        self._start_thread("viewer-prepare", self._prepare_loop)
        if self._finish is not None:
            self._start_thread("viewer-layers", self._finish_loop)
        if self._discover:
            self._start_thread("viewer-discover", self._discover_loop)

    def _start_thread(self, name: str, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def add_robot(self, robot: str) -> bool:
        """Subscribe to one more robot and fetch its latest (not on a Zenoh thread: the
        late-join ``get`` waits). False if it was there already."""
        k = self.keys
        with self._lock:
            if robot in self._robots:
                return False
            r = _Robot(robot, len(self._robots), Latest(on_put=self._prepare_wake.set),
                       Latest(), Queue("health", self._on_input),
                       prepared=Latest(on_put=self._on_input))
            regs = {c.name: _RegistrationInput(Latest(on_put=self._on_input))
                    for c in self._cameras.values()}
        puller = None
        if self.source == "summary":  # pulled, one query at a time (its own thread)
            puller = SummaryPuller(self.bus, k.summary(robot), self._summary_query,
                                   lambda p, t: r.state_slot.put(Raw(p, t)),
                                   name=f"viewer-summary-{robot}")
            with self._lock:
                self._puller_of[robot] = puller
        else:
            # the newest state only is ever decoded: the others are never copied out
            self.bus.subscribe_lazy(k.state(robot), _store_lazy(r.state_slot))
        self.bus.subscribe(k.health(robot), lambda _key, p: r.health_queue.offer(p))
        self.bus.subscribe(k.tracked(robot), _store(r.tracked_slot))
        for name, reg in regs.items():
            self.bus.subscribe(k.registration(name, robot), _store(reg.slot))
        with self._lock:
            self._robots[robot] = r
            for name, reg in regs.items():
                self._cameras[name].registrations[robot] = reg
            self._added.append(robot)
        self._late_join(r, regs)
        if puller is not None:
            puller.start()
        self._on_input()
        return True

    def _late_join(self, robot: _Robot, regs: dict[str, _RegistrationInput]) -> None:
        """Ask the estimator and the cameras for their latest (SPEC §7), so a viewer that
        joins late shows the current picture at once."""
        timeout = self._late_join_timeout_s
        if timeout <= 0:
            return
        wanted: list[tuple[str, Latest[Any]]] = (
            [] if self.source == "summary"  # the first pull is answered at once
            else [(self.keys.state(robot.name), robot.state_slot)])
        wanted += [(self.keys.registration(c, robot.name), reg.slot) for c, reg in regs.items()]
        for key, slot in wanted:
            try:
                replies = self.bus.get(key, timeout=timeout)
            except Exception as exc:  # a failed get must not stop the viewer
                log.warning("late-join get on %s failed: %s", key, exc)
                continue
            if replies and slot.count == 0:  # a live sample that came first is newer
                slot.put(Raw(replies[-1].payload, time.monotonic()))
        health_key = self.keys.health(robot.name)
        try:  # the monitor may answer too; its verdict is optional for the picture
            replies = self.bus.get(health_key, timeout=min(timeout, 0.5))
        except Exception as exc:
            log.debug("late-join get on %s failed: %s", health_key, exc)
            replies = []
        if replies and robot.health_queue.received_count == 0:
            robot.health_queue.offer(replies[-1].payload)

    def _discover_loop(self) -> None:
        pattern = self.keys.any_estimator_alive()
        while not self._stop.is_set():
            try:
                alive = self.bus.alive(pattern, timeout=1.0)
            except Exception as exc:  # the session closing, a router away: try again
                log.debug("liveliness get on %s failed: %s", pattern, exc)
                alive = []
            for key in alive:
                robot = self.keys.robot_of(key)
                if robot and robot not in self.robot_names and not self._stop.is_set():
                    log.info("robot %s: its estimator is alive; shown from now on", robot)
                    self.add_robot(robot)
            self._stop.wait(self.DISCOVER_EVERY_S)

    def stop(self) -> None:
        self._stop.set()
        self._decode_wake.set()
        self._prepare_wake.set()
        self._handed.set()
        try:  # wakes ``viewer-layers`` waiting for a state (a full handoff wakes it anyway)
            self._handoff.put_nowait(None)
        except queue.Full:
            pass
        with self._lock:
            pullers = list(self._puller_of.values())
        for puller in pullers:  # all told first; a query in flight ends with the bus
            puller.stop(timeout=0.0)
        for puller in pullers:
            puller.stop(timeout=0.5)
        for thread in self._threads:
            thread.join(timeout=5.0)

    # -- decoding -----------------------------------------------------------------
    def _prepare_loop(self) -> None:
        """States: decoded here, newest first (latest wins), handed to ``prepare`` and
        then to the render thread, which meanwhile draws the previous state (issue 13:
        at n = 1000 a state's decoding and scenes cost as much as drawing it).

        With ``finish`` the state goes to ``viewer-layers`` instead, which draws it while
        this thread decodes the next: two stages, each a state's half of the work, so on a
        machine with a core to spare a new state is ready every max(stage) instead of
        every sum. The next state is taken from Zenoh only once the handoff is free, so
        it is the newest when its work begins (a finished state never waits for another)."""
        while not self._stop.is_set():
            while self._finish is not None and self._handoff.full() \
                    and not self._stop.is_set():
                self._handed.wait(0.5)
                self._handed.clear()
            self._prepare_wake.wait(0.5)
            self._prepare_wake.clear()
            with self._lock:
                robots = list(self._robots.values())
            for r in robots:
                taken = r.state_slot.take()
                if taken is None:
                    continue
                try:
                    raw = taken.load() if isinstance(taken, LazyRaw) else taken
                except Exception as exc:  # e.g. the session closing under it
                    self.bad.drop("state", f"payload unreadable ({exc!r:.200})")
                    continue
                state = self._decode_state(r, raw)
                del raw  # the decoded state holds what it needs of the payload
                if state is not None and self._prepare is not None:
                    try:
                        self._prepare(r.name, state)
                    except Exception:  # preparing is an optimisation: the render draws
                        log.exception("preparing state seq %d failed", state.seq)
                if self._finish is None:
                    r.prepared.put((taken.received, state))
                else:  # only this thread puts: after the wait above there is room
                    self._handoff.put((r, taken.received, state))

    def _finish_loop(self) -> None:
        """The second stage (``viewer-layers``): each prepared state to ``finish``, then
        to the render thread."""
        assert self._finish is not None
        while not self._stop.is_set():
            try:
                handed = self._handoff.get(timeout=0.5)
            except queue.Empty:
                continue
            if handed is None:  # stopping
                continue
            r, received, state = handed
            self._handed.set()
            if state is not None:
                try:
                    self._finish(r.name, state)
                except Exception:  # as in preparing: the render thread draws it itself
                    log.exception("finishing state seq %d failed", state.seq)
            r.prepared.put((received, state))

    def _decode_state(self, r: _Robot, raw: Raw) -> SlamState | None:
        # symmetry is the monitor's business: the viewer shows what the estimator sent
        state = decode("state", raw, decode_summary_state if self.source == "summary"
                       else lambda b: SlamState.from_bytes(b, check_symmetry=False),
                       self.bad)
        if state is not None and state.robot != r.name:
            self.bad.drop("state", f"SlamState.robot: expected {r.name!r}, "
                          f"got {state.robot!r}")
            return None
        return state

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
                try:
                    decoded = self._decode_frame(cam, raw)
                except Exception as exc:  # a frame nobody foresaw: dropped, decoding goes on
                    self.bad.drop(f"frame {cam.name}", f"undecodable ({exc!r:.200})")
                    continue
                if decoded:
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
        with self._lock:  # the largest size this camera was registered with, for any robot
            regs = [r.registration for r in cam.registrations.values()
                    if r.registration is not None]
        if regs:
            reg = max(regs, key=lambda r: r.width * r.height)
            if 4 * reg.width * reg.height < limit:
                limit, why = (4 * reg.width * reg.height,
                              f"4 × the registered {reg.width}×{reg.height}")
        if width * height > limit:
            return (f"CameraFrame.data: a {width}×{height} JPEG has more pixels than {limit} "
                    f"({why}; not decoded)")
        return ""

    def ingest(self) -> Arrivals:
        """Decode whatever states, tracked poses, health and registrations arrived since
        the last call (on the render thread); returns what is new."""
        with self._lock:
            robots = list(self._robots.values())
            added, self._added = tuple(self._added), []
        out = []
        for r in robots:
            state, restarted = self._ingest_state(r)
            tracked = None
            raw_tracked = r.tracked_slot.take()
            if raw_tracked is not None:
                tracked = decode("tracked", raw_tracked, Truth.from_bytes, self.bad)
            healths = []
            for raw in r.health_queue.drain():
                health = decode("health", raw, Health.from_bytes, self.bad)
                if health is None:
                    continue
                if health.robot != r.name:
                    self.bad.drop("health", f"Health.robot: expected {r.name!r}, "
                                  f"got {health.robot!r}")
                    continue
                with self._lock:
                    r.health = health
                    r.health_version += 1
                    for v in health.violations:
                        r.violations.append({"seq": health.seq, "stamp": health.stamp,
                                             **v.to_dict(), "text": violation_text(v)})
                healths.append(health)
            if state is not None or tracked is not None or healths:
                out.append(RobotArrivals(r.name, state, restarted, tracked, tuple(healths)))
        for cam in self._cameras.values():
            with self._lock:
                regs = list(cam.registrations.items())
            for _robot, reg_input in regs:
                raw_reg = reg_input.slot.take()
                if raw_reg is None:
                    continue
                reg = decode(f"registration {cam.name}", raw_reg, self._registration,
                             self.bad)
                if reg is not None:
                    with self._lock:
                        reg_input.registration, reg_input.received = reg, raw_reg.received
                        reg_input.version += 1
                        self._note_registration(cam.name, reg)
        return Arrivals(robots=tuple(out), added=added)

    def _note_registration(self, camera: str, reg: Registration) -> None:
        """Keep one event per registration made (its reason, epoch and stamp tell them
        apart; the same one published again is not a new event). Under ``_lock``."""
        if reg.reason is None:
            return  # a registration service that does not say why: nothing to tell
        ident = (reg.epoch, reg.stamp, reg.reason, reg.moved_m, reg.moved_deg)
        if self._reg_last.get((camera, reg.robot)) == ident:
            return
        self._reg_last[(camera, reg.robot)] = ident
        self._reg_events.append({
            "camera": camera, "robot": reg.robot, "epoch": reg.epoch, "stamp": reg.stamp,
            "reason": reg.reason, "moved_m": reg.moved_m, "moved_deg": reg.moved_deg,
            "status": reg.status, "refused": reg.reason.startswith("refused"),
            "at": time.time()})

    def registration_events(self) -> list[dict[str, Any]]:
        """The registrations seen (newest first): who asked, how far the frame moved."""
        with self._lock:
            return [dict(e) for e in reversed(self._reg_events)]

    def _registration(self, payload: bytes) -> Registration:
        """A registration the viewer can draw through: well-formed, a camera model
        (positive focal lengths, K[2,2] = 1, a known number of distortion coefficients) and
        at most ``max_frame_pixels`` (the picture is drawn at its size even before a frame
        comes); else an error naming what is wrong (counted, never a failed render)."""
        reg = Registration.from_bytes(payload)
        if reg.width * reg.height > self.max_frame_pixels:
            raise MessageError("Registration", "width×height",
                               f"at most {self.max_frame_pixels} pixels (max_frame_pixels)",
                               f"{reg.width}×{reg.height}")
        CameraModel.from_registration(reg)  # CalibrationError: no camera has such a model
        return reg

    def _ingest_state(self, r: _Robot) -> tuple[SlamState | None, bool]:
        item = r.prepared.take()  # decoded on the viewer-prepare thread
        if item is None:
            return None, False
        received, state = item
        if state is None:
            return None, False
        with self._lock:
            restarted = is_new_map(r.state, state)
            if restarted:
                assert r.state is not None
                log.warning("robot %s: map restarted (epoch %d → %d, seq %d → %d): the old "
                            "map's path, plots and registration are dropped", r.name,
                            r.state.epoch, state.epoch, r.state.seq, state.seq)
                r.epoch_started, r.restarted_at = received, time.monotonic()
                r.restarts += 1
            r.state, r.state_received = state, received
            r.state_version += 1
        r.state_rate.tick()
        return state, restarted

    # -- what the other parts read ------------------------------------------------
    def versions(self) -> tuple[Any, ...]:
        """Changes whenever a decoded input does (a picture of older versions is stale)."""
        with self._lock:
            return self._versions()

    def _versions(self) -> tuple[Any, ...]:
        return (tuple((r.state_version, r.health_version) for r in self._robots.values()),
                tuple((c.frame_version, tuple(g.version for g in c.registrations.values()))
                      for c in self._cameras.values()))

    def snapshot(self) -> Inputs:
        """One consistent view of the newest inputs and their versions."""
        with self._lock:
            robots = tuple(RobotInputs(r.name, r.index, r.state, r.state_received, r.health,
                                       r.epoch_started, r.restarted_at, r.restarts,
                                       r.state_rate)
                           for r in self._robots.values())
            cameras = tuple(CameraInputs(
                c.name, c.image, c.frame, c.frame_received,
                {robot: (g.registration, g.received) for robot, g in c.registrations.items()
                 if g.registration is not None and g.received is not None}, c.rate)
                for c in self._cameras.values())
            return Inputs(robots=robots, cameras=cameras, versions=self._versions())

    def recent_violations(self, robot: str | None = None) -> list[dict[str, Any]]:
        """The last 200 violations the monitor reported for ``robot`` (default: the
        first), oldest first."""
        name = robot or self.robot
        with self._lock:
            r = self._robots.get(name)
            return [] if r is None else list(r.violations)
