"""What the viewer receives, as values: raw payloads, the newest decoded inputs, what arrived.

* As it arrived: :class:`Raw` (a payload and its receipt time), :class:`LazyRaw` (a state
  not yet copied out of Zenoh's buffer), :class:`Queue` (a bounded FIFO: health), and the
  raw slots of one robot (:class:`RawRobot`) and one camera (:class:`RawCamera`), which
  the intake fills and the pipeline empties; filling one sets an event of
  :class:`Wakeups`.
* Decoded: :class:`RobotInputs`, :class:`CameraInputs` and :class:`Inputs`, one
  consistent snapshot of the store (:mod:`store`).
* What one take-in brought (:mod:`takein`): :class:`RobotArrivals`, :class:`Arrivals`.

Maps and epochs (docs/protocol.md): a state whose ``epoch`` differs from the robot's
previous one (or, with epoch 0 = unknown, whose seq went back) starts a new map
(:func:`is_new_map`). A registration places one epoch's map frame: one whose ``epoch``
differs from the state's, or without an epoch and received before the state that began
the current epoch, is *stale* (:meth:`RobotInputs.registration_usable`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from slamlens.common.latest import Latest
from slamlens.common.messages import CameraFrame, Health, Registration, SlamState, Truth


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


class Wakeups:
    """What filling a raw slot wakes (a Zenoh callback only sets an event): ``state`` the
    thread that decodes states, ``frame`` the one that decodes camera frames, ``input``
    the render thread (health, registrations, decoded frames and states, a new view)."""

    def __init__(self) -> None:
        self.state = threading.Event()
        self.frame = threading.Event()
        self.input = threading.Event()


@dataclass(frozen=True, eq=False)
class RawRobot:
    """One robot's raw slots (filled by the intake's subscriptions)."""

    name: str
    index: int  #: order of arrival: 0 for the first robot (the settings' colours)
    state_slot: Latest[Raw | LazyRaw]  #: the newest state, copied out only when decoded
    tracked_slot: Latest[Raw]  #: the newest camera-tracked pose
    health_queue: Queue  #: every verdict since the last take-in


@dataclass(frozen=True, eq=False)
class RawCamera:
    """One camera's raw slots: its newest frame, and its newest registration per robot."""

    name: str
    frame_slot: Latest[Raw]
    registration_slots: Mapping[str, Latest[Raw]]  #: by robot


#: a robot's newest state through the pipeline's stages, for the render thread: (its
#: receipt time, time.monotonic() s; the decoded state, or None if it was bad)
Prepared = tuple[float, SlamState | None]


class RawSource(Protocol):
    """Where the raw slots are (the intake): the robots and cameras subscribed so far."""

    def robots(self) -> tuple[RawRobot, ...]: ...

    def cameras(self) -> tuple[RawCamera, ...]: ...


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
    """Whether ``state`` starts a new map after ``previous`` (docs/protocol.md): another
    epoch, or (epoch 0 = unknown, a third-party estimator) a seq that went back. The same
    epoch with a lower seq is an estimator resumed from its checkpoint: the same map."""
    if previous is None:
        return False
    if state.epoch != previous.epoch:
        return True
    return state.epoch == 0 and state.seq < previous.seq


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
    """What one take-in brought for one robot."""

    robot: str
    state: SlamState | None = None  #: a new state
    restarted: bool = False  #: it began a new map (another epoch, or seq went back)
    tracked: Truth | None = None  #: a new camera-tracked pose
    healths: tuple[Health, ...] = ()  #: new verdicts, oldest first


@dataclass(frozen=True, eq=False)
class Arrivals:
    """What one take-in brought, per robot, for the parts that keep a history."""

    robots: tuple[RobotArrivals, ...] = ()

    def of(self, robot: str) -> RobotArrivals:
        return next((a for a in self.robots if a.robot == robot), RobotArrivals(robot))
