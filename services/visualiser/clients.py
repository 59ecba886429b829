"""Who looks at what: each client's view settings, each distinct view's picture, recorders.

A client is a browser tab (a random id) with its own :class:`ViewSettings`. A view is
one distinct settings: clients with equal settings share one rendering. A view is
*active* while somebody streams it (:meth:`ClientRegistry.watch`) or records it, and for
``ttl_s`` after the last request for it (:meth:`ClientRegistry.touch`); then it is
dropped, its picture with it: nothing is rendered, or kept, when nobody looks.

Resources are bounded: at most ``max_views`` views besides the default view (a new one
evicts the view nobody streams that was asked for longest ago, and is refused with
:class:`TooManyViews` when every view is streamed), at most ``max_recordings``
recordings at once (:class:`RecordingRefused`), and :class:`RenderBudget` keeps the views
other than the default from taking more than their share of the render thread.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slamlens.common.errors import SlamlensError
from slamlens.common.memory import release_freed_memory
from slamlens.services.visualiser.inputs import RateMeter
from slamlens.services.visualiser.recording import Recorder, RecordingRefused
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.views import Rendered

#: makes the recorder of one client's view: (client, source of its pictures, its settings)
RecorderFactory = Callable[[str, Callable[[], np.ndarray | None], Callable[[], ViewSettings]],
                           Recorder]


class TooManyViews(SlamlensError):
    """Every view the viewer may keep is being streamed: a new one is refused (HTTP 503)."""


@dataclass
class View:
    """One distinct settings and its last picture."""

    settings: ViewSettings
    touched: float  #: time.monotonic() when somebody last asked for it
    rendered: Rendered | None = None
    inputs: tuple[Any, ...] | None = None  #: input versions of ``rendered``
    pending: tuple[Any, ...] | None = None  #: input versions of the picture being encoded
    rate: RateMeter = field(default_factory=RateMeter)  #: pictures per second
    #: streams showing it now, by client ("" for none): a watched view is not evicted
    #: (unless only its own client watches it and is moving to other settings)
    watchers: Counter[str] = field(default_factory=Counter)
    drawn_at: float = -float("inf")  #: time.monotonic() when it was last drawn

    @property
    def picture_bytes(self) -> int:
        """Memory its picture holds (the BGR image and its JPEG)."""
        r = self.rendered
        return 0 if r is None else r.image.nbytes + len(r.jpeg)


class RenderBudget:
    """How much render time the views other than the default may take.

    A token bucket counted in seconds: it fills at ``share`` seconds per second of wall
    clock, holds at most ``bank_s``, and each render of another view spends what it took.
    While it is empty those views wait, so the default view is drawn at its own pace
    whatever other clients ask; over time they share ``share`` of the render thread.
    """

    def __init__(self, share: float, *, bank_s: float) -> None:
        self.share = share
        self.bank_s = bank_s
        self._credit = bank_s
        self._at: float | None = None

    def refill(self, now: float) -> None:
        if self._at is not None:
            self._credit = min(self.bank_s, self._credit + (now - self._at) * self.share)
        self._at = now

    @property
    def allows(self) -> bool:
        return self._credit > 0.0

    def spend(self, seconds: float) -> None:
        self._credit -= seconds

    def wait_s(self) -> float:
        """Seconds until the bucket allows another render (0 if it does now)."""
        return max(0.0, -self._credit / self.share) if self._credit <= 0.0 else 0.0


class ClientRegistry:
    """Clients' settings (the most recent ``MAX_CLIENTS``), views and video recorders."""

    MAX_CLIENTS = 256  # settings of the most recently seen browser tabs
    MAX_FINISHED = 64  # recordings that stopped by themselves, kept for their info

    def __init__(self, default_settings: ViewSettings, *, ttl_s: float,
                 on_new_view: Callable[[], None], new_recorder: RecorderFactory,
                 max_views: int = 64, max_recordings: int = 2) -> None:
        self.default_settings = default_settings
        self.ttl_s = ttl_s
        self.max_views = max_views  #: views kept besides the default view
        self.max_recordings = max_recordings
        self._on_new_view = on_new_view
        self._new_recorder = new_recorder
        self._lock = threading.RLock()
        self._clients: OrderedDict[str, ViewSettings] = OrderedDict()
        self._views: dict[ViewSettings, View] = {}
        self._recorders: dict[str, Recorder] = {}
        self.evicted = 0  #: views dropped to make room for a new one
        self._freed = False  # views were dropped: hand their memory back to the system
        self.refused = 0  #: new views refused because every kept view was streamed

    # -- clients ------------------------------------------------------------------
    def settings_for(self, client: str | None) -> ViewSettings:
        """The client's settings (a new client starts with the defaults)."""
        if client is None:
            return self.default_settings
        with self._lock:
            settings = self._clients.get(client)
            if settings is None:
                settings = self._clients[client] = self.default_settings
                while len(self._clients) > self.MAX_CLIENTS:
                    self._clients.popitem(last=False)
            self._clients.move_to_end(client)
            return settings

    def update_settings(self, client: str, changes: Mapping[str, Any]) -> ViewSettings:
        """Apply web-page changes (strings, numbers, booleans); ConfigError if bad,
        TooManyViews if they make a new view and there is no room (settings unchanged).
        The view the client leaves may make that room, even while its streams show it:
        they follow the client to the new settings."""
        query = {k: (("true" if v else "false") if isinstance(v, bool) else
                     "" if v is None else str(v)) for k, v in changes.items()}
        now = time.monotonic()
        with self._lock:
            settings = ViewSettings.from_query(query, base=self.settings_for(client))
            # first: a refused view leaves the client's settings as they were
            self._view(settings, now, leaving=client).touched = now
            self._clients[client] = settings
        return settings

    @property
    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    # -- views --------------------------------------------------------------------
    def touch(self, settings: ViewSettings) -> None:
        """Keep rendering ``settings`` for the next ``ttl_s`` seconds (TooManyViews if it
        is a new view and there is no room for it)."""
        now = time.monotonic()
        with self._lock:
            self._view(settings, now).touched = now

    def watch(self, settings: ViewSettings, client: str | None = None) -> None:
        """A stream of ``client`` shows ``settings`` from now on (until :meth:`unwatch`):
        its view is kept and rendered. TooManyViews if there is no room for it."""
        now = time.monotonic()
        with self._lock:
            view = self._view(settings, now)
            view.touched = now
            view.watchers[client or ""] += 1

    def unwatch(self, settings: ViewSettings, client: str | None = None) -> None:
        """A stream stopped showing ``settings`` (its view lives ``ttl_s`` longer)."""
        now = time.monotonic()
        with self._lock:
            view = self._views.get(settings)
            if view is not None:
                view.watchers[client or ""] -= 1
                view.watchers += Counter()  # drops the clients no longer watching
                view.touched = now

    def _view(self, settings: ViewSettings, now: float, *, leaving: str = "") -> View:
        view = self._views.get(settings)
        if view is None:
            if settings != self.default_settings:
                self._make_room(leaving)
            view = self._views[settings] = View(settings, now)
            self._on_new_view()
        return view

    def _make_room(self, leaving: str) -> None:
        """Evict the idle view asked for longest ago if ``max_views`` are kept (a view
        only ``leaving``'s streams show counts as idle: they are moving away from it)."""
        others = [v for v in self._views.values() if v.settings != self.default_settings]
        if len(others) < self.max_views:
            return
        recorded = {r.settings() for r in self._recorders.values() if r.running}
        idle = [v for v in others if set(v.watchers) <= {leaving} - {""}
                and v.settings not in recorded]
        if not idle:
            self.refused += 1
            raise TooManyViews(
                f"the viewer already draws {len(others)} distinct views, every one of them "
                f"streamed (max_views {self.max_views}): use the settings of another tab, "
                "or try again when one closes")
        victim = min(idle, key=lambda v: v.touched)
        del self._views[victim.settings]  # its picture goes with it
        self.evicted += 1
        self._freed = True

    def latest(self, settings: ViewSettings) -> Rendered | None:
        """The newest picture of ``settings`` (None before the first)."""
        with self._lock:
            view = self._views.get(settings)
            return None if view is None else view.rendered

    def is_current(self, settings: ViewSettings, inputs: tuple[Any, ...]) -> bool:
        """True when the view's picture was rendered from ``inputs`` (input versions)."""
        with self._lock:
            view = self._views.get(settings)
            return view is not None and view.rendered is not None and view.inputs == inputs

    def looked_at(self, now: float | None = None) -> list[View]:
        """The views somebody streams or asked for within ``ttl_s``."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return [v for v in self._views.values()
                    if v.watchers or now - v.touched <= self.ttl_s]

    def active(self) -> list[View]:
        """The views to render now: recorded ones are kept active; the others nobody
        streams nor asked for within ``ttl_s`` are dropped, their pictures with them."""
        now = time.monotonic()
        with self._lock:
            for recorder in [r for r in self._recorders.values() if r.running]:
                try:
                    self.touch(recorder.settings())
                except TooManyViews:  # its client switched to settings with no room
                    pass
            for key in [k for k, v in self._views.items()
                        if not v.watchers and now - v.touched > self.ttl_s]:
                del self._views[key]  # nobody looks: release its picture now
                self._freed = True
            views = list(self._views.values())
            freed, self._freed = self._freed, False
        # the allocator keeps freed pictures for itself unless told (common/memory.py)
        if freed and not release_freed_memory():
            with self._lock:
                self._freed = True  # trimmed less than a second ago: next cycle
        return views

    def render_order(self, views: list[View]) -> list[View]:
        """The default view first, then the others, the one drawn longest ago first."""
        return sorted(views, key=lambda v: (v.settings != self.default_settings, v.drawn_at))

    def memory(self) -> dict[str, Any]:
        """What the views hold: counts, limits and their pictures' bytes."""
        with self._lock:
            views = list(self._views.values())
            return {"kept": len(views), "streamed": sum(1 for v in views if v.watchers),
                    "max": self.max_views, "evicted": self.evicted, "refused": self.refused,
                    "picture_bytes": sum(v.picture_bytes for v in views)}

    def publish(self, view: View, rendered: Rendered, *, inputs: tuple[Any, ...]) -> None:
        """Make ``rendered`` (drawn from ``inputs``) the view's picture (unless the view
        was dropped meanwhile: then the picture is dropped too)."""
        with self._lock:
            if self._views.get(view.settings) is view:
                view.rendered, view.inputs = rendered, inputs

    # -- recordings ---------------------------------------------------------------
    def record_start(self, client: str) -> dict[str, Any]:
        """Record the client's view (whatever its settings become); its info if running.
        RecordingRefused if ``max_recordings`` run already or the disk is short of space
        (the recorder checks), TooManyViews if its view has no room."""
        with self._lock:
            current = self._recorders.get(client)
            if current is not None and current.running:
                return current.info()
            running = sum(1 for r in self._recorders.values() if r.running)
            if running >= self.max_recordings:
                raise RecordingRefused(f"{running} recordings are running already "
                                       f"(max_recordings {self.max_recordings})")

            def settings() -> ViewSettings:
                return self.settings_for(client)

            def source() -> np.ndarray | None:
                rendered = self.latest(settings())
                return None if rendered is None else rendered.image

            self.touch(settings())
            recorder = self._new_recorder(client, source, settings)
            recorder.start()  # RecordingRefused: too little disk space
            self._recorders.pop(client, None)
            self._recorders[client] = recorder
            finished = [c for c, r in self._recorders.items() if not r.running]
            for old in finished[:max(0, len(finished) - self.MAX_FINISHED)]:
                del self._recorders[old]
        return recorder.info()

    def record_stop(self, client: str) -> dict[str, Any] | None:
        """Stop the client's recording (or take the info of one that stopped by itself,
        at a limit); its info, or None if it was not recording."""
        with self._lock:
            recorder = self._recorders.pop(client, None)
        if recorder is None:
            return None
        recorder.stop()
        return recorder.info()

    def recording(self) -> list[str]:
        """The clients recording now, sorted."""
        with self._lock:
            return sorted(c for c, r in self._recorders.items() if r.running)

    def stop_recordings(self) -> None:
        with self._lock:
            recorders = list(self._recorders.values())
        for recorder in recorders:
            recorder.stop()
