"""A state's way through the viewer, and every thread it takes on the way.

The intake (:mod:`intake`) only fills raw slots; from there the pipeline owns each step
and each hand-off:

* ``viewer-decode``, ``viewer-prepare``, ``viewer-layers`` (:mod:`stages`): camera frames
  decoded into the store; each robot's newest state decoded, its scenes computed for the
  views looked at (:meth:`RenderPipeline._prepare`) and, over a camera, drawn onto its
  layers (:meth:`RenderPipeline._finish`), the two stages overlapping;
* ``viewer-render`` wakes on new inputs (or a new view), takes them in (:mod:`takein`:
  into the store, then into the robots' histories) and renders every active view whose
  inputs changed (:mod:`compose`), at most ``fps`` times a second;
* ``viewer-encode`` JPEG-encodes each picture, overlapping the next render, makes it the
  view's picture and tells the listeners (the web layer);
* ``viewer-plots`` (:class:`~slamlens.services.visualiser.series.PlotSampler`) samples a
  large map for the plots, off the render thread.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from slamlens.common.drops import DropCounter
from slamlens.common.messages import SlamState
from slamlens.services.visualiser.clients import ClientRegistry, RenderBudget, View
from slamlens.services.visualiser.compose import Composer, Frame
from slamlens.services.visualiser.intake import Intake
from slamlens.services.visualiser.series import PlotSampler
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.stages import StateStages
from slamlens.services.visualiser.takein import SummaryChoice, TakeIn, remember, summary_choice
from slamlens.services.visualiser.views import Rendered

log = logging.getLogger("slamlens.viewer")


class RenderPipeline:
    """Takes the inputs ``intake`` receives through to the pictures of the active views
    of ``clients``, drawn by ``composer`` (whose store, eyes and histories it fills); the
    module docstring names its threads."""

    BURST = 2.0  # render cycles the fps cap lets through back to back after a pause

    def __init__(self, intake: Intake, composer: Composer, clients: ClientRegistry, *,
                 drops: DropCounter, fps: float, jpeg_quality: int,
                 other_views_share: float = 1.0, max_frame_pixels: int = 16_777_216) -> None:
        self._intake = intake
        self.composer = composer
        self.clients = clients
        self.fps = fps
        self.jpeg_quality = jpeg_quality
        self._wake = intake.wakeups.input
        store = composer.store
        self.stages = StateStages(intake, store, intake.wakeups, fps=fps, drops=drops,
                                  max_frame_pixels=max_frame_pixels,
                                  summary=intake.source == "summary",
                                  prepare=self._prepare, finish=self._finish)
        self.take_in = TakeIn(intake, store, prepared=self.stages.take_prepared, drops=drops,
                              max_frame_pixels=max_frame_pixels)
        #: a large map's plot samples are taken off the render thread (series.py)
        self.plots = PlotSampler(lambda state, exc: composer.failures.drop(
            "plots", f"state seq {state.seq}: {exc!r}"))
        #: --source summary: the selection whose pairs the summary queries ask for
        self._summary_choice: SummaryChoice | None = None
        # the views other than the default take at most this share of the render thread
        # while the default view is looked at (banked for two frame periods)
        self.budget = RenderBudget(other_views_share, bank_s=other_views_share * 2.0 / fps)
        self._deferred_s = 0.0  # > 0: views wait for the budget; render again this soon
        self._stop = threading.Event()
        self._encode_queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=2)
        self._listeners: list[Callable[[], None]] = []
        self._threads: list[threading.Thread] = []
        self.render_ms: deque[float] = deque(maxlen=120)  #: render + encode time per picture
        #: the inputs of the last render cycle (the next state's layers are drawn for its
        #: eyes before the render thread takes that state in)
        self.last_frame: Frame | None = None

    def wake(self) -> None:
        """Something changed (an input arrived, a view appeared): render soon."""
        self._wake.set()

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Called (on the encoding thread) after each new picture of any view."""
        self._listeners.append(listener)

    def fresh(self, settings: ViewSettings) -> bool:
        """True when the view's picture reflects the newest inputs."""
        return self.clients.is_current(settings, self.composer.inputs())

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        self.stages.start()
        self.plots.start()
        for name, target in (("viewer-render", self._render_loop),
                             ("viewer-encode", self._encode_loop)):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        self.stages.stop()
        self._stop.set()
        self._wake.set()
        try:  # wakes ``viewer-encode`` waiting for a picture (a full queue wakes it anyway)
            self._encode_queue.put_nowait(None)
        except queue.Full:
            pass
        for thread in self._threads:
            thread.join(timeout=5.0)
        self.plots.stop()

    # -- the state stages' work -----------------------------------------------------
    def _prepare(self, robot: str, state: SlamState) -> None:
        """On ``viewer-prepare``, the first stage of a new state: the scenes of the views
        looked at (clusters, the overview, glyphs: the heavier half of a picture at
        n = 1000). One robot only (several draw under per-robot settings)."""
        if len(self._intake.robots()) != 1:
            return
        health = self.composer.store.health(robot)
        for view in self.clients.looked_at():
            self.composer.prepare_scene(robot, state, view.settings, health)

    def _finish(self, robot: str, state: SlamState) -> None:
        """On ``viewer-layers``, the second stage, while ``viewer-prepare`` decodes the
        next state: over a camera, the state drawn on layers
        (:meth:`Composer.prepare_layers`) for the eyes of the last render cycle, so the
        render thread only puts them over camera frames — of the previous state,
        meanwhile."""
        if len(self._intake.robots()) != 1:
            return
        health = self.composer.store.health(robot)
        frame = self.last_frame
        for view in self.clients.looked_at():
            self.composer.prepare_layers(frame, robot, state, view.settings, health)

    # -- the render thread's take-in step ---------------------------------------------
    def _take_in_and_remember(self) -> None:
        """Take in what arrived; hand it to the parts that keep a history."""
        now = time.monotonic()
        if self._intake.source == "summary":
            self._select_summary()
        c = self.composer
        remember(self.take_in(), histories=c.histories, eyes=c.eyes, plots=self.plots,
                 failures=c.failures, now=now)

    def _select_summary(self) -> None:
        """``--source summary``: the summary queries ask for the pairs of the selection
        of the open view touched last that has one, else for the clusters."""
        choice = summary_choice([(v.touched, v.settings) for v in self.clients.looked_at()])
        if choice != self._summary_choice:
            self._summary_choice = choice
            self._intake.summary_selection(choice[0], feature=choice[1], cluster=choice[2])

    # -- rendering ------------------------------------------------------------------
    def _render_loop(self) -> None:
        # The fps cap is a token bucket (refilled at fps, holding BURST): on average at most
        # fps pictures per view set, but a camera's timing jitter is absorbed instead of
        # piling up behind a rigid 1/fps spacing (which drops frames at an equal input rate)
        rate, burst = self.fps, self.BURST
        tokens, refilled = burst, time.monotonic()
        while not self._stop.is_set():
            self._wake.wait(min(0.5, self._deferred_s) if self._deferred_s > 0 else 0.5)
            if self._stop.is_set():
                break
            now = time.monotonic()
            tokens, refilled = min(burst, tokens + (now - refilled) * rate), now
            if tokens < 1.0:  # newer inputs keep arriving meanwhile (latest wins)
                self._stop.wait((1.0 - tokens) / rate)
                now = time.monotonic()
                tokens, refilled = min(burst, tokens + (now - refilled) * rate), now
            self._wake.clear()
            try:
                self._take_in_and_remember()
                if self._render_active():
                    tokens -= 1.0
            except Exception:  # a rendering bug must not kill the viewer
                log.exception("render cycle failed")

    def _render_active(self) -> bool:
        """Render every active view whose inputs changed, the default view first and the
        others within their budget; hand the pictures to encoding."""
        self._deferred_s = 0.0
        views = self.clients.render_order(self.clients.active())
        if not views:
            return False
        frame = self.composer.frame()
        self.last_frame = frame
        default = self.clients.default_settings
        contended = views[0].settings == default  # somebody looks at the default view
        self.budget.refill(time.monotonic())
        produced = False
        for view in views:
            if view.rendered is not None and frame.inputs in (view.inputs, view.pending):
                continue
            other = contended and view.settings != default
            if other and not self.budget.allows:
                self._deferred_s = max(self.budget.wait_s(), 1e-3)  # the rest wait
                break
            t0 = time.perf_counter()
            view.drawn_at = time.monotonic()
            image = self.composer.compose(frame, view.settings)
            image.setflags(write=False)
            view.pending = frame.inputs
            if other:
                self.budget.spend(time.perf_counter() - t0)
            # encoding runs on its own thread, overlapping the next render (throughput);
            # a full queue makes this thread wait: the encoder sets the pace then
            while not self._stop.is_set():
                try:
                    self._encode_queue.put((view, image, frame, t0), timeout=0.5)
                    break
                except queue.Full:
                    continue
            produced = True
        return produced

    # -- encoding -------------------------------------------------------------------
    def _encode_loop(self) -> None:
        while not self._stop.is_set():
            try:
                job = self._encode_queue.get(timeout=0.5)
            except queue.Empty:
                continue
            if job is not None:  # None: stopping
                self._encode(*job)

    def _encode(self, view: View, image: np.ndarray, frame: Frame, t0: float) -> None:
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            log.error("JPEG encoding failed")
            return
        state = frame.state
        rendered = Rendered(
            version=(view.rendered.version + 1) if view.rendered else 1,
            seq=None if state is None else state.seq,
            stamp=None if state is None else state.stamp,
            image=image, jpeg=jpeg.tobytes(), rendered_at=time.monotonic())
        self.clients.publish(view, rendered, inputs=frame.inputs)
        view.rate.tick()
        self.render_ms.append((time.perf_counter() - t0) * 1e3)
        for listener in list(self._listeners):
            try:
                listener()
            except Exception:  # a broken listener must not stop the pictures
                log.exception("viewer listener failed")
