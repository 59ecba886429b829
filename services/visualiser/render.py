"""The AR renderer: the estimator's state drawn over a camera picture (SPEC §6, paper §3.2).

Drawing order:

1. the floor layer: map grid (map view only), cluster outlines, robot path, pair lines,
   heading arrow: flat on the floor, so everything standing on the floor covers them;
2. the 3D objects, glyphs and cones, far to near by camera depth (painter's algorithm);
3. overlays that must never be hidden: health outlines and rings, labels, the legend.

Each step draws on a :class:`Canvas`: the picture, its camera, the state and its scene,
the settings and the line width unit, shared by every step of one picture. Over a camera
picture the steps draw on two layers once per state (:meth:`Renderer.layers`: steps 1–2,
and 3 but the camera-tracked pose, which is drawn between them on each frame), which are
then put over every camera frame until the next state (:mod:`draw`, layers).

``Renderer`` keeps only what needs history: the robot's path (reset when the robot changes
or ``seq`` goes backwards; drawn incrementally per view, :mod:`trail`) and the cluster
trackers that keep cluster ids and colours stable from frame to frame. Use one
``Renderer`` per robot; it may be shared by threads.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import Counter, OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import cv2
import numpy as np

from slamlens.common.clusters import ClusterTracker, cluster_colour, cluster_labels
from slamlens.common.messages import Health, SlamState
from slamlens.common.verdict import summary_text
from slamlens.services.visualiser import draw
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.glyphs import ImageEllipses, project_ellipsoids
from slamlens.services.visualiser.scene import (
    ROLE_NAMES,
    ROLE_PAIR,
    Scene,
    build_scene,
    plan_overview,
)
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.summary_view import SummarisedState, summary_scene
from slamlens.services.visualiser.trail import Trail

T = TypeVar("T")

_MAX_TRACKERS = 8  # one per distinct clustering setting in use, oldest dropped
_MAX_SCENES = 16  # scenes kept per state (distinct settings of open views)
#: states whose scenes, cluster ids and layers are kept: the one drawn, the one being drawn
#: onto layers (viewer-layers), the one being prepared (viewer-prepare)
_STATES_KEPT = 3
_MAX_LAYERS = 4  # drawn layers kept per state (distinct settings and cameras of open views)
#: states of at least this many features are drawn onto layers over a camera (below, a
#: state is cheap to draw and usually comes faster than camera frames: drawn straight)
LAYERS_FROM_N = 200
_AA_LINES_LIMIT = 400  # anti-aliased pair lines up to this many, plain beyond (frame time)
_AA_GLYPH_LIMIT = 400  # same for the inner shading layers of glyphs
#: "min" / "mean" / "max" labels up to this many glyphs (beyond: the legend says where)
MAX_ROLE_LABELS = 30


@dataclass(frozen=True, eq=False)
class Canvas:
    """One picture being drawn, and what every drawing step of it shares."""

    img: np.ndarray  #: BGR uint8, drawn in place
    camera: CameraModel  #: the camera, fitted to ``img``'s size
    state: SlamState  #: the state drawn
    scene: Scene  #: what of it is drawn under ``settings`` (pairs, glyphs, lines)
    settings: ViewSettings
    px: int  #: line width unit for this resolution (1 up to 720 rows, 2 at 1440, …)


@dataclass(frozen=True, eq=False)
class _Lines:
    """The pair lines as drawn: image polylines and, for each, its index in the scene."""

    polylines: list[np.ndarray]
    index: np.ndarray


@dataclass(frozen=True, eq=False)
class _Glyphs:
    """The glyphs' projections, those on screen, and their shaded drawing (if drawn)."""

    ellipses: ImageEllipses  #: every scene glyph, projected
    shown: np.ndarray  #: indices of the glyphs on screen
    shaded: draw.ShadedEllipses | None  #: None when ellipsoids are off or there are none


class _PerState(Generic[T]):
    """Values computed from a state, kept for the :data:`_STATES_KEPT` newest states (the
    one drawn, the one on layers, the one being prepared) and at most ``per_state`` keys
    of each, oldest out first (``touch``: a key used again counts as new). States are
    held, not only their ids, so an id is never reused while it is a key. The caller
    holds the renderer's lock.
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
            while len(self._states) > _STATES_KEPT:  # older states are done
                self._states.popitem(last=False)
        held[1][key] = value
        while len(held[1]) > self._per_state:
            held[1].popitem(last=False)

    def clear(self) -> None:
        self._states.clear()


class Renderer:
    """Draws ``SlamState`` (and ``Health``) over a picture; see the module docstring."""

    def __init__(self, *, layers_from_n: int = LAYERS_FROM_N) -> None:
        #: over a camera, states of at least this many features are drawn onto layers
        self.layers_from_n = layers_from_n
        self._lock = threading.Lock()
        self._path = Trail()
        self._trackers: OrderedDict[tuple[float, int], ClusterTracker] = OrderedDict()
        self._floor: tuple[tuple[object, ...], np.ndarray] | None = None  # map view cache
        self._cluster_of: dict[tuple[float, int], tuple[np.ndarray, np.ndarray]] = {}
        #: the overview note of the last picture per selection/budget (for the web page)
        self._overviews: OrderedDict[tuple[object, ...], str] = OrderedDict()
        #: the scenes of the two newest states (the one drawn, the one being prepared),
        #: per settings and flagged pairs: a picture of the same state again (a new
        #: camera frame, another tab) reuses its scene
        self._scenes: _PerState[Scene] = _PerState(_MAX_SCENES, touch=True)
        #: the stable cluster ids of the two newest states per clustering (one tracker
        #: update per state, however many pictures are drawn of it)
        self._clustered: _PerState[np.ndarray] = _PerState(_MAX_TRACKERS)
        self.scenes_built = 0  #: scenes computed (the rest were reused)
        #: the newest states drawn as layers, per settings, camera, health and notes
        self._layers: _PerState[Layers] = _PerState(_MAX_LAYERS)
        self.layers_built = 0  #: states drawn onto layers (the rest were reused)
        #: the same, by the name of the thread that drew them (the viewer draws them on
        #: viewer-layers, so that viewer-render only puts them over camera frames)
        self.layers_built_on: Counter[str] = Counter()

    # -- history --------------------------------------------------------------------
    def reset_path(self) -> None:
        with self._lock:
            self._path.reset()
            self._layers.clear()  # they show the old path

    def new_map(self) -> None:
        """A new map began (another epoch): forget the path and the cluster identities."""
        with self._lock:
            self._path.reset(forget_robot=True)
            self._trackers.clear()
            self._cluster_of.clear()
            self._clustered.clear()
            self._scenes.clear()
            self._layers.clear()

    @property
    def path_xy(self) -> np.ndarray:
        """The remembered path (k, 2), m, map frame."""
        return self._path.points()

    def track(self, robot: str, seq: int, xy: np.ndarray, epoch: int = 0) -> None:
        """Add a position to the path without drawing (for callers that draw only some
        states, e.g. a viewer whose latest-wins input skips states)."""
        self._path.track(robot, seq, (float(xy[0]), float(xy[1])), epoch)

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
                while len(self._trackers) > _MAX_TRACKERS:
                    self._trackers.popitem(last=False)
            self._trackers.move_to_end(key)
            stable = tracker.update(state.landmark_ids, labels)
            self._cluster_of[key] = (np.asarray(state.landmark_ids), stable)
            self._clustered.put(state, key, stable)
            return stable

    def known_cluster_ids(self, settings: ViewSettings
                          ) -> tuple[np.ndarray, np.ndarray] | None:
        """(landmark ids, their stable cluster ids) of the last picture clustered as
        ``settings`` clusters, or None (none clustered yet)."""
        with self._lock:
            return self._cluster_of.get((settings.cluster_threshold_m, settings.cluster_count))

    def overview_note(self, settings: ViewSettings) -> str:
        """What the last picture drawn under ``settings`` showed instead of its pairs (the
        glyph budget), or "" — for the web page's note."""
        with self._lock:
            return self._overviews.get(_overview_key(settings), "")

    def scene(self, state: SlamState, settings: ViewSettings,
              violating: frozenset[tuple[int, int]] = frozenset()) -> Scene:
        """What ``state`` shows under ``settings`` (pairs, glyphs, the overview): computed
        once per state, settings and flagged pairs, then reused for every picture of that
        state (the camera's frames come faster than states; issue 13)."""
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
            self.scenes_built += 1
        return scene

    def prepare(self, state: SlamState, settings: ViewSettings,
                health: Health | None = None) -> None:
        """Compute the scene a picture of ``state`` under ``settings`` will draw (off the
        render thread: the viewer's ``viewer-prepare``)."""
        violating = _health_sets(health if settings.health else None, state)[0]
        self.scene(state, settings, violating)

    # -- drawing --------------------------------------------------------------------
    def _floor_image(self, camera: CameraModel,
                     settings: ViewSettings) -> tuple[np.ndarray, CameraModel]:
        """The map view's floor and grid: drawn once per camera and colour, then copied."""
        key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(),
               camera.T_camera_from_map.tobytes(), settings.colour_background)
        with self._lock:
            cached = self._floor
        if cached is None or cached[0] != key:
            pixel = np.array(settings.colour_background, dtype=np.uint8)
            floor = np.ascontiguousarray(
                np.broadcast_to(pixel, (camera.height, camera.width, 3)))
            _draw_grid(floor, camera)
            cached = (key, floor)
            with self._lock:
                self._floor = cached
        return cached[1].copy(), camera

    def render(self, image_bgr: np.ndarray | None, *, state: SlamState, camera: CameraModel,
               settings: ViewSettings, health: Health | None = None,
               reference_pose: np.ndarray | None = None,
               reference_estimate: np.ndarray | None = None,
               notes: Sequence[LegendRow] = ()) -> np.ndarray:
        """A new BGR uint8 picture: ``image_bgr`` (or the map view's floor) with the state.

        The camera is rescaled if the image's size differs from the camera's.
        ``reference_pose`` (x, y, θ in the map frame) is an independent measurement of the
        robot — the camera-tracked pose or the simulator's truth — drawn as a white ring
        joined to the estimate of the same instant (``reference_estimate``; the state's own
        pose if not given), with the position error written beside it. ``notes`` are extra
        legend rows (e.g. "map restarted").

        Over a camera picture a state of ``layers_from_n`` features or more is drawn once
        onto two layers (:mod:`draw`: under and over the reference pose, which moves with
        every camera frame) and put over each new frame of the same state, settings and
        camera (issue 13: at n = 1000 drawing 1000 cones and the overview per camera frame
        cost more than the frames are apart); a smaller one is drawn straight.
        """
        if image_bgr is None or not self.layered(state):
            img, camera = self.background(image_bgr, camera, settings)
            drawn = self.draw(img, state=state, camera=camera, settings=settings,
                              health=health, reference_pose=reference_pose,
                              reference_estimate=reference_estimate)
            if settings.legend:
                _draw_legend(drawn.canvas, health=health, glyphs_shown=drawn.glyphs_shown,
                             notes=[*rejected_legend(state, settings), *notes])
            return img
        img, camera = _bgr_copy(image_bgr, camera)
        layers = self.layers(state, camera, settings, health, notes)
        layers.under.put_over(img)
        if settings.robot and reference_pose is not None:
            c = Canvas(img, camera, state, layers.scene, settings,
                       px=max(1, round(camera.height / 720)))
            estimate = state.pose if reference_estimate is None else reference_estimate
            _draw_reference(c, estimate=np.asarray(estimate, float),
                            reference=np.asarray(reference_pose, float))
        layers.over.put_over(img)
        return img

    def layered(self, state: SlamState) -> bool:
        """Whether a picture of ``state`` over a camera is put together from its layers."""
        return state.n >= self.layers_from_n

    def layers(self, state: SlamState, camera: CameraModel, settings: ViewSettings,
               health: Health | None = None, notes: Sequence[LegendRow] = ()) -> Layers:
        """The state drawn under ``settings`` through ``camera`` (fitted to the picture's
        size) as two layers (:meth:`render`): drawn once per state, settings, camera,
        health drawn and notes, then reused (the viewer's ``viewer-layers`` thread draws
        them before the render thread needs them)."""
        violating, suspects = _health_sets(health if settings.health else None, state)
        shown_health = (summary_text(health) if settings.health and health is not None
                        else None)
        key = (settings, _camera_key(camera), violating, suspects.tobytes(), shown_health,
               tuple(tuple(row) for row in notes))
        with self._lock:
            kept = self._layers.get(state, key)
        if kept is not None:
            return kept
        scene, c_under = self._canvas(draw.new_layer(camera.height, camera.width),
                                      state, camera, settings, violating)
        lines, glyphs = _draw_under(c_under, self._path)
        c_over = dataclasses.replace(c_under, img=draw.new_layer(camera.height, camera.width))
        rejected = _draw_over(c_over, glyphs=glyphs, lines=lines, suspects=suspects)
        if settings.legend:
            _draw_legend(c_over, health=health, glyphs_shown=len(glyphs.shown),
                         notes=[*rejected_legend(state, settings), *notes])
        out = Layers(draw.Overlay(c_under.img), draw.Overlay(c_over.img), scene,
                     len(glyphs.shown), rejected)
        with self._lock:
            self._layers.put(state, key, out)
            self.layers_built += 1
            self.layers_built_on[threading.current_thread().name] += 1
        return out

    def background(self, image_bgr: np.ndarray | None, camera: CameraModel,
                   settings: ViewSettings) -> tuple[np.ndarray, CameraModel]:
        """The picture to draw on (a copy of ``image_bgr``, or the map view's floor) and
        the camera fitted to its size."""
        return (self._floor_image(camera, settings) if image_bgr is None
                else _bgr_copy(image_bgr, camera))

    def _canvas(self, img: np.ndarray, state: SlamState, camera: CameraModel,
                settings: ViewSettings, violating: frozenset[tuple[int, int]]
                ) -> tuple[Scene, Canvas]:
        """The scene and a canvas on ``img`` for drawing ``state`` (its pose added to the
        path)."""
        camera = camera.resized(img.shape[1], img.shape[0])
        self._path.track(state.robot, state.seq, (float(state.pose[0]), float(state.pose[1])),
                         state.epoch)
        scene = self.scene(state, settings, violating)
        with self._lock:
            key = _overview_key(settings)
            self._overviews[key] = scene.overview
            self._overviews.move_to_end(key)
            while len(self._overviews) > 64:
                self._overviews.popitem(last=False)
        c = Canvas(img, camera, state, scene, settings, px=max(1, round(camera.height / 720)))
        return scene, c

    def draw(self, img: np.ndarray, *, state: SlamState, camera: CameraModel,
             settings: ViewSettings, health: Health | None = None,
             reference_pose: np.ndarray | None = None,
             reference_estimate: np.ndarray | None = None) -> Drawn:
        """Draw the state onto ``img`` in place (everything but the legend): one robot of a
        picture that may show several, each with its own renderer and camera."""
        violating, suspects = _health_sets(health if settings.health else None, state)
        _, c = self._canvas(img, state, camera, settings, violating)
        lines, glyphs = _draw_under(c, self._path)
        if settings.robot and reference_pose is not None:
            estimate = state.pose if reference_estimate is None else reference_estimate
            _draw_reference(c, estimate=np.asarray(estimate, float),
                            reference=np.asarray(reference_pose, float))
        rejected = _draw_over(c, glyphs=glyphs, lines=lines, suspects=suspects)
        return Drawn(c, len(glyphs.shown), rejected)


def _draw_under(c: Canvas, path: Trail) -> tuple[_Lines, _Glyphs]:
    """Steps 1 and 2 (module docstring): the floor layer, then glyphs and cones."""
    settings, scene = c.settings, c.scene
    # outlines: every cluster (or overview group) in the clustered pictures; in "all"
    # pairs only a selected cluster's
    pairwise = settings.mode == "all" and scene.mode == "all"
    outlined = None if pairwise else scene.cluster_ids
    if pairwise and scene.cluster_ids is not None and \
            settings.selected_cluster is not None:
        outlined = np.where(scene.cluster_ids == settings.selected_cluster,
                            settings.selected_cluster, -1)
    lines = _draw_floor_layer(c, path=path, cluster_ids=outlined)
    return lines, _draw_objects(c)


def _draw_over(c: Canvas, *, glyphs: _Glyphs, lines: _Lines, suspects: np.ndarray) -> int:
    """Step 3 but the reference pose and the legend: rejected observations, health,
    labels, roles; returns the number of rejected observations drawn."""
    settings, scene = c.settings, c.scene
    rejected = rejected_observations(c.state) if settings.rejected else np.zeros((0, 2))
    if len(rejected):
        _draw_rejected(c, rejected)
    if settings.health:
        _draw_health(c, glyphs=glyphs, lines=lines, suspects=suspects)
    if settings.labels and settings.features:
        _draw_labels(c)
    if (glyphs.shaded is not None and scene.mode == "minmeanmax"
            and len(glyphs.shown) <= MAX_ROLE_LABELS):
        _draw_roles(c, glyphs)
    return len(rejected)


@dataclass(frozen=True, eq=False)
class Layers:
    """One state drawn for one picture size, settings and camera (:meth:`Renderer.layers`)."""

    under: draw.Overlay  #: floor layer, glyphs and cones
    over: draw.Overlay  #: rejected observations, health, labels, roles, the legend
    scene: Scene
    glyphs_shown: int
    rejected_shown: int


def _camera_key(camera: CameraModel) -> tuple[object, ...]:
    return (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(),
            camera.T_camera_from_map.tobytes())


#: a legend row: [(text, swatch colour or None), …]
LegendRow = list[tuple[str, tuple[int, int, int] | None]]


@dataclass(frozen=True, eq=False)
class Drawn:
    """What :meth:`Renderer.draw` drew: its canvas (for the legend) and the glyph count."""

    canvas: Canvas
    glyphs_shown: int
    rejected_shown: int = 0  #: rejected (gated) observations drawn


#: colours (BGR) of the second, third … robot of one picture; the first robot keeps the
#: settings' (the paper's green); none is red (glyphs), yellow (lines) or magenta (faults)
ROBOT_COLOURS = ((0, 140, 255), (255, 170, 40), (235, 235, 235), (255, 110, 150),
                 (60, 200, 190))


def robot_settings(settings: ViewSettings, index: int) -> ViewSettings:
    """``settings`` for the ``index``-th robot of a picture: the first as given, the others
    with their own colour for the robot, its path and (lighter) its features."""
    if index <= 0:
        return settings
    colour = ROBOT_COLOURS[(index - 1) % len(ROBOT_COLOURS)]
    return settings.replace(colour_robot=colour, colour_path=colour,
                            colour_features=draw.shade(colour, 0.85, 0.4))


@dataclass(frozen=True, eq=False)
class RobotLegend:
    """One robot's rows of a shared legend."""

    state: SlamState
    health: Health | None
    glyphs_shown: int
    colour: tuple[int, int, int]
    notes: Sequence[LegendRow] = ()


def draw_robots_legend(img: np.ndarray, settings: ViewSettings, robots: Sequence[RobotLegend],
                       *, waiting: Sequence[str] = ()) -> None:
    """The legend of a picture of several robots: mode and glyph meaning once, then one
    row per robot (its colour, seq, features, glyphs, verdict) and any notes."""
    rows: list[LegendRow] = [[(f"mode: {_MODE_TEXT[settings.mode]}", None)],
                             [(_glyph_text(settings), settings.colour_ellipsoids)]]
    for r in robots:
        s = r.state
        rows.append([(f"robot {s.robot}", r.colour),
                     (f"seq {s.seq} {s.step}  {s.n} features  {r.glyphs_shown} glyphs", None)])
        if settings.health and r.health is not None:
            rows.append(_health_row(r.health, settings))
        rows += [list(row) for row in r.notes]
    rows += [[(text, None)] for text in waiting]
    draw.text_box(img, rows, scale=max(0.35, 0.45 * img.shape[0] / 720))


def _overview_key(settings: ViewSettings) -> tuple[object, ...]:
    return (settings.mode, settings.glyph_budget, settings.cluster_threshold_m,
            settings.cluster_count, settings.selected_feature, settings.selected_cluster,
            settings.selected_robot)


def side_by_side(left_bgr: np.ndarray, right_bgr: np.ndarray) -> np.ndarray:
    """Left and right pictures in one frame (right scaled to the left's height if needed)."""
    if right_bgr.shape[0] != left_bgr.shape[0]:
        h = left_bgr.shape[0]
        w = max(1, round(right_bgr.shape[1] * h / right_bgr.shape[0]))
        right_bgr = cv2.resize(right_bgr, (w, h), interpolation=cv2.INTER_AREA)
    return np.hstack([left_bgr, right_bgr])


def feature_pixels(state: SlamState, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(ids (n,), pixels (n, 2)) of the feature estimates (cone tips); NaN if not visible."""
    uv, _ = camera.project(np.column_stack([state.landmarks, np.zeros(state.n)]))
    return state.landmark_ids.copy(), uv


def pick_feature(u: float, v: float, *, state: SlamState, camera: CameraModel,
                 radius_px: float = 20.0) -> int | None:
    """The id of the feature whose tip is nearest pixel (u, v) within ``radius_px``."""
    ids, uv = feature_pixels(state, camera)
    if not len(ids):
        return None
    d = np.hypot(uv[:, 0] - u, uv[:, 1] - v)
    d[~np.isfinite(d)] = np.inf
    k = int(np.argmin(d))
    return int(ids[k]) if d[k] <= radius_px else None


# -- helpers ------------------------------------------------------------------------------
def _bgr_copy(image: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, CameraModel]:
    """A BGR uint8 copy of ``image`` to draw on, and the camera fitted to its size."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    else:
        img = img.copy()
    return img, camera.resized(img.shape[1], img.shape[0])


def _health_sets(health: Health | None,
                 state: SlamState) -> tuple[frozenset[tuple[int, int]], np.ndarray]:
    """Violating pairs (min id, max id) and the feature ids to ring (suspects + feature kind);
    none without a Health (or with health drawing off: the caller passes None)."""
    if health is None:
        return frozenset(), np.zeros(0, np.int64)
    pairs = frozenset((min(v.ids), max(v.ids)) for v in health.violations
                      if v.kind == "pair" and len(v.ids) == 2)
    ring = set(health.suspects.tolist())
    ring.update(i for v in health.violations if v.kind == "feature" for i in v.ids)
    present = np.array(sorted(ring), dtype=np.int64)
    return pairs, present[np.isin(present, state.landmark_ids)]


def _on_screen(ie: ImageEllipses, camera: CameraModel) -> np.ndarray:
    a, b, t = ie.axes[:, 0], ie.axes[:, 1], ie.angle
    half_w = np.sqrt((a * np.cos(t)) ** 2 + (b * np.sin(t)) ** 2)
    half_h = np.sqrt((a * np.sin(t)) ** 2 + (b * np.cos(t)) ** 2)
    cu, cv = ie.centre[:, 0], ie.centre[:, 1]
    ok = (ie.valid & (cu + half_w >= 0) & (cu - half_w < camera.width)
          & (cv + half_h >= 0) & (cv - half_h < camera.height))
    return np.flatnonzero(ok)


def _floor_bounds(camera: CameraModel) -> tuple[float, float, float, float] | None:
    """Map-frame xy bounds of the floor seen by an undistorted camera (None: horizon)."""
    corners = np.array([[0, 0], [camera.width, 0], [0, camera.height],
                        [camera.width, camera.height]], dtype=float)
    rays_cam = np.column_stack([corners, np.ones(4)]) @ np.linalg.inv(camera.K).T
    R = camera.T_camera_from_map[:3, :3]
    rays = rays_cam @ R  # = (Rᵀ·ray) per row: directions in the map frame
    origin = camera.centre_map
    if np.any(rays[:, 2] >= 0) or origin[2] <= 0:
        return None
    t = -origin[2] / rays[:, 2]
    pts = origin[:2] + t[:, None] * rays[:, :2]
    return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), \
        float(pts[:, 1].max())


def _draw_grid(img: np.ndarray, camera: CameraModel, *, step_m: float = 0.5) -> None:
    bounds = _floor_bounds(camera)
    if bounds is None:
        return
    xmin, ymin, xmax, ymax = bounds
    if (xmax - xmin) / step_m > 400 or (ymax - ymin) / step_m > 400:
        return
    xs = np.arange(math.floor(xmin / step_m), math.ceil(xmax / step_m) + 1) * step_m
    ys = np.arange(math.floor(ymin / step_m), math.ceil(ymax / step_m) + 1) * step_m
    p0 = np.concatenate([np.column_stack([xs, np.full_like(xs, ys[0]), np.zeros_like(xs)]),
                         np.column_stack([np.full_like(ys, xs[0]), ys, np.zeros_like(ys)])])
    p1 = np.concatenate([np.column_stack([xs, np.full_like(xs, ys[-1]), np.zeros_like(xs)]),
                         np.column_stack([np.full_like(ys, xs[-1]), ys, np.zeros_like(ys)])])
    major = np.concatenate([np.isclose(xs, 0.0), np.isclose(ys, 0.0)])
    b, g, r = (int(c) for c in img[0, 0])
    minor_colour = (min(b + 14, 255), min(g + 14, 255), min(r + 14, 255))
    major_colour = (min(b + 45, 255), min(g + 45, 255), min(r + 45, 255))
    draw.draw_polylines(img, draw.project_segments(camera, p0[~major], p1[~major])[0],
                        colour=minor_colour, thickness=1)
    draw.draw_polylines(img, draw.project_segments(camera, p0[major], p1[major])[0],
                        colour=major_colour, thickness=1)


def _draw_floor_layer(c: Canvas, *, path: Trail,
                      cluster_ids: np.ndarray | None) -> _Lines:
    """Cluster outlines, the robot path, the pair lines and the heading arrow, flat on the
    floor; returns the pair lines as drawn (health outlines the violating ones)."""
    settings = c.settings
    if cluster_ids is not None:
        _draw_cluster_outlines(c, cluster_ids)
    if settings.path:
        path.draw(c.img, c.camera, colour=settings.colour_path, thickness=2 * c.px)
    lines = _Lines([], np.zeros(0, dtype=np.int64))
    lines_xy = c.scene.lines_xy
    if settings.lines and len(lines_xy):
        zeros = np.zeros((len(lines_xy), 1))
        lines = _Lines(*draw.project_segments(c.camera, np.hstack([lines_xy[:, 0], zeros]),
                                              np.hstack([lines_xy[:, 1], zeros])))
        draw.draw_polylines(c.img, lines.polylines, colour=settings.colour_lines,
                            thickness=c.px, line_type=draw.line_type_for(
                                len(lines.polylines), limit=_AA_LINES_LIMIT))
    if settings.robot:
        _draw_heading(c)
    return lines


def _draw_objects(c: Canvas) -> _Glyphs:
    """Glyphs and cones, far to near by camera depth (painter's algorithm)."""
    settings, camera, state = c.settings, c.camera, c.state
    ie = project_ellipsoids(c.scene.glyphs, camera)
    shown = np.zeros(0, dtype=np.int64)
    shaded = None
    if settings.ellipsoids and len(c.scene.glyphs):
        shown = _on_screen(ie, camera)
        shaded = draw.ShadedEllipses(ie, shown, colour=settings.colour_ellipsoids,
                                     max_axis_px=4.0 * (camera.width + camera.height))
    cone_sets: list[draw.Cones] = []
    if settings.features and state.n:
        cone_sets.append(draw.Cones(camera, state.landmarks, height_m=settings.cone_height_m,
                                    radius_m=settings.cone_radius_m,
                                    colour=settings.colour_features))
    if settings.robot:
        cone_sets.append(draw.Cones(camera, state.pose[None, :2],
                                    height_m=1.4 * settings.cone_height_m,
                                    radius_m=1.4 * settings.cone_radius_m,
                                    colour=settings.colour_robot))
    depth = np.concatenate([ie.depth[shown]] + [cones.depth for cones in cone_sets])
    kind = np.concatenate([np.full(len(shown), -1)]
                          + [np.full(len(cones), s) for s, cones in enumerate(cone_sets)])
    item = np.concatenate([np.arange(len(shown))]
                          + [np.arange(len(cones)) for cones in cone_sets])
    lt = draw.line_type_for(len(shown), limit=_AA_GLYPH_LIMIT)
    kinds, items = kind.tolist(), item.tolist()  # Python ints: ~1000 items per picture
    for k in np.argsort(-depth, kind="stable").tolist():
        s, i = kinds[k], items[k]
        if s < 0:
            shaded.draw(c.img, i, line_type=lt)  # type: ignore[union-attr]
        else:
            cone_sets[s].draw(c.img, i)
    return _Glyphs(ie, shown, shaded)


def _draw_cluster_outlines(c: Canvas, cluster_ids: np.ndarray) -> None:
    """A rounded hull around each cluster's features, in the cluster's colour: the convex
    hull of its members grown by a ring of ``pad`` (the hull of the members' hull vertices
    ⊕ the ring, the same polygon as the hull of every member ⊕ the ring), all clusters
    projected in one call (a large map has hundreds, many of one feature)."""
    pad = 2.5 * c.settings.cone_radius_m
    ring = draw.floor_circle(np.zeros(2), pad, vertices=16)[:, :2]
    outlined = cluster_ids >= 0  # the rest are not outlined
    if not outlined.any():
        return
    ids, xy = cluster_ids[outlined], c.state.landmarks[outlined]
    order = np.argsort(ids, kind="stable")
    ids, xy = ids[order], xy[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], len(ids)]
    polygons = []
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        members = xy[s:e]
        if e - s == 1:  # one feature: the ring around it
            polygons.append(members[0] + ring)
            continue
        if e - s > 2:  # only the members' hull vertices can be on the grown hull
            members = members[cv2.convexHull(members.astype(np.float32),
                                             returnPoints=False).ravel()]
        pts = (members[:, None, :] + ring[None]).reshape(-1, 2).astype(np.float32)
        polygons.append(cv2.convexHull(pts).reshape(-1, 2).astype(float))
    bounds = np.r_[0, np.cumsum([len(p) for p in polygons])]
    flat = np.concatenate(polygons)
    uv, _ = c.camera.project(np.column_stack([flat, np.zeros(len(flat))]))
    whole = np.logical_and.reduceat(np.isfinite(uv).all(axis=1), bounds[:-1]).tolist()
    points = draw.fixed(np.nan_to_num(uv))
    for k, (cid, a, b) in enumerate(zip(ids[starts].tolist(), bounds[:-1].tolist(),
                                        bounds[1:].tolist(), strict=True)):
        colour = cluster_colour(int(cid))
        if whole[k]:  # the common case: every vertex projected
            cv2.polylines(c.img, [points[a:b]], True, colour, c.px, cv2.LINE_AA, draw.SHIFT)
        else:  # split where the lens cannot project (draw.polylines_from_uv)
            draw.draw_polylines(c.img, draw.polylines_from_uv(uv[a:b], closed=True),
                                colour=colour, thickness=c.px)


def _draw_heading(c: Canvas) -> None:
    """A flat arrow on the floor from the robot's position along its heading."""
    pose = c.state.pose
    length = 2.2 * c.settings.cone_height_m
    shaft, head, half = 0.018 * length / 0.33, 0.3 * length, 0.16 * length
    outline = np.array([[0, -shaft], [length - head, -shaft], [length - head, -half],
                        [length, 0], [length - head, half], [length - head, shaft],
                        [0, shaft]])
    cos, sin = math.cos(float(pose[2])), math.sin(float(pose[2]))
    xy = outline @ np.array([[cos, sin], [-sin, cos]]) + pose[:2]
    uv, _ = c.camera.project(np.column_stack([xy, np.full(len(xy), 0.002)]))
    if np.isfinite(uv).all():
        cv2.fillPoly(c.img, [draw.fixed(uv)], c.settings.colour_heading, cv2.LINE_AA,
                     draw.SHIFT)


REFERENCE_COLOUR = (255, 255, 255)  # BGR: the independent pose is white, the estimate green


def _draw_reference(c: Canvas, *, estimate: np.ndarray, reference: np.ndarray) -> None:
    """The independently measured robot pose: a ring, a line to the estimate, the error."""
    px = c.px
    uv, _ = c.camera.project(np.array([[reference[0], reference[1], 0.0],
                                       [estimate[0], estimate[1], 0.0]]))
    if not np.isfinite(uv).all():
        return
    ref_px = tuple(int(v) for v in draw.fixed(uv[:1])[0])
    est_px = tuple(int(v) for v in draw.fixed(uv[1:])[0])
    cv2.line(c.img, ref_px, est_px, REFERENCE_COLOUR, px, cv2.LINE_AA, draw.SHIFT)
    cv2.circle(c.img, ref_px, (9 * px) << draw.SHIFT, REFERENCE_COLOUR, 2 * px, cv2.LINE_AA,
               draw.SHIFT)
    error_cm = 100.0 * float(np.hypot(*(reference[:2] - estimate[:2])))
    u, v = (int(x) for x in uv[0])
    draw.put_text(c.img, f"tracked: {error_cm:.1f} cm", (u + 12 * px, v - 12 * px),
                  0.45 * px, REFERENCE_COLOUR, px)


REJECTED_COLOUR = (170, 170, 170)  # BGR grey: an observation the filter did not use


def rejected_observations(state: SlamState) -> np.ndarray:
    """Map positions (g, 2) of the observations the estimator's innovation gate refused in
    this update (``SlamState.gated_observations``: range, bearing from the state's pose);
    none when the state does not carry them (an estimator without the gate)."""
    obs = getattr(state, "gated_observations", None)
    if obs is None:
        return np.zeros((0, 2))
    obs = np.asarray(obs, dtype=float).reshape(-1, 2)
    x, y, theta = (float(v) for v in state.pose)
    angle = theta + obs[:, 1]
    return np.column_stack([x + obs[:, 0] * np.cos(angle), y + obs[:, 0] * np.sin(angle)])


def rejected_legend(state: SlamState, settings: ViewSettings) -> list[LegendRow]:
    """"rejected observations: 2 in this update, 17 in all" when the state says."""
    if not settings.rejected:
        return []
    ids = getattr(state, "gated_ids", None)
    diagnostics = getattr(state, "diagnostics", None) or {}
    total = diagnostics.get("gated")
    now = 0 if ids is None else int(np.asarray(ids).size)
    if ids is None and total is None:
        return []
    text = f"rejected observations (gate): {now} in this {state.step}"
    if total is not None:
        text += f", {int(total)} in all"
    return [[(text, REJECTED_COLOUR)]]


def _draw_rejected(c: Canvas, xy: np.ndarray) -> None:
    """A small grey cross at each rejected observation's position, on the floor."""
    uv, _ = c.camera.project(np.column_stack([xy, np.zeros(len(xy))]))
    half = 5 * c.px
    for u, v in uv.tolist():
        if not (math.isfinite(u) and math.isfinite(v)):
            continue
        p = (int(round(u)), int(round(v)))
        for colour, width in (((0, 0, 0), 3 * c.px), (REJECTED_COLOUR, c.px)):
            cv2.line(c.img, (p[0] - half, p[1] - half), (p[0] + half, p[1] + half), colour,
                     width, cv2.LINE_AA)
            cv2.line(c.img, (p[0] - half, p[1] + half), (p[0] + half, p[1] - half), colour,
                     width, cv2.LINE_AA)


def _draw_health(c: Canvas, *, glyphs: _Glyphs, lines: _Lines, suspects: np.ndarray) -> None:
    """Violating pair lines and glyphs outlined, suspect features ringed and labelled."""
    colour, scene, camera, state = c.settings.colour_violation, c.scene, c.camera, c.state
    if lines.polylines and scene.line_violation.any():
        bad = [lines.polylines[k] for k in np.flatnonzero(scene.line_violation[lines.index])]
        draw.draw_polylines(c.img, bad, colour=colour, thickness=2 * c.px)
    shaded = glyphs.shaded
    if shaded is not None and scene.glyph_violation.any():
        for k in np.flatnonzero(scene.glyph_violation[shaded.index]).tolist():
            shaded.outline(c.img, k, colour=colour, thickness=2 * c.px)
    if len(suspects):
        scale = 0.45 * camera.height / 720
        for fid in suspects.tolist():
            xy = state.landmarks[int(np.flatnonzero(state.landmark_ids == fid)[0])]
            ring = draw.floor_circle(xy, 2.2 * c.settings.cone_radius_m,
                                     z=0.5 * c.settings.cone_height_m)
            polys = draw.project_polyline(camera, ring, closed=True)
            draw.draw_polylines(c.img, polys, colour=colour, thickness=2 * c.px)
            uv, _ = camera.project(ring[:1])
            if np.isfinite(uv).all():
                draw.text(c.img, str(fid), (int(uv[0, 0]) + 4, int(uv[0, 1])), scale=scale,
                          colour=colour)


def _draw_labels(c: Canvas) -> None:
    """Each feature's id beside its cone tip."""
    ids, uv = feature_pixels(c.state, c.camera)
    scale = 0.42 * c.camera.height / 720
    offset = 8 * c.camera.height / 720
    for fid, (u, v) in zip(ids.tolist(), uv.tolist(), strict=True):
        if math.isfinite(u) and math.isfinite(v):
            draw.text(c.img, str(fid), (int(u + offset), int(v - offset)), scale=scale,
                      colour=c.settings.colour_features)


def _draw_roles(c: Canvas, glyphs: _Glyphs) -> None:
    """'min' / 'mean' / 'max' beside the minmeanmax glyphs."""
    ie, scene = glyphs.ellipses, c.scene
    scale = 0.42 * c.camera.height / 720
    for g in glyphs.shown.tolist():
        role = int(scene.glyph_role[g])
        if role == ROLE_PAIR:
            continue
        a, b, t = ie.axes[g, 0], ie.axes[g, 1], ie.angle[g]
        half_w = math.sqrt((a * math.cos(t)) ** 2 + (b * math.sin(t)) ** 2)
        u, v = ie.centre[g]
        draw.text(c.img, ROLE_NAMES[role], (int(u + half_w + 4), int(v + 5)), scale=scale)


_MODE_TEXT = {"all": "all pairs", "inter": "inter-cluster pairs",
              "minmeanmax": "min/mean/max per cluster pair (size = sqrt of largest eigenvalue)"}


def _glyph_text(settings: ViewSettings) -> str:
    if settings.glyph == "sigma":
        text = f"{settings.sigma_k:g}-sigma ellipsoid of P_d"
    else:
        text = "semi-axes = eigenvalues of P_d (m^2 drawn as m)"
    if settings.scale != 1.0:
        text += f" x{settings.scale:g}"
    return text


OVERVIEW_COLOUR = (0, 215, 255)  # BGR amber: the picture is not pair by pair

#: legend colour of a "tuning" verdict (BGR orange: the filter computes right, its noise
#: or models do not fit the data); a fault is in the violation colour
TUNING_COLOUR = (0, 165, 255)


def _health_row(health: Health, settings: ViewSettings) -> LegendRow:
    """The monitor's verdict, as the page and the terminal say it (slamlens.common.verdict)."""
    colour = {"fault": settings.colour_violation, "tuning": TUNING_COLOUR}.get(health.verdict)
    return [(f"verdict: {summary_text(health)}", colour)]


def _draw_legend(c: Canvas, *, health: Health | None, glyphs_shown: int,
                 notes: Sequence[LegendRow] = ()) -> None:
    """The legend box: robot and seq, mode, glyph meaning, colours, clusters, health."""
    state, scene, settings = c.state, c.scene, c.settings
    rows: list[LegendRow] = [
        [(f"robot {state.robot}  seq {state.seq}  {state.step}", None)],
        [(f"mode: {_MODE_TEXT[scene.mode]}", None)],
        [(f"{glyphs_shown} glyphs: {_glyph_text(settings)}", settings.colour_ellipsoids)],
        [("robot", settings.colour_robot), ("heading", settings.colour_heading),
         (f"features ({state.n})", settings.colour_features),
         (f"pair lines ({len(scene.lines_xy)})", settings.colour_lines)],
    ]
    if settings.selected_feature is not None:
        note = " (not in the map)" if scene.selected_missing else ""
        rows.append([(f"selected feature {settings.selected_feature}{note}", None)])
    if settings.selected_cluster is not None:
        rows.append([(f"selected cluster {settings.selected_cluster}: all its pairs",
                      cluster_colour(settings.selected_cluster))])
    if scene.tile_m is not None:
        rows.append([(f"map tiles of {scene.tile_m:g} m ({len(scene.centroids)})",
                      None)])
    elif scene.cluster_ids is not None:
        ids = np.unique(scene.cluster_ids).tolist()
        row: LegendRow = [(f"clusters ({len(ids)}):", None)]
        row += [(f"{c}", cluster_colour(int(c))) for c in ids[:12]]
        rows.append(row)
    if scene.overview:
        rows.append([(scene.overview, OVERVIEW_COLOUR)])
    if scene.mode == "minmeanmax" and glyphs_shown > MAX_ROLE_LABELS:
        rows.append([("per group pair: min below the line, mean at its middle, max above",
                      None)])
    if settings.health and health is not None:
        rows.append(_health_row(health, settings))
    rows += [list(row) for row in notes]
    draw.text_box(c.img, rows, scale=max(0.35, 0.45 * c.camera.height / 720))
