"""Who looks at what: each client's view settings, each distinct view's picture, recorders.

A client is a browser tab (a random id) with its own :class:`ViewSettings`. A view is
one distinct settings: clients with equal settings share one rendering. A view is
*active* while somebody streams, requests or records it (:meth:`ClientRegistry.touch`)
and for ``ttl_s`` after that; nothing is rendered when nobody looks.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.visualiser.intake import RateMeter
from services.visualiser.recording import Recorder
from services.visualiser.settings import ViewSettings
from services.visualiser.views import Rendered

#: makes the recorder of one client's view: (client, source of its pictures, its settings)
RecorderFactory = Callable[[str, Callable[[], np.ndarray | None], Callable[[], ViewSettings]],
                           Recorder]


@dataclass
class View:
    """One distinct settings and its last picture."""

    settings: ViewSettings
    touched: float  #: time.monotonic() when somebody last asked for it
    rendered: Rendered | None = None
    inputs: tuple[Any, ...] | None = None  #: input versions of ``rendered``
    pending: tuple[Any, ...] | None = None  #: input versions of the picture being encoded
    rate: RateMeter = field(default_factory=RateMeter)  #: pictures per second


class ClientRegistry:
    """Clients' settings (the most recent ``MAX_CLIENTS``), views and video recorders."""

    MAX_CLIENTS = 256  # settings of the most recently seen browser tabs
    FORGET_AFTER_TTLS = 12  # a view nobody asked for in this many ttl_s is dropped

    def __init__(self, default_settings: ViewSettings, *, ttl_s: float,
                 on_new_view: Callable[[], None], new_recorder: RecorderFactory) -> None:
        self.default_settings = default_settings
        self.ttl_s = ttl_s
        self._on_new_view = on_new_view
        self._new_recorder = new_recorder
        self._lock = threading.RLock()
        self._clients: OrderedDict[str, ViewSettings] = OrderedDict()
        self._views: dict[ViewSettings, View] = {}
        self._recorders: dict[str, Recorder] = {}

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
        """Apply web-page changes (strings, numbers, booleans); ConfigError if bad."""
        query = {k: (("true" if v else "false") if isinstance(v, bool) else
                     "" if v is None else str(v)) for k, v in changes.items()}
        with self._lock:
            settings = ViewSettings.from_query(query, base=self.settings_for(client))
            self._clients[client] = settings
        self.touch(settings)
        return settings

    @property
    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    # -- views --------------------------------------------------------------------
    def touch(self, settings: ViewSettings) -> None:
        """Keep rendering ``settings`` for the next ``ttl_s`` seconds."""
        now = time.monotonic()
        with self._lock:
            view = self._views.get(settings)
            if view is None:
                view = self._views[settings] = View(settings, now)
                self._on_new_view()
            view.touched = now

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
        """The views somebody asked for within ``ttl_s``."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return [v for v in self._views.values() if now - v.touched <= self.ttl_s]

    def active(self) -> list[View]:
        """The views to render now: recorded ones are kept active; views nobody asked for
        in a long while are forgotten."""
        now = time.monotonic()
        with self._lock:
            for recorder in self._recorders.values():
                self.touch(recorder.settings())
            forget = self.FORGET_AFTER_TTLS * self.ttl_s
            for key in [k for k, v in self._views.items() if now - v.touched > forget]:
                del self._views[key]  # forget renderers nobody asked for in a while
            return self.looked_at(now)

    def publish(self, view: View, rendered: Rendered, *, inputs: tuple[Any, ...]) -> None:
        """Make ``rendered`` (drawn from ``inputs``) the view's picture."""
        with self._lock:
            view.rendered, view.inputs = rendered, inputs

    # -- recordings ---------------------------------------------------------------
    def record_start(self, client: str) -> dict[str, Any]:
        """Record the client's view (whatever its settings become); its info if running."""
        with self._lock:
            if client in self._recorders:
                return self._recorders[client].info()

            def settings() -> ViewSettings:
                return self.settings_for(client)

            def source() -> np.ndarray | None:
                rendered = self.latest(settings())
                return None if rendered is None else rendered.image

            recorder = self._recorders[client] = self._new_recorder(client, source, settings)
        self.touch(settings())
        recorder.start()
        return recorder.info()

    def record_stop(self, client: str) -> dict[str, Any] | None:
        """Stop the client's recording; its info, or None if it was not recording."""
        with self._lock:
            recorder = self._recorders.pop(client, None)
        if recorder is None:
            return None
        recorder.stop()
        return recorder.info()

    def recording(self) -> list[str]:
        """The clients recording now, sorted."""
        with self._lock:
            return sorted(self._recorders)

    def stop_recordings(self) -> None:
        with self._lock:
            recorders = list(self._recorders.values())
        for recorder in recorders:
            recorder.stop()
