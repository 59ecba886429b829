"""What a :class:`~slamlens.services.visualiser.render.Renderer` keeps between pictures.

A camera's frames come faster than states, and several views draw the same state, so what
a state shows is computed once and reused for every picture of it:

* :class:`SceneCache` — per state, its scenes (pairs, glyphs, the overview) per settings
  and flagged pairs, and its stable cluster ids per clustering (the cluster trackers
  advance once per state, however many pictures are drawn of it); per selection, the
  overview note of the last picture (for the web page);
* :class:`LayerCache` — per state, its drawing onto layers per settings, camera, drawn
  health and notes;
* :class:`FloorCache` — the map view's floor and grid, per camera and colour.

Values are kept for the :data:`STATES_KEPT` newest states (:class:`PerState`). Each cache
has its own lock: the viewer's threads share one renderer, and nothing is computed while
a lock is held but the cluster trackers' update.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from collections.abc import Hashable
from typing import Generic, TypeVar

import numpy as np

from slamlens.common.clusters import ClusterTracker, cluster_labels
from slamlens.common.messages import SlamState
from slamlens.services.visualiser.scene import Scene, build_scene, plan_overview
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.summary_view import SummarisedState, summary_scene

T = TypeVar("T")

MAX_TRACKERS = 8  #: one per distinct clustering setting in use, oldest dropped
MAX_SCENES = 16  #: scenes kept per state (distinct settings of open views)
#: states whose scenes, cluster ids and layers are kept: the one drawn, the one being drawn
#: onto layers (viewer-layers), the one being prepared (viewer-prepare)
STATES_KEPT = 3
MAX_LAYERS = 4  #: drawn layers kept per state (distinct settings and cameras of open views)
MAX_OVERVIEW_NOTES = 64  #: overview notes kept (distinct selections)


class PerState(Generic[T]):
    """Values computed from a state, kept for the :data:`STATES_KEPT` newest states (the
    one drawn, the one on layers, the one being prepared) and at most ``per_state`` keys
    of each, oldest out first (``touch``: a key used again counts as new). States are
    held, not only their ids, so an id is never reused while it is a key. Not locked: its
    owner holds its own lock.
    """

    def __init__(self, per_state: int, *, touch: bool = False) -> None:
        self._per_state = per_state
        self._touch = touch
        self._states: OrderedDict[int, tuple[SlamState, OrderedDict[Hashable, T]]] = \
            OrderedDict()

    def get(self, state: SlamState, key: Hashable) -> T | None:
        held = self._states.get(id(state))
        if held is None or held[0] is not state or key not in held[1]:
            return None
        if self._touch:
            held[1].move_to_end(key)
        return held[1][key]

    def put(self, state: SlamState, key: Hashable, value: T) -> None:
        held = self._states.get(id(state))
        if held is None or held[0] is not state:
            held = self._states[id(state)] = (state, OrderedDict())
            while len(self._states) > STATES_KEPT:  # older states are done
                self._states.popitem(last=False)
        held[1][key] = value
        while len(held[1]) > self._per_state:
            held[1].popitem(last=False)

    def clear(self) -> None:
        self._states.clear()


class SceneCache:
    """A state's scenes and stable cluster ids, and the overview notes (module docstring)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._trackers: OrderedDict[tuple[float, int], ClusterTracker] = OrderedDict()
        #: the last clustering's (landmark ids, stable cluster ids) per clustering
        self._cluster_of: dict[tuple[float, int], tuple[np.ndarray, np.ndarray]] = {}
        #: the overview note of the last picture per selection/budget (for the web page)
        self._overviews: OrderedDict[tuple[object, ...], str] = OrderedDict()
        #: per state and settings and flagged pairs: a picture of the same state again (a
        #: new camera frame, another tab) reuses its scene
        self._scenes: PerState[Scene] = PerState(MAX_SCENES, touch=True)
        #: per state and clustering (one tracker update per state)
        self._clustered: PerState[np.ndarray] = PerState(MAX_TRACKERS)
        self.built = 0  #: scenes computed (the rest were reused)

    def clear(self) -> None:
        """A new map: forget the cluster identities and the scenes."""
        with self._lock:
            self._trackers.clear()
            self._cluster_of.clear()
            self._clustered.clear()
            self._scenes.clear()

    def cluster_ids(self, state: SlamState, settings: ViewSettings) -> np.ndarray:
        """Stable cluster id per landmark of ``state`` under ``settings``' clustering (the
        same state asked again: the same ids, clustered once)."""
        key = (settings.cluster_threshold_m, settings.cluster_count)
        with self._lock:
            kept = self._clustered.get(state, key)
        if kept is not None:
            return kept
        labels = cluster_labels(state.landmarks, threshold_m=settings.cluster_threshold_m,
                                count=settings.cluster_count)
        with self._lock:
            tracker = self._trackers.get(key)
            if tracker is None:
                tracker = self._trackers[key] = ClusterTracker()
                while len(self._trackers) > MAX_TRACKERS:
                    self._trackers.popitem(last=False)
            self._trackers.move_to_end(key)
            stable = tracker.update(state.landmark_ids, labels)
            self._cluster_of[key] = (np.asarray(state.landmark_ids), stable)
            self._clustered.put(state, key, stable)
            return stable

    def known_cluster_ids(self, settings: ViewSettings
                          ) -> tuple[np.ndarray, np.ndarray] | None:
        """(landmark ids, their stable cluster ids) of the last state clustered as
        ``settings`` clusters, or None (none clustered yet)."""
        with self._lock:
            return self._cluster_of.get((settings.cluster_threshold_m, settings.cluster_count))

    def scene(self, state: SlamState, settings: ViewSettings,
              violating: frozenset[tuple[int, int]] = frozenset()) -> Scene:
        """What ``state`` shows under ``settings`` with ``violating`` pairs flagged,
        computed once and then reused for every picture of that state."""
        key = (settings, violating)
        with self._lock:
            kept = self._scenes.get(state, key)
        if kept is not None:
            return kept
        if isinstance(state, SummarisedState):  # --source summary: the robot's picture
            scene = summary_scene(state, settings, violating)
        else:
            n = state.n
            # the clusters: for the clustered modes, a selected cluster, and the glyph
            # budget (a mode whose pairs exceed it draws the min/mean/max overview instead)
            over_budget = (settings.glyph_budget > 0 and settings.mode == "all"
                           and n * (n - 1) // 2 > settings.glyph_budget
                           and settings.selected_feature is None
                           and settings.selected_cluster is None)
            clustered = (settings.mode in ("inter", "minmeanmax") or over_budget
                         or settings.selected_cluster is not None)
            cluster_ids = self.cluster_ids(state, settings) if clustered else None
            plan = plan_overview(state, settings, cluster_ids)
            scene = build_scene(state, settings, cluster_ids=cluster_ids,
                                violating_pairs=violating, plan=plan)
        with self._lock:
            self._scenes.put(state, key, scene)
            self.built += 1
        return scene

    def note_overview(self, settings: ViewSettings, note: str) -> None:
        """What the picture being drawn under ``settings`` shows instead of its pairs."""
        key = _overview_key(settings)
        with self._lock:
            self._overviews[key] = note
            self._overviews.move_to_end(key)
            while len(self._overviews) > MAX_OVERVIEW_NOTES:
                self._overviews.popitem(last=False)

    def overview_note(self, settings: ViewSettings) -> str:
        """The note of the last picture drawn under ``settings`` (the glyph budget), or ""."""
        with self._lock:
            return self._overviews.get(_overview_key(settings), "")


class LayerCache(Generic[T]):
    """A state's drawing onto layers, per key (settings, camera, drawn health, notes)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._layers: PerState[T] = PerState(MAX_LAYERS)
        self.built = 0  #: states drawn onto layers (the rest were reused)
        #: the same, by the name of the thread that drew them (the viewer draws them on
        #: viewer-layers, so that viewer-render only puts them over camera frames)
        self.built_on: Counter[str] = Counter()

    def get(self, state: SlamState, key: Hashable) -> T | None:
        with self._lock:
            return self._layers.get(state, key)

    def put(self, state: SlamState, key: Hashable, layers: T) -> None:
        """Keep ``layers``, drawn on this thread."""
        with self._lock:
            self._layers.put(state, key, layers)
            self.built += 1
            self.built_on[threading.current_thread().name] += 1

    def clear(self) -> None:
        with self._lock:
            self._layers.clear()


class FloorCache:
    """The map view's floor (its grid drawn), for the last camera and colour asked."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._floor: tuple[Hashable, np.ndarray] | None = None

    def get(self, key: Hashable) -> np.ndarray | None:
        with self._lock:
            kept = self._floor
        return kept[1] if kept is not None and kept[0] == key else None

    def put(self, key: Hashable, floor: np.ndarray) -> None:
        with self._lock:
            self._floor = (key, floor)


def _overview_key(settings: ViewSettings) -> tuple[object, ...]:
    return (settings.mode, settings.glyph_budget, settings.cluster_threshold_m,
            settings.cluster_count, settings.selected_feature, settings.selected_cluster,
            settings.selected_robot)
