"""When pictures are made: the render thread and the encode thread of the viewer.

* ``viewer-render`` wakes on new inputs (or a new view), takes them in (``ingest``), and
  renders every active view whose inputs changed, at most ``fps`` times a second;
* ``viewer-encode`` JPEG-encodes each picture, overlapping the next render, makes it the
  view's picture and tells the listeners (the web layer).
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

from slamlens.services.visualiser.clients import ClientRegistry, RenderBudget, View
from slamlens.services.visualiser.compose import Composer, Frame
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.views import Rendered

log = logging.getLogger("slamlens.viewer")


class RenderPipeline:
    """Renders the active views of ``clients`` with ``composer`` on two threads."""

    BURST = 2.0  # render cycles the fps cap lets through back to back after a pause

    def __init__(self, composer: Composer, clients: ClientRegistry, *,
                 ingest: Callable[[], None], fps: float, jpeg_quality: int,
                 other_views_share: float = 1.0) -> None:
        self.composer = composer
        self.clients = clients
        self._ingest = ingest
        self.fps = fps
        self.jpeg_quality = jpeg_quality
        # the views other than the default take at most this share of the render thread
        # while the default view is looked at (banked for two frame periods)
        self.budget = RenderBudget(other_views_share, bank_s=other_views_share * 2.0 / fps)
        self._deferred_s = 0.0  # > 0: views wait for the budget; render again this soon
        self._stop = threading.Event()
        self._wake = threading.Event()
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
        for name, target in (("viewer-render", self._render_loop),
                             ("viewer-encode", self._encode_loop)):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        try:  # wakes ``viewer-encode`` waiting for a picture (a full queue wakes it anyway)
            self._encode_queue.put_nowait(None)
        except queue.Full:
            pass
        for thread in self._threads:
            thread.join(timeout=5.0)

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
                self._ingest()
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
