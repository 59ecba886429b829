"""Which map a camera's registration places, and why each registration was made.

Maps (docs/delivery.md, epochs): a :class:`MapFollower` watches the robot's state header
(epoch, origin_stamp, pose). The first map it sees keeps the registration made while the
robot stood still; a new map (a new epoch) is registered from the remembered frame nearest
its ``origin_stamp`` — where the robot stood when that map started. A requested
re-registration that would move the map frame by more than ``max_reregister_move_m`` /
``max_reregister_turn_deg`` while the robot is not at its map origin is refused, with the
reason, and the old one kept. Only the header is read of a state, and a state is copied
out of Zenoh's buffer only when its header is read: at most every
:data:`STATE_HEAD_EVERY_S` (a 32 MB state at n = 1000 costs ~20 ms of CPU to copy, and the
estimator publishes tens a second; docs/registration.md, "Maps").

Pure bookkeeping on the camera's :class:`~slamlens.services.registration.tracking.Registrar`:
no bus; the pipeline (:mod:`~slamlens.services.registration.pipeline`) calls it from its
processing thread, and a Zenoh callback only offers states.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from slamlens.common.arrays import decode_array
from slamlens.common.errors import MessageError
from slamlens.common.latest import Latest
from slamlens.common.messages import peek_fields
from slamlens.services.registration.tracking import Registrar, frame_change

log = logging.getLogger("slamlens.services.registration.service")

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


class Counts(Protocol):
    """The camera's counters a :class:`MapFollower` keeps up to date."""

    registrations: int
    refused: int


class MapFollower:
    """The map a camera's registration is for, and the reason of each (module docstring)."""

    def __init__(self, settings: CameraSettings, registrar: Registrar, counts: Counts) -> None:
        self.settings = settings
        self.camera, self.robot = settings.camera, settings.robot
        self.registrar = registrar
        self.stats = counts
        #: the robot's newest state, still in Zenoh's buffer: a call copies it out
        self._states: Latest[Callable[[], bytes]] = Latest()
        self._head_read_at = -math.inf  #: when follow last read a state's header
        self.map: MapHead | None = None  #: the map the registration is for
        self._waiting: MapHead | None = None  #: a new map not registered yet
        self.pending_request: tuple[str, np.ndarray | None] | None = None
        self.reason = "start"  #: why the current registration was made
        self.change: tuple[float, float] | None = None  #: how far it moved the frame

    def offer_state(self, fetch: Callable[[], bytes]) -> None:
        """The robot's newest state, as a function that copies it out (a Zenoh thread)."""
        self._states.put(fetch)

    @property
    def epoch(self) -> int | None:
        """The map epoch the current registration is for (None before a state is seen)."""
        return None if self.map is None else self.map.epoch

    def inherit(self, epoch: int | None, camera: str) -> None:
        """The registrar was given ``camera``'s registration of map ``epoch``."""
        if epoch is not None:
            self.map = MapHead(epoch=epoch, origin_stamp=None, pose=None)
        self.reason, self.change = f"from camera {camera}", None
        self.stats.registrations += 1

    def request(self, requester: str) -> None:
        """Re-register from the next frames; the old registration kept to compare."""
        T = self.registrar.T_anchor_from_map
        self.pending_request = (requester, None if T is None else T.copy())
        self.registrar.reset()
        log.info("camera %s: re-registering robot %s from the next frames (requested by "
                 "%s)", self.camera, self.robot, requester)

    def registered_now(self) -> bool:
        """A registration from still frames just completed (a start, or a request);
        False if it was a request refused (and undone)."""
        self.stats.registrations += 1
        request, self.pending_request = self.pending_request, None
        if request is None:
            self.reason, self.change = "start", None
            log.info("camera %s: robot %s registered (reprojection error %.3f px)",
                     self.camera, self.robot, self.registrar.reprojection_error_px)
            return True
        requester, old = request
        if old is None:
            self.reason, self.change = f"requested by {requester}", None
            return True
        assert self.registrar.T_anchor_from_map is not None
        change = frame_change(old, self.registrar.T_anchor_from_map)
        s = self.settings
        # (no estimate of the robot known — no estimator — then nothing says it moved)
        pose = None if self.map is None else self.map.pose
        away = pose is not None and (float(np.hypot(pose[0], pose[1])) > s.origin_tolerance_m
                                     or abs(math.degrees(float(pose[2])))
                                     > s.max_reregister_turn_deg)
        if (change.moved_m > s.max_reregister_move_m
                or change.moved_deg > s.max_reregister_turn_deg) and away:
            assert pose is not None
            self.registrar.T_anchor_from_map = old  # refused: keep the registration we had
            self.reason = (f"refused a re-registration requested by {requester}: it would "
                            f"move the map frame {change.moved_m:.2f} m / "
                            f"{change.moved_deg:.1f}° while the robot is "
                            f"{float(np.hypot(pose[0], pose[1])):.2f} m from its map origin")
            self.change = None
            self.stats.refused += 1
            self.stats.registrations -= 1
            log.warning("camera %s: %s", self.camera, self.reason)
            return False
        self.reason = f"requested by {requester}"
        self.change = (change.moved_m, change.moved_deg)
        log.info("camera %s: robot %s re-registered (requested by %s): the map frame moved "
                 "%.3f m / %.2f°", self.camera, self.robot, requester, change.moved_m,
                 change.moved_deg)
        return True

    def follow(self) -> np.ndarray | None:
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
        if self.map is None or head.epoch == self.map.epoch:
            if self.map is None:  # the first map: registered while the robot stood still
                log.info("camera %s: registration is for map epoch %d", self.camera,
                         head.epoch)
            self.map = head
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
        old_epoch = self.map.epoch
        self.map = head
        if change is None and not self.registrar.registered:
            return None
        if change is None:
            # no frame of that instant (the marker was not seen, or camera and robot do not
            # share a clock): register from the next still frames instead
            self.pending_request = None
            self.registrar.reset()
            self.reason = "new map (registered from the next frames: none of its origin)"
            log.warning("camera %s: map restarted (epoch %d → %d) but no frame near its "
                        "origin instant t = %.3f s; re-registering from the next frames",
                        self.camera, old_epoch, head.epoch, head.origin_stamp)
            return None
        self.stats.registrations += 1
        self.reason, self.change = "new map", (change.moved_m, change.moved_deg)
        log.info("camera %s: map restarted (epoch %d → %d): registered at its origin instant "
                 "t = %.3f s; the map frame moved %.3f m / %.1f°", self.camera, old_epoch,
                 head.epoch, head.origin_stamp, change.moved_m, change.moved_deg)
        # a fixed camera is its own anchor; a moving one gets it right from the next frame
        return None if self.settings.moving else self.registrar.T_anchor_from_map

