"""The AR renderer: the estimator's state drawn over a camera picture (paper §3.2).

Drawing order (:mod:`render_steps`):

1. the floor layer: map grid (map view only), cluster outlines, robot path, pair lines,
   heading arrow: flat on the floor, so everything standing on the floor covers them;
2. the 3D objects, glyphs and cones, far to near by camera depth (painter's algorithm);
3. overlays that must never be hidden: health outlines and rings, labels, the legend
   (:mod:`legend`).

Each step draws on a :class:`~slamlens.services.visualiser.render_steps.Canvas`: the
picture, its camera, the state and its scene, the settings and the line width unit, shared
by every step of one picture. Over a camera picture the steps draw on two layers once per
state (:meth:`Renderer.layers`: steps 1–2, and 3 but the camera-tracked pose, which is
drawn between them on each frame), which are then put over every camera frame until the
next state (:mod:`draw`, layers).

``Renderer`` keeps only what needs history: the robot's path (reset when the robot changes
or ``seq`` goes backwards; drawn incrementally per view, :mod:`trail`) and, in
:mod:`render_cache`, what a state shows (its scenes, its layers) and the cluster trackers
that keep cluster ids and colours stable from frame to frame. Use one ``Renderer`` per
robot; it may be shared by threads.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from slamlens.common.messages import Health, SlamState
from slamlens.common.verdict import summary_text
from slamlens.services.visualiser import draw
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.legend import LegendRow, draw_legend, rejected_legend
from slamlens.services.visualiser.render_cache import FloorCache, LayerCache, SceneCache
from slamlens.services.visualiser.render_steps import (
    Canvas,
    draw_grid,
    draw_over,
    draw_reference,
    draw_under,
    feature_pixels,
)
from slamlens.services.visualiser.scene import Scene
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.trail import Trail

#: states of at least this many features are drawn onto layers over a camera (below, a
#: state is cheap to draw and usually comes faster than camera frames: drawn straight)
LAYERS_FROM_N = 200


class Renderer:
    """Draws ``SlamState`` (and ``Health``) over a picture; see the module docstring."""

    def __init__(self, *, layers_from_n: int = LAYERS_FROM_N) -> None:
        #: over a camera, states of at least this many features are drawn onto layers
        self.layers_from_n = layers_from_n
        self._path = Trail()
        self.scene_cache = SceneCache()  #: scenes and cluster ids of the newest states
        #: the newest states drawn as layers, per settings, camera, health and notes
        self.layer_cache: LayerCache[Layers] = LayerCache()
        self._floor = FloorCache()  #: the map view's floor

    @property
    def scenes_built(self) -> int:
        """Scenes computed (the rest were reused)."""
        return self.scene_cache.built

    @property
    def layers_built(self) -> int:
        """States drawn onto layers (the rest were reused)."""
        return self.layer_cache.built

    @property
    def layers_built_on(self) -> Counter[str]:
        """States drawn onto layers, by the name of the thread that drew them."""
        return self.layer_cache.built_on

    # -- history --------------------------------------------------------------------
    def reset_path(self) -> None:
        self._path.reset()
        self.layer_cache.clear()  # they show the old path

    def new_map(self) -> None:
        """A new map began (another epoch): forget the path and the cluster identities."""
        self._path.reset(forget_robot=True)
        self.scene_cache.clear()
        self.layer_cache.clear()

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
        return self.scene_cache.cluster_ids(state, settings)

    def known_cluster_ids(self, settings: ViewSettings
                          ) -> tuple[np.ndarray, np.ndarray] | None:
        """(landmark ids, their stable cluster ids) of the last picture clustered as
        ``settings`` clusters, or None (none clustered yet)."""
        return self.scene_cache.known_cluster_ids(settings)

    def overview_note(self, settings: ViewSettings) -> str:
        """What the last picture drawn under ``settings`` showed instead of its pairs (the
        glyph budget), or "" — for the web page's note."""
        return self.scene_cache.overview_note(settings)

    def scene(self, state: SlamState, settings: ViewSettings,
              violating: frozenset[tuple[int, int]] = frozenset()) -> Scene:
        """What ``state`` shows under ``settings`` (pairs, glyphs, the overview): computed
        once per state, settings and flagged pairs, then reused for every picture of that
        state (the camera's frames come faster than states)."""
        return self.scene_cache.scene(state, settings, violating)

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
        floor = self._floor.get(key)
        if floor is None:
            pixel = np.array(settings.colour_background, dtype=np.uint8)
            floor = np.ascontiguousarray(
                np.broadcast_to(pixel, (camera.height, camera.width, 3)))
            draw_grid(floor, camera)
            self._floor.put(key, floor)
        return floor.copy(), camera

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
        camera (at n = 1000 drawing 1000 cones and the overview per camera frame cost
        more than the frames are apart); a smaller one is drawn straight.
        """
        if image_bgr is None or not self.layered(state):
            img, camera = self.background(image_bgr, camera, settings)
            drawn = self.draw(img, state=state, camera=camera, settings=settings,
                              health=health, reference_pose=reference_pose,
                              reference_estimate=reference_estimate)
            if settings.legend:
                draw_legend(drawn.canvas, health=health, glyphs_shown=drawn.glyphs_shown,
                             notes=[*rejected_legend(state, settings), *notes])
            return img
        img, camera = _bgr_copy(image_bgr, camera)
        layers = self.layers(state, camera, settings, health, notes)
        layers.under.put_over(img)
        if settings.robot and reference_pose is not None:
            c = Canvas(img, camera, state, layers.scene, settings,
                       px=max(1, round(camera.height / 720)))
            estimate = state.pose if reference_estimate is None else reference_estimate
            draw_reference(c, estimate=np.asarray(estimate, float),
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
        kept = self.layer_cache.get(state, key)
        if kept is not None:
            return kept
        scene, c_under = self._canvas(draw.new_layer(camera.height, camera.width),
                                      state, camera, settings, violating)
        lines, glyphs = draw_under(c_under, self._path)
        c_over = dataclasses.replace(c_under, img=draw.new_layer(camera.height, camera.width))
        rejected = draw_over(c_over, glyphs=glyphs, lines=lines, suspects=suspects)
        if settings.legend:
            draw_legend(c_over, health=health, glyphs_shown=len(glyphs.shown),
                         notes=[*rejected_legend(state, settings), *notes])
        out = Layers(draw.Overlay(c_under.img), draw.Overlay(c_over.img), scene,
                     len(glyphs.shown), rejected)
        self.layer_cache.put(state, key, out)
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
        self.scene_cache.note_overview(settings, scene.overview)
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
        lines, glyphs = draw_under(c, self._path)
        if settings.robot and reference_pose is not None:
            estimate = state.pose if reference_estimate is None else reference_estimate
            draw_reference(c, estimate=np.asarray(estimate, float),
                            reference=np.asarray(reference_pose, float))
        rejected = draw_over(c, glyphs=glyphs, lines=lines, suspects=suspects)
        return Drawn(c, len(glyphs.shown), rejected)


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


@dataclass(frozen=True, eq=False)
class Drawn:
    """What :meth:`Renderer.draw` drew: its canvas (for the legend) and the glyph count."""

    canvas: Canvas
    glyphs_shown: int
    rejected_shown: int = 0  #: rejected (gated) observations drawn


def side_by_side(left_bgr: np.ndarray, right_bgr: np.ndarray) -> np.ndarray:
    """Left and right pictures in one frame (right scaled to the left's height if needed)."""
    if right_bgr.shape[0] != left_bgr.shape[0]:
        h = left_bgr.shape[0]
        w = max(1, round(right_bgr.shape[1] * h / right_bgr.shape[0]))
        right_bgr = cv2.resize(right_bgr, (w, h), interpolation=cv2.INTER_AREA)
    return np.hstack([left_bgr, right_bgr])


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
