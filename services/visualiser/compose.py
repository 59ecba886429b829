"""What each picture shows: the newest inputs seen through the view's eyes, states drawn over.

:meth:`Composer.frame` takes one snapshot of the inputs for a render cycle and chooses its
eyes; :meth:`Composer.compose` draws it for one view's settings: over each eye, every
robot whose map that eye can place (its own registration in a camera view; the map view
places them all), each in its own colour, with the camera-tracked pose beside the
estimate; a note for what cannot be drawn (no state yet, not registered, registered for an
older map); two eyes side by side.

One robot is drawn exactly as :meth:`Renderer.render` draws it (the settings' colours and
the single-robot legend); several share one legend with a row per robot.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from slamlens.common.drops import DropCounter
from slamlens.common.messages import Health, SlamState
from slamlens.services.visualiser.inputs import CameraInputs, Inputs, RobotInputs
from slamlens.services.visualiser.legend import (
    LegendRow,
    RobotLegend,
    draw_robots_legend,
    rejected_legend,
    robot_settings,
)
from slamlens.services.visualiser.render import side_by_side
from slamlens.services.visualiser.robots import RobotHistories
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.store import InputStore
from slamlens.services.visualiser.views import CameraView, Eye, EyeChooser, placeholder

RESTART_COLOUR = (0, 165, 255)  # BGR orange: news, not a fault


@dataclass(frozen=True, eq=False)
class Frame:
    """The inputs of one render cycle, shared by every view drawn in it."""

    robots: tuple[RobotInputs, ...]
    eyes: tuple[Eye, ...]
    inputs: tuple[Any, ...]  #: versions of everything a picture depends on (but settings)
    restarted: frozenset[str]  #: robots whose "map restarted" note is showing

    @property
    def state(self) -> SlamState | None:
        """The first robot's state (the picture's seq and stamp)."""
        return self.robots[0].state if self.robots else None

    @property
    def health(self) -> Health | None:
        return self.robots[0].health if self.robots else None


def camera_views(inputs: Inputs) -> list[CameraView]:
    """Per camera, the registrations that place each robot's *current* map, and a note for
    each robot that has none (not registered yet, or registered for an older map)."""
    out = []
    for cam in inputs.cameras:
        usable, waiting = {}, {}
        for robot in inputs.robots:
            entry = cam.registrations.get(robot.name)
            if entry is None:
                waiting[robot.name] = (f"waiting for the registration of camera {cam.name} "
                                       f"for robot {robot.name}")
            elif robot.registration_usable(*entry):
                usable[robot.name] = entry[0]
            else:
                waiting[robot.name] = (f"map restarted: waiting for camera {cam.name} to "
                                       f"register the new map of robot {robot.name}")
        out.append(CameraView(cam.name, cam.image, usable, waiting))
    return out


def registration_status(cam: CameraInputs, robot: RobotInputs) -> str | None:
    """Whether ``cam`` places ``robot``'s current map: None (no registration), "current"
    or "stale" (registered for an older map)."""
    entry = cam.registrations.get(robot.name)
    if entry is None:
        return None
    return "current" if robot.registration_usable(*entry) else "stale"


class Composer:
    """Turns the newest inputs into one picture per view settings."""

    def __init__(self, store: InputStore, *, eyes: EyeChooser, histories: RobotHistories,
                 failures: DropCounter, restart_note_s: float = 10.0) -> None:
        self.store = store
        self.eyes = eyes
        self.histories = histories
        self.failures = failures  #: states that could not be drawn
        self.restart_note_s = restart_note_s

    def _restarted(self, robots: tuple[RobotInputs, ...], now: float) -> frozenset[str]:
        return frozenset(r.name for r in robots if r.restarted_at is not None
                         and now - r.restarted_at < self.restart_note_s)

    def inputs(self) -> tuple[Any, ...]:
        """Signature of everything a picture depends on (besides its settings)."""
        snap = self.store.snapshot()
        return (*snap.versions, self.eyes.bounds,
                self._restarted(snap.robots, time.monotonic()))

    def frame(self) -> Frame:
        """One consistent snapshot of the inputs and the eyes to see them through."""
        snap = self.store.snapshot()
        states = [r.state for r in snap.robots if r.state is not None]
        eyes = self.eyes.choose(states, camera_views(snap))
        restarted = self._restarted(snap.robots, time.monotonic())
        return Frame(robots=snap.robots, eyes=eyes,
                     inputs=(*snap.versions, self.eyes.bounds, restarted),
                     restarted=restarted)

    def compose(self, frame: Frame, settings: ViewSettings) -> np.ndarray:
        """The picture of ``frame`` under ``settings`` (BGR uint8, contiguous)."""
        pictures = [self._eye(frame, eye, settings) for eye in frame.eyes]
        if len(pictures) == 2:
            return side_by_side(pictures[0], pictures[1])
        return np.ascontiguousarray(pictures[0])

    # -- one eye --------------------------------------------------------------------
    def _eye(self, frame: Frame, eye: Eye, settings: ViewSettings) -> np.ndarray:
        drawable: list[tuple[RobotInputs, Any]] = []
        notes: list[str] = []
        for robot in frame.robots:
            model, why = eye.model_for(robot.name)
            if model is None:
                notes.append(why or f"waiting for camera {eye.name}")
            elif robot.state is None:
                notes.append(f"waiting for the state of robot {robot.name}")
            else:
                drawable.append((robot, model))
        if not frame.robots:
            first = self.store.robot
            notes.append(f"waiting for the state of robot {first}"
                         if first else "waiting for a robot's estimator")
        if not drawable:
            text = eye.note if eye.note and not frame.robots else "; ".join(notes)
            return placeholder(eye, text or eye.note, settings)
        try:
            if len(frame.robots) == 1:
                return self._one(frame, eye, settings, *drawable[0])
            return self._several(frame, eye, settings, drawable, notes)
        except Exception as exc:  # keep the picture flowing, say what went wrong
            state = drawable[0][0].state
            assert state is not None
            self.failures.drop("render", f"state seq {state.seq}: {exc!r}")
            return placeholder(eye, f"cannot draw state seq {state.seq}: "
                                    f"{type(exc).__name__}", settings)

    def prepare_scene(self, robot: str, state: SlamState, settings: ViewSettings,
                      health: Health | None) -> None:
        """The first half of preparing ``state`` (``viewer-prepare``): its scene under
        ``settings`` (clusters, the overview, glyphs)."""
        self.histories.get(robot).renderer.prepare(state, settings, health)

    def prepare_layers(self, frame: Frame | None, robot: str, state: SlamState,
                       settings: ViewSettings, health: Health | None) -> None:
        """The second half (``viewer-layers``): one robot over a camera, ``state`` drawn
        on its layers through each eye of ``frame`` (the last render cycle's; a camera or
        notes changed meanwhile are drawn again by the render thread), so that thread
        only puts them over camera frames."""
        renderer = self.histories.get(robot).renderer
        if (frame is None or len(frame.robots) != 1 or frame.robots[0].name != robot
                or not renderer.layered(state)):
            return
        for eye in frame.eyes:
            model, _ = eye.model_for(robot)
            if eye.image is None or model is None:
                continue
            height, width = eye.image.shape[:2]
            renderer.layers(state, model.resized(width, height), settings, health,
                            self._notes(frame, frame.robots[0]))

    def _notes(self, frame: Frame, robot: RobotInputs) -> list[LegendRow]:
        rows: list[LegendRow] = []
        if robot.name in frame.restarted:
            rows.append([(f"map restarted: the estimator of robot {robot.name} began a new "
                          f"map; the old map's path and plots were dropped", RESTART_COLOUR)])
        return rows

    def _one(self, frame: Frame, eye: Eye, settings: ViewSettings, robot: RobotInputs,
             model: Any) -> np.ndarray:
        """One robot: exactly the renderer's own picture."""
        history = self.histories.get(robot.name)
        reference, estimate = history.tracked.reference()
        assert robot.state is not None
        return history.renderer.render(
            eye.image, state=robot.state, camera=model, settings=settings,
            health=robot.health, reference_pose=reference, reference_estimate=estimate,
            notes=self._notes(frame, robot))

    def _several(self, frame: Frame, eye: Eye, settings: ViewSettings,
                 drawable: list[tuple[RobotInputs, Any]], notes: list[str]) -> np.ndarray:
        """Several robots over one picture, each through its own camera model, in its own
        colour (the first robot in the settings' colours), with one legend."""
        base = eye.camera if eye.camera is not None else drawable[0][1]
        history0 = self.histories.get(drawable[0][0].name)
        img, _ = history0.renderer.background(eye.image, base, settings)
        entries = []
        for robot, model in drawable:
            if settings.selected_robot not in (None, robot.name):
                own = settings.replace(selected_feature=None)
            else:
                own = settings
            own = robot_settings(own, robot.index)
            history = self.histories.get(robot.name)
            reference, estimate = history.tracked.reference()
            assert robot.state is not None
            drawn = history.renderer.draw(
                img, state=robot.state, camera=model, settings=own.replace(legend=False),
                health=robot.health, reference_pose=reference, reference_estimate=estimate)
            entries.append(RobotLegend(robot.state, robot.health, drawn.glyphs_shown,
                                       own.colour_robot,
                                       [*rejected_legend(robot.state, own),
                                        *self._notes(frame, robot)]))
        if settings.legend:
            draw_robots_legend(img, settings, entries,
                               waiting=[n for n in notes if n])
        return img
