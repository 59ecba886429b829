"""The render thread's first step of every cycle: take in what arrived, remember it.

:class:`TakeIn` moves what arrived since the last cycle into the store: each robot's
prepared state (decoded by the stages, :mod:`stages`), its tracked pose and health
verdicts, and every registration, decoded here (:mod:`decoding`); it returns what was new
(:class:`~slamlens.services.visualiser.inputs.Arrivals`). :func:`remember` hands that to
the parts that keep a history: a robot's path, tracked-pose match and plots
(:mod:`robots`), the map view's bounds; a new map empties them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from slamlens.common.drops import DropCounter
from slamlens.common.messages import Health, Registration, SlamState, Truth
from slamlens.services.visualiser.decoding import decode, decode_health, drawable_registration
from slamlens.services.visualiser.inputs import (
    Arrivals,
    Prepared,
    RawRobot,
    RawSource,
    RobotArrivals,
)
from slamlens.services.visualiser.robots import RobotHistories
from slamlens.services.visualiser.series import DENSE_PAIRS, PlotSampler
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.store import InputStore
from slamlens.services.visualiser.summary_view import SummarisedState
from slamlens.services.visualiser.views import EyeChooser


class TakeIn:
    """What arrived since the last call, decoded into ``store`` (module docstring)."""

    def __init__(self, raw: RawSource, store: InputStore, *,
                 prepared: Callable[[str], Prepared | None], drops: DropCounter,
                 max_frame_pixels: int) -> None:
        self._raw = raw
        self._store = store
        self._prepared = prepared
        self._drops = drops
        self._max_frame_pixels = max_frame_pixels

    def __call__(self) -> Arrivals:
        robots = self._raw.robots()
        for r in robots:  # the robots subscribed since the last call are shown from now on
            self._store.add_robot(r.name, r.index)
        out = []
        for r in robots:
            state, restarted = self._state(r.name)
            tracked = None
            raw_tracked = r.tracked_slot.take()
            if raw_tracked is not None:
                tracked = decode("tracked", raw_tracked, Truth.from_bytes, self._drops)
            healths = self._healths(r)
            if state is not None or tracked is not None or healths:
                out.append(RobotArrivals(r.name, state, restarted, tracked, tuple(healths)))
        for cam in self._raw.cameras():
            for robot, slot in cam.registration_slots.items():
                raw_reg = slot.take()
                if raw_reg is None:
                    continue
                reg = decode(f"registration {cam.name}", raw_reg, self._registration,
                             self._drops)
                if reg is not None:
                    self._store.put_registration(cam.name, robot, reg, raw_reg.received)
        return Arrivals(robots=tuple(out))

    def _state(self, robot: str) -> tuple[SlamState | None, bool]:
        item = self._prepared(robot)
        if item is None:
            return None, False
        received, state = item
        if state is None:  # a bad state (counted when it was decoded)
            return None, False
        return state, self._store.put_state(robot, state, received)

    def _healths(self, r: RawRobot) -> list[Health]:
        healths = []
        for raw in r.health_queue.drain():
            health = decode_health(raw, r.name, self._drops)
            if health is not None:
                self._store.put_health(r.name, health)
                healths.append(health)
        return healths

    def _registration(self, payload: bytes) -> Registration:
        return drawable_registration(payload, max_frame_pixels=self._max_frame_pixels)


def remember(arrivals: Arrivals, *, histories: RobotHistories, eyes: EyeChooser,
             plots: PlotSampler, failures: DropCounter, now: float | None = None) -> None:
    """Hand what arrived to the parts that keep a history of it."""
    now = time.monotonic() if now is None else now
    for arrived in arrivals.robots:
        history = histories.get(arrived.robot)
        state = arrived.state
        if state is not None:
            if arrived.restarted:
                history.new_map()  # a new map: its path, clusters and plots start over
                eyes.restart()
            # the path remembers every state taken in, drawn or not: views render
            # only on demand, and a path started at the first render would be short
            history.renderer.track(state.robot, state.seq, state.pose[:2], state.epoch)
            history.tracked.add_estimate(state.stamp, state.pose)
            try:
                if isinstance(state, SummarisedState):  # no cross terms: no P_d
                    pass
                elif state.n * (state.n - 1) // 2 > DENSE_PAIRS:  # a large map
                    if history.series.due(now):  # off this thread: it only hands over
                        plots.offer(history.series, state, now)
                else:
                    history.series.add_state(state, now=now)
            except Exception as exc:  # the plots are optional; the picture is not
                failures.drop("plots", f"state seq {state.seq}: {exc!r}")
        if arrived.tracked is not None:
            history.tracked.set_tracked(arrived.tracked)
        for health in arrived.healths:
            history.series.add_health(health, now=now)


#: what a ``--source summary`` query asks for: (robot, selected feature, selected cluster)
SummaryChoice = tuple[str | None, int | None, int | None]


def summary_choice(looked_at: Sequence[tuple[float, ViewSettings]]) -> SummaryChoice:
    """``--source summary``: the selection (a feature or a cluster) of the open view
    touched last that has one — its pairs are pulled at full detail from the robot — or
    none (the clusters). ``looked_at``: (when touched, settings) of each open view."""
    selected = [(touched, s) for touched, s in looked_at
                if s.selected_feature is not None or s.selected_cluster is not None]
    if not selected:
        return None, None, None
    s = max(selected, key=lambda v: v[0])[1]
    return s.selected_robot, s.selected_feature, s.selected_cluster
