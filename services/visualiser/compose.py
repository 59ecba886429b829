"""What each picture shows: the newest inputs seen through the view's eyes, state drawn over.

:meth:`Composer.frame` takes one snapshot of the inputs for a render cycle and chooses its
eyes; :meth:`Composer.compose` draws it for one view's settings: the renderer over each
eye (with the camera-tracked pose beside the estimate), a one-line note where there is
nothing to draw yet, two eyes side by side.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from common.drops import DropCounter
from common.messages import Health, SlamState
from services.visualiser.intake import Intake
from services.visualiser.render import Renderer, side_by_side
from services.visualiser.settings import ViewSettings
from services.visualiser.tracked import TrackedMatch
from services.visualiser.views import Eye, EyeChooser, placeholder


@dataclass(frozen=True, eq=False)
class Frame:
    """The inputs of one render cycle, shared by every view drawn in it."""

    state: SlamState | None
    health: Health | None
    eyes: tuple[Eye, ...]
    inputs: tuple[Any, ...]  #: versions of everything a picture depends on (but settings)


class Composer:
    """Turns the newest inputs into one picture per view settings."""

    def __init__(self, intake: Intake, *, eyes: EyeChooser, renderer: Renderer,
                 tracked: TrackedMatch, failures: DropCounter) -> None:
        self.intake = intake
        self.eyes = eyes
        self.renderer = renderer
        self.tracked = tracked
        self.failures = failures  #: states that could not be drawn

    def inputs(self) -> tuple[Any, ...]:
        """Signature of everything a picture depends on (besides its settings)."""
        return (*self.intake.versions(), self.eyes.bounds)

    def frame(self) -> Frame:
        """One consistent snapshot of the inputs and the eyes to see them through."""
        snap = self.intake.snapshot()
        cams = [(c.name, c.registration, c.image) for c in snap.cameras]
        eyes = self.eyes.choose(snap.state, cams)
        return Frame(state=snap.state, health=snap.health, eyes=eyes,
                     inputs=(*snap.versions, self.eyes.bounds))

    def compose(self, frame: Frame, settings: ViewSettings) -> np.ndarray:
        """The picture of ``frame`` under ``settings`` (BGR uint8, contiguous)."""
        state = frame.state
        pictures = []
        reference, estimate = self.tracked.reference()
        for eye in frame.eyes:
            if state is None or eye.camera is None:
                text = eye.note or f"waiting for the state of robot {self.intake.robot}"
                pictures.append(placeholder(eye, text, settings))
            else:
                try:
                    pictures.append(self.renderer.render(
                        eye.image, state=state, camera=eye.camera, settings=settings,
                        health=frame.health, reference_pose=reference,
                        reference_estimate=estimate))
                except Exception as exc:  # keep the picture flowing, say what went wrong
                    self.failures.drop("render", f"state seq {state.seq}: {exc!r}")
                    pictures.append(placeholder(
                        eye, f"cannot draw state seq {state.seq}: {type(exc).__name__}",
                        settings))
        if len(pictures) == 2:
            return side_by_side(pictures[0], pictures[1])
        return np.ascontiguousarray(pictures[0])
