"""What a view is seen through: eyes (one camera, or two for stereo), map bounds, placeholders.

:class:`EyeChooser` is the viewer's view choice: the registered camera(s) over their
frames, or a virtual top-down camera over the map, alone or as a stereo pair. The rest
are small pure pieces: rendered pictures, growing map bounds, notes, feature pixels.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from slamlens.common.messages import Registration, SlamState
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.settings import ViewSettings

#: map-view bounds snap to this grid, so the virtual camera moves rarely, not every state
BOUNDS_STEP_M = 0.5
#: smallest extent of the map view, m (a robot alone at the origin still gets a floor)
MIN_EXTENT_M = 2.0
PLACEHOLDER_SIZE = (1280, 720)
DEFAULT_BOUNDS = (-1.0, -1.0, 4.0, 4.0)  #: map view before any state, m


@dataclass(frozen=True, eq=False)
class Rendered:
    """One composited picture of one view."""

    version: int  #: +1 per picture of this view
    seq: int | None  #: seq of the state drawn (None: no state yet)
    stamp: float | None  #: stamp of that state, s
    image: np.ndarray  #: BGR uint8, read-only
    jpeg: bytes
    rendered_at: float  #: time.monotonic() when it was finished


@dataclass(frozen=True, eq=False)
class Eye:
    """One camera of a view: its model (None until registered), picture and a note.

    ``models`` (camera views) gives each robot's own model of this camera — every robot's
    map has its own frame, so its own registration — or None and the note saying why it
    cannot be drawn (not registered yet, or registered for an older map). Without
    ``models`` (the map view) every robot is seen through ``camera``.
    """

    name: str
    camera: CameraModel | None  #: the picture's camera (camera views: the first usable)
    image: np.ndarray | None  #: BGR camera picture; None draws the neutral floor
    note: str  #: shown instead of the overlay when it cannot be drawn
    models: tuple[tuple[str, CameraModel | None, str], ...] | None = None

    def model_for(self, robot: str) -> tuple[CameraModel | None, str]:
        """(this eye's camera model for ``robot``'s map, or None and the reason)."""
        if self.models is None:
            return self.camera, self.note
        for name, model, note in self.models:
            if name == robot:
                return model, note
        return None, f"waiting for the registration of camera {self.name} for robot {robot}"


@dataclass(frozen=True, eq=False)
class CameraView:
    """What the eyes need of one camera: its picture and, per robot, a registration that
    places the robot's current map, or the reason there is none."""

    name: str
    image: np.ndarray | None
    registrations: dict[str, Registration]  #: robot → usable registration
    waiting: dict[str, str]  #: robot → why it has none ("waiting for …")


def grow_bounds(bounds: tuple[float, float, float, float] | None,
                state: SlamState) -> tuple[float, float, float, float]:
    """Map-view bounds (xmin, ymin, xmax, ymax) that grow with the map, snapped to a grid.

    Growing only and snapping keep the virtual top-down camera still while the map fills
    in, instead of zooming with every new landmark or robot step. They shrink back only
    when the map fits in less than half of them both ways (e.g. after one wild estimate),
    so a single outlier does not leave the view zoomed out for good.
    """
    points = np.vstack([np.asarray(state.landmarks).reshape(-1, 2),
                        np.asarray(state.pose[:2]).reshape(1, 2)])
    with np.errstate(over="ignore", invalid="ignore"):
        lo, hi = points.min(axis=0), points.max(axis=0)
        centre = lo / 2 + hi / 2
        half = np.maximum(hi / 2 - lo / 2, MIN_EXTENT_M / 2)
        lo, hi = (centre - half) / BOUNDS_STEP_M, (centre + half) / BOUNDS_STEP_M
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return bounds or DEFAULT_BOUNDS  # estimates near the float limit: keep the view
    snapped = (math.floor(lo[0]) * BOUNDS_STEP_M, math.floor(lo[1]) * BOUNDS_STEP_M,
               math.ceil(hi[0]) * BOUNDS_STEP_M, math.ceil(hi[1]) * BOUNDS_STEP_M)
    if bounds is None:
        return snapped
    if (snapped[2] - snapped[0] < 0.5 * (bounds[2] - bounds[0])
            and snapped[3] - snapped[1] < 0.5 * (bounds[3] - bounds[1])):
        return snapped
    return (min(bounds[0], snapped[0]), min(bounds[1], snapped[1]),
            max(bounds[2], snapped[2]), max(bounds[3], snapped[3]))


class EyeChooser:
    """The eyes of every picture, from the configured view and the newest inputs.

    ``view`` is ``camera``, ``map`` or ``stereo`` (resolved from ``auto``). With every
    named camera registered (for at least one robot), those cameras over their frames; a
    camera view still waiting for a registration shows the frame with a note; otherwise the
    map view, whose bounds grow with the maps (:func:`grow_bounds`) until :meth:`restart`.
    """

    def __init__(self, view: str, *, map_width: int, map_height: int,
                 stereo_baseline_m: float) -> None:
        self.view = view
        self.map_size = (map_width, map_height)
        self.stereo_baseline_m = stereo_baseline_m
        self._lock = threading.Lock()
        self._bounds: tuple[float, float, float, float] | None = None
        self._eyes: tuple[Eye, ...] = ()

    @property
    def bounds(self) -> tuple[float, float, float, float] | None:
        """The map view's bounds so far (None before the first state)."""
        with self._lock:
            return self._bounds

    @property
    def current(self) -> tuple[Eye, ...]:
        """The eyes of the last :meth:`choose`."""
        with self._lock:
            return self._eyes

    def restart(self) -> None:
        """A new map: the map view starts over."""
        with self._lock:
            self._bounds = None

    def choose(self, states: Sequence[SlamState], cams: Sequence[CameraView]
               ) -> tuple[Eye, ...]:
        """The camera models and background picture of each eye (one, or two for stereo)."""
        eyes: list[Eye] = []
        if cams and all(c.registrations for c in cams):
            for c in cams:
                models: list[tuple[str, CameraModel | None, str]] = []
                for robot, reg in c.registrations.items():
                    model = CameraModel.from_registration(reg)
                    if c.image is not None and c.image.shape[:2] != (reg.height, reg.width):
                        # frames of another size than calibrated: scale the intrinsics
                        model = model.resized(c.image.shape[1], c.image.shape[0])
                    models.append((robot, model, ""))
                models += [(robot, None, note) for robot, note in c.waiting.items()]
                first = next(m for _, m, _ in models if m is not None)
                eyes.append(Eye(c.name, first, c.image, "", tuple(models)))
        elif self.view == "camera":
            c = cams[0]
            note = next(iter(c.waiting.values()), f"waiting for the registration of camera "
                                                  f"{c.name}")
            eyes.append(Eye(c.name, None, c.image, note,
                            tuple((robot, None, n) for robot, n in c.waiting.items())))
        else:
            with self._lock:
                for state in states:
                    self._bounds = grow_bounds(self._bounds, state)
                bounds = self._bounds or DEFAULT_BOUNDS
            width, height = self.map_size
            model = CameraModel.top_down(bounds_xy=bounds, width=width, height=height)
            if self.view == "stereo":
                left, right = model.stereo_pair(self.stereo_baseline_m)
                eyes += [Eye("map-left", left, None, ""), Eye("map-right", right, None, "")]
            else:
                eyes.append(Eye("map", model, None, ""))
        with self._lock:
            self._eyes = tuple(eyes)
        return self._eyes


def placeholder(eye: Eye, text: str, settings: ViewSettings) -> np.ndarray:
    """The eye's picture (or a neutral floor) with a one-line note: nothing to overlay yet."""
    if eye.image is not None:
        image = eye.image.copy()
    else:
        if eye.camera is not None:
            width, height = eye.camera.width, eye.camera.height
        else:
            width, height = PLACEHOLDER_SIZE
        image = np.empty((height, width, 3), np.uint8)
        image[:] = settings.colour_background
    h = image.shape[0]
    scale = max(0.5, h / 1200)
    cv2.rectangle(image, (0, h - int(40 * scale) - 8), (image.shape[1], h), (0, 0, 0), -1)
    cv2.putText(image, text, (12, h - 14), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255),
                max(1, round(scale * 1.5)), cv2.LINE_AA)
    return image


def project_features(eyes: tuple[Eye, ...], landmarks_xy: np.ndarray,
                     robot: str | None = None) -> list[Any]:
    """Pixel position of each landmark (of ``robot``'s map: its own camera model) in the
    composited picture (left eye first; a landmark behind the camera, outside the picture
    or of a map not registered in that eye is None)."""
    out: list[Any] = [None] * len(landmarks_xy)
    offset = 0
    for eye in eyes:
        width = (eye.camera.width if eye.camera is not None else
                 PLACEHOLDER_SIZE[0] if eye.image is None else eye.image.shape[1])
        model = eye.camera if robot is None else eye.model_for(robot)[0]
        if model is None or len(landmarks_xy) == 0:
            offset += width
            continue
        points = np.c_[landmarks_xy, np.zeros(len(landmarks_xy))]
        uv, depth = model.project(points)
        for k, ((u, v), z) in enumerate(zip(uv, depth, strict=True)):
            inside = z > 0 and 0 <= u < model.width and 0 <= v < model.height
            if out[k] is None and inside and np.isfinite(u) and np.isfinite(v):
                out[k] = [float(u) + offset, float(v)]
        offset += width
    return out
