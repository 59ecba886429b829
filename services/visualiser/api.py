"""What the web layer asks of the viewer: JSON answers, and the pictures of a view.

:class:`ViewerApi` is the one object :mod:`services.visualiser.web` talks to. Its JSON
methods return plain dicts (the web layer only adds HTTP); bad settings raise
:class:`~common.errors.ConfigError` naming the field.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from common.drops import DropCounter
from services.visualiser.clients import ClientRegistry
from services.visualiser.intake import Intake
from services.visualiser.pipeline import RenderPipeline
from services.visualiser.series import SeriesStore
from services.visualiser.settings import ViewSettings
from services.visualiser.views import EyeChooser, Rendered, project_features


class ViewerApi:
    """Status, health, plots, features, settings, recordings and pictures of one viewer."""

    def __init__(self, *, intake: Intake, eyes: EyeChooser, clients: ClientRegistry,
                 pipeline: RenderPipeline, series: SeriesStore, failures: DropCounter,
                 camera: str | None, recordings_dir: str) -> None:
        self._intake = intake
        self._eyes = eyes
        self._clients = clients
        self._pipeline = pipeline
        self._series = series
        self._failures = failures
        self._camera = camera
        self._recordings_dir = Path(recordings_dir)

    @property
    def robot(self) -> str:
        return self._intake.robot

    @property
    def default_settings(self) -> ViewSettings:
        return self._clients.default_settings

    # -- pictures -----------------------------------------------------------------
    def settings_for(self, client: str | None) -> ViewSettings:
        return self._clients.settings_for(client)

    def touch(self, settings: ViewSettings) -> None:
        """Keep rendering ``settings`` (somebody is looking); TooManyViews if it is a new
        view and the viewer keeps as many as it may, all streamed."""
        self._clients.touch(settings)

    def watch(self, settings: ViewSettings, client: str | None) -> None:
        """A stream of ``client`` shows ``settings`` until :meth:`unwatch`
        (TooManyViews: no room for it)."""
        self._clients.watch(settings, client)

    def unwatch(self, settings: ViewSettings, client: str | None) -> None:
        self._clients.unwatch(settings, client)

    def latest(self, settings: ViewSettings) -> Rendered | None:
        return self._clients.latest(settings)

    def fresh(self, settings: ViewSettings) -> bool:
        """True when the view's picture reflects the newest inputs."""
        return self._pipeline.fresh(settings)

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Called (on the encoding thread) after each new picture of any view."""
        self._pipeline.add_listener(listener)

    def recording_path(self, name: str) -> Path:
        """Where the recording file ``name`` (already checked to be a plain name) lives."""
        return self._recordings_dir / name

    # -- JSON ---------------------------------------------------------------------
    def update_settings(self, client: str, changes: Mapping[str, Any]) -> ViewSettings:
        """Apply web-page changes (strings, numbers, booleans); ConfigError if bad."""
        return self._clients.update_settings(client, changes)

    def features(self, settings: ViewSettings) -> dict[str, Any]:
        """Feature ids, map positions and pixel positions in this view (click to select)."""
        state, eyes = self._intake.snapshot().state, self._eyes.current
        if state is None:
            return {"seq": None, "ids": [], "xy": [], "uv": [], "selected":
                    settings.selected_feature}
        return {"seq": state.seq, "ids": [int(i) for i in state.landmark_ids],
                "xy": [[float(x), float(y)] for x, y in state.landmarks],
                "uv": project_features(eyes, np.asarray(state.landmarks)),
                "selected": settings.selected_feature}

    def health(self) -> dict[str, Any]:
        """The latest verdict and the recent violations, newest first."""
        health, recent = self._intake.snapshot().health, self._intake.recent_violations()
        latest = None
        if health is not None:
            latest = {"seq": health.seq, "stamp": health.stamp, "ok": health.ok,
                      "suspects": [int(s) for s in health.suspects],
                      "violations": [v.to_dict() for v in health.violations],
                      "statistics": dict(health.statistics)}
        return {"latest": latest, "recent": recent[::-1]}

    def series(self, settings: ViewSettings,
               pairs: list[tuple[int, int]] | None = None) -> dict[str, Any]:
        """Time series of ``pairs`` (default: the flagged, selected or largest pairs)."""
        if not pairs:
            health = self._intake.snapshot().health
            flagged = [] if health is None else [
                (v.ids[0], v.ids[1]) for v in health.violations
                if v.kind == "pair" and len(v.ids) == 2]
            pairs = self._series.default_pairs(selected=settings.selected_feature,
                                               flagged=flagged)
        return self._series.to_json(pairs)

    def status(self) -> dict[str, Any]:
        now = time.monotonic()
        inputs = self._intake.snapshot()
        state, health = inputs.state, inputs.health
        active = self._clients.looked_at(now)
        render_ms = list(self._pipeline.render_ms)
        return {
            "robot": self.robot, "view": self._eyes.view, "camera": self._camera,
            "state": None if state is None else {
                "seq": state.seq, "stamp": state.stamp, "step": state.step, "n": state.n,
                "age_s": None if inputs.state_received is None
                else now - inputs.state_received,
                "rate_hz": self._intake.state_rate.rate(now)},
            "cameras": [{
                "name": c.name,
                "frame": None if c.frame is None else {
                    "seq": c.frame.seq, "stamp": c.frame.stamp, "width": c.frame.width,
                    "height": c.frame.height, "rate_hz": c.rate.rate(now),
                    "age_s": None if c.frame_received is None else now - c.frame_received},
                "registration": None if c.registration is None else {
                    "status": c.registration.status, "stamp": c.registration.stamp,
                    "reprojection_error_px": c.registration.reprojection_error_px},
            } for c in inputs.cameras],
            "health": None if health is None else {
                "seq": health.seq, "ok": health.ok, "violations": len(health.violations),
                "suspects": [int(s) for s in health.suspects]},
            "fps": max((v.rate.rate(now) for v in active), default=0.0),
            "render_ms_median": float(np.median(render_ms)) if render_ms else None,
            "views_active": len(active), "clients": self._clients.client_count,
            "views": self._clients.memory(),
            "bad_messages": dict(self._intake.bad.counts),
            "failures": dict(self._failures.counts),
            "recording": self._clients.recording(),
        }

    # -- recordings ---------------------------------------------------------------
    def record_start(self, client: str) -> dict[str, Any]:
        return self._clients.record_start(client)

    def record_stop(self, client: str) -> dict[str, Any] | None:
        return self._clients.record_stop(client)
