"""The newest decoded inputs of every robot and camera the viewer shows, and their versions.

The pipeline writes what it decoded (:mod:`stages`: frames; :mod:`takein`: states, health,
tracked poses, registrations); every part that draws or answers reads one consistent
:meth:`InputStore.snapshot`, whose ``versions`` change whenever a decoded input does (a
picture of older versions is stale). Several robots: each has its own state and health,
and one registration per camera (``camera/C/registration/R``).

A state that begins a new map (:func:`~slamlens.services.visualiser.inputs.is_new_map`)
is counted and remembered with its receipt time, from which a registration without an
epoch is current (:meth:`~slamlens.services.visualiser.inputs.RobotInputs.registration_usable`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slamlens.common.messages import CameraFrame, Health, Registration, SlamState
from slamlens.common.verdict import violation_text
from slamlens.services.visualiser.inputs import (
    CameraInputs,
    Inputs,
    RateMeter,
    RobotInputs,
    is_new_map,
)

log = logging.getLogger("slamlens.viewer")

#: registration events kept for the page (start, new map, requested, refused)
REGISTRATION_EVENTS = 20
VIOLATIONS_KEPT = 200  #: the monitor's violations kept per robot (the page's log)


@dataclass
class _Registration:
    """One camera's newest decoded registration for one robot."""

    registration: Registration | None = None
    received: float | None = None  #: time.monotonic() at receipt
    version: int = 0  #: +1 per registration decoded


@dataclass
class _Camera:
    """One camera's newest decoded frame and registrations."""

    name: str
    image: np.ndarray | None = None  #: decoded BGR frame
    frame: CameraFrame | None = None  #: its message (data kept for the status only)
    frame_received: float | None = None
    frame_version: int = 0  #: +1 per frame decoded
    registrations: dict[str, _Registration] = field(default_factory=dict)  #: by robot
    rate: RateMeter = field(default_factory=RateMeter)


@dataclass
class _Robot:
    """One robot's newest decoded inputs, and where its current map began."""

    name: str
    index: int  #: order of arrival (its colour)
    state: SlamState | None = None
    state_received: float | None = None
    state_version: int = 0
    state_rate: RateMeter = field(default_factory=RateMeter)
    health: Health | None = None
    health_version: int = 0
    violations: deque[dict[str, Any]] = field(
        default_factory=lambda: deque(maxlen=VIOLATIONS_KEPT))
    #: receipt time of the state that began the current map (−inf: the first map seen)
    epoch_started: float = -float("inf")
    restarted_at: float | None = None  #: time.monotonic() of the last new map seen
    restarts: int = 0  #: new maps seen


class InputStore:
    """The newest decoded inputs (module docstring); thread-safe.

    ``robots``, the robots named in the settings, are shown from the start, in their
    order (the intake subscribes to them in the same order at its start); robots it
    discovers later are added as the pipeline takes them in (:meth:`add_robot`).
    """

    def __init__(self, *, robots: tuple[str, ...], cameras: tuple[str, ...]) -> None:
        self._lock = threading.Lock()
        self._robots: dict[str, _Robot] = {}
        self._cameras = {c: _Camera(c) for c in cameras}
        #: every registration made (start, new map, requested, refused), newest last
        self._reg_events: deque[dict[str, Any]] = deque(maxlen=REGISTRATION_EVENTS)
        self._reg_last: dict[tuple[str, str], tuple[Any, ...]] = {}
        for name in robots:
            self.add_robot(name, len(self._robots))

    # -- the robots and cameras shown ---------------------------------------------
    def add_robot(self, name: str, index: int) -> bool:
        """Show one more robot (``index``: its order of arrival); False if it is shown."""
        with self._lock:
            if name in self._robots:
                return False
            self._robots[name] = _Robot(name, index)
            for cam in self._cameras.values():
                cam.registrations[name] = _Registration()
            return True

    @property
    def robot(self) -> str:
        """The first robot (named first, or discovered first; "" before any)."""
        with self._lock:
            return next(iter(self._robots), "")

    @property
    def robot_names(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._robots)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(self._cameras)

    # -- what the pipeline decoded ------------------------------------------------
    def put_frame(self, camera: str, image: np.ndarray, frame: CameraFrame,
                  received: float) -> None:
        cam = self._cameras[camera]
        with self._lock:
            cam.image, cam.frame, cam.frame_received = image, frame, received
            cam.frame_version += 1
        cam.rate.tick()

    def put_state(self, robot: str, state: SlamState, received: float) -> bool:
        """The robot's newest state; True if it began a new map."""
        with self._lock:
            r = self._robots[robot]
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
        return restarted

    def put_health(self, robot: str, health: Health) -> None:
        """The robot's newest verdict; its violations join the page's log."""
        with self._lock:
            r = self._robots[robot]
            r.health = health
            r.health_version += 1
            for v in health.violations:
                r.violations.append({"seq": health.seq, "stamp": health.stamp,
                                     **v.to_dict(), "text": violation_text(v)})

    def put_registration(self, camera: str, robot: str, registration: Registration,
                         received: float) -> None:
        with self._lock:
            entry = self._cameras[camera].registrations[robot]
            entry.registration, entry.received = registration, received
            entry.version += 1
            self._note_registration(camera, registration)

    def registrations(self, camera: str) -> list[Registration]:
        """The camera's registrations decoded so far, one per robot registered."""
        with self._lock:
            return [r.registration for r in self._cameras[camera].registrations.values()
                    if r.registration is not None]

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

    def health(self, robot: str) -> Health | None:
        """The robot's newest verdict (None: none yet, or no such robot)."""
        with self._lock:
            r = self._robots.get(robot)
            return None if r is None else r.health

    def registration_events(self) -> list[dict[str, Any]]:
        """The registrations seen (newest first): who asked, how far the frame moved."""
        with self._lock:
            return [dict(e) for e in reversed(self._reg_events)]

    def recent_violations(self, robot: str | None = None) -> list[dict[str, Any]]:
        """The last 200 violations the monitor reported for ``robot`` (default: the
        first), oldest first."""
        name = robot or self.robot
        with self._lock:
            r = self._robots.get(name)
            return [] if r is None else list(r.violations)
