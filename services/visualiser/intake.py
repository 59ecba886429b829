"""What the viewer subscribes to: the raw slots its Zenoh callbacks fill, late join, robots.

A Zenoh callback only stores the raw payload and its receipt time and sets an event of
:class:`~slamlens.services.visualiser.inputs.Wakeups` (O(1), no decoding), so a slow
viewer never slows the estimator or the camera. State, frames, registrations and tracked
poses are kept latest-wins (:class:`~slamlens.common.latest.Latest`); health verdicts in
a bounded FIFO (every verdict feeds the plots). A state's callback keeps only a getter of
its payload (``Bus.subscribe_lazy``), so only the state the pipeline takes is ever copied
out of Zenoh's buffer. Decoding, and everything after it, is the pipeline's
(:mod:`pipeline`).

Several robots: each has its own raw slots, and one registration slot per camera
(``camera/C/registration/R``). Robots are named, or discovered: with ``discover`` every
robot whose estimator is alive (liveliness ``robot/*/alive/estimator``) is added as it
appears, by the ``viewer-discover`` thread (subscriptions and the late-join ``get`` never
run on a Zenoh thread or the render thread). With ``source="summary"`` each robot's
summary is pulled (a :class:`~slamlens.common.summary_pull.SummaryPuller` per robot,
docs/remote_viewers.md) into its state slot instead of a subscription to its state.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from slamlens.common.bus import Bus
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.summary import SummaryQuery
from slamlens.common.summary_pull import SummaryPuller
from slamlens.services.visualiser.inputs import (
    LazyRaw,
    Queue,
    Raw,
    RawCamera,
    RawRobot,
    Wakeups,
)

log = logging.getLogger("slamlens.viewer")


def _store(slot: Latest[Raw]) -> Callable[[str, bytes], None]:
    """A bus callback that only stores the payload (no decoding on Zenoh's thread)."""

    def callback(_key: str, payload: bytes) -> None:
        slot.put(Raw(payload, time.monotonic()))

    return callback


def _store_lazy(slot: Latest[Raw | LazyRaw]) -> Callable[[str, Callable[[], bytes]], None]:
    """A lazy bus callback that only stores the payload's getter (no copy, no decoding)."""

    def callback(_key: str, fetch: Callable[[], bytes]) -> None:
        slot.put(LazyRaw(fetch, time.monotonic()))

    return callback


class Intake:
    """Subscribes to the robots' state, health and tracked pose and to the cameras.

    ``robots`` are subscribed at :meth:`start`; with ``discover`` every robot whose
    estimator is alive is added as it appears. Filling a slot sets an event of
    ``wakeups``: a state ``state``, a frame ``frame``, a health verdict or registration
    ``input``; the tracked pose wakes nobody (it is drawn with the next state).
    """

    DISCOVER_EVERY_S = 1.0  #: how often the alive estimators are asked for (discover)

    def __init__(self, bus: Bus, *, keys: Keys, wakeups: Wakeups, robots: tuple[str, ...],
                 cameras: tuple[str, ...], late_join_timeout_s: float,
                 discover: bool = False, source: str = "state",
                 summary_query: SummaryQuery | None = None) -> None:
        self.bus = bus
        self.keys = keys
        self.wakeups = wakeups
        #: "state": subscribe to each robot's full state; "summary": pull its summary
        #: stream instead (docs/remote_viewers.md); either fills the robot's state slot
        self.source = source
        self._summary_query = summary_query or SummaryQuery(what="clusters")
        self._puller_of: dict[str, SummaryPuller] = {}  #: by robot
        self._late_join_timeout_s = late_join_timeout_s
        self._discover = discover
        self._named = tuple(robots)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._robots: dict[str, RawRobot] = {}
        self._frame_slots = {c: Latest[Raw](on_put=wakeups.frame.set) for c in cameras}
        #: camera → robot → the registration slot
        self._registration_slots: dict[str, dict[str, Latest[Raw]]] = {c: {} for c in cameras}

    # -- the raw slots (what the pipeline takes) ------------------------------------
    def robots(self) -> tuple[RawRobot, ...]:
        """The robots subscribed so far, in order of arrival."""
        with self._lock:
            return tuple(self._robots.values())

    def cameras(self) -> tuple[RawCamera, ...]:
        """The cameras, each with the registration slots of the robots subscribed so far."""
        with self._lock:
            return tuple(RawCamera(c, slot, dict(self._registration_slots[c]))
                         for c, slot in self._frame_slots.items())

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
        """Subscribe, fetch the latest state and registrations (late join), and start
        discovering robots (``discover``)."""
        for camera, slot in self._frame_slots.items():
            self.bus.subscribe(self.keys.frame(camera), _store(slot))
        for robot in self._named:
            self.add_robot(robot)
        if self._discover:
            thread = threading.Thread(target=self._discover_loop, name="viewer-discover",
                                      daemon=True)
            thread.start()
            self._threads.append(thread)

    def add_robot(self, robot: str) -> bool:
        """Subscribe to one more robot and fetch its latest (not on a Zenoh thread: the
        late-join ``get`` waits). False if it was there already."""
        k, wake = self.keys, self.wakeups
        with self._lock:
            if robot in self._robots:
                return False
            r = RawRobot(robot, len(self._robots), Latest(on_put=wake.state.set), Latest(),
                         Queue("health", wake.input.set))
            regs = {c: Latest[Raw](on_put=wake.input.set) for c in self._frame_slots}
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
        for camera, slot in regs.items():
            self.bus.subscribe(k.registration(camera, robot), _store(slot))
        with self._lock:
            self._robots[robot] = r
            for camera, slot in regs.items():
                self._registration_slots[camera][robot] = slot
        self._late_join(r, regs)
        if puller is not None:
            puller.start()
        wake.input.set()
        return True

    def _late_join(self, robot: RawRobot, regs: dict[str, Latest[Raw]]) -> None:
        """Ask the estimator and the cameras for their latest (docs/protocol.md), so a
        viewer that joins late shows the current picture at once."""
        timeout = self._late_join_timeout_s
        if timeout <= 0:
            return
        wanted: list[tuple[str, Latest[Any]]] = (
            [] if self.source == "summary"  # the first pull is answered at once
            else [(self.keys.state(robot.name), robot.state_slot)])
        wanted += [(self.keys.registration(c, robot.name), slot) for c, slot in regs.items()]
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
                if robot and not self._has(robot) and not self._stop.is_set():
                    log.info("robot %s: its estimator is alive; shown from now on", robot)
                    self.add_robot(robot)
            self._stop.wait(self.DISCOVER_EVERY_S)

    def _has(self, robot: str) -> bool:
        with self._lock:
            return robot in self._robots

    def stop(self) -> None:
        self._stop.set()
        with self._lock:
            pullers = list(self._puller_of.values())
        for puller in pullers:  # all told first; a query in flight ends with the bus
            puller.stop(timeout=0.0)
        for puller in pullers:
            puller.stop(timeout=0.5)
        for thread in self._threads:
            thread.join(timeout=5.0)
