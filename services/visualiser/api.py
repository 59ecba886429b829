"""What the web layer asks of the viewer: JSON answers, and the pictures of a view.

:class:`ViewerApi` is the one object :mod:`slamlens.services.visualiser.web` talks to. Its JSON
methods return plain dicts (the web layer only adds HTTP); bad settings raise
:class:`~slamlens.common.errors.ConfigError` naming the field.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError
from slamlens.common.messages import Registration
from slamlens.common.verdict import WORDS, summary_text, violation_text
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.clients import ClientRegistry
from slamlens.services.visualiser.compose import registration_status
from slamlens.services.visualiser.inputs import RobotInputs
from slamlens.services.visualiser.legend import ROBOT_COLOURS
from slamlens.services.visualiser.pipeline import RenderPipeline
from slamlens.services.visualiser.robots import RobotHistories
from slamlens.services.visualiser.series import SeriesStore
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.store import InputStore
from slamlens.services.visualiser.views import EyeChooser, Rendered, project_features


def _css(bgr: tuple[int, int, int]) -> str:
    return f"rgb({bgr[2]},{bgr[1]},{bgr[0]})"


class ViewerApi:
    """Status, health, plots, features, settings, recordings and pictures of one viewer."""

    def __init__(self, *, store: InputStore, eyes: EyeChooser, clients: ClientRegistry,
                 pipeline: RenderPipeline, histories: RobotHistories, bad: DropCounter,
                 failures: DropCounter, camera: str | None, recordings_dir: str,
                 discovering: bool = False, restart_note_s: float = 10.0,
                 reregister: Callable[[str | None], dict[str, Any]] | None = None) -> None:
        self._store = store
        self._bad = bad
        self._discovering = discovering
        self._eyes = eyes
        self._clients = clients
        self._pipeline = pipeline
        self._histories = histories
        self._failures = failures
        self._camera = camera
        self._recordings_dir = Path(recordings_dir)
        self._restart_note_s = restart_note_s
        self._reregister = reregister

    @property
    def robot(self) -> str:
        return self._store.robot

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

    def _robot(self, robot: str | None) -> str:
        """``robot``, checked to be shown (default: the first robot)."""
        if robot is None or robot == "":
            return self._store.robot
        if robot not in self._store.robot_names:
            raise ConfigError(f"robot: {robot!r} is not shown by this viewer; shown: "
                              f"{', '.join(self._store.robot_names) or 'none yet'}")
        return robot

    def colour_of(self, robot: RobotInputs) -> str:
        """The robot's colour in the picture (CSS), as the settings' colours give it."""
        if robot.index == 0:
            return _css(self.default_settings.colour_robot)
        return _css(ROBOT_COLOURS[(robot.index - 1) % len(ROBOT_COLOURS)])

    def features(self, settings: ViewSettings) -> dict[str, Any]:
        """Feature ids, map positions and pixel positions in this view (click to select),
        of every robot shown (``robot`` names the map of each)."""
        inputs, eyes = self._store.snapshot(), self._eyes.current
        several = len(inputs.robots) > 1
        out: dict[str, Any] = {"seq": None, "ids": [], "xy": [], "uv": [], "robot": [],
                               "selected": settings.selected_feature,
                               "selected_robot": settings.selected_robot,
                               "selected_cluster": settings.selected_cluster,
                               "clusters": {}, "overview": {}}
        for r in inputs.robots:
            state = r.state
            if state is None:
                continue
            if out["seq"] is None:
                out["seq"] = state.seq
            out["ids"] += [int(i) for i in state.landmark_ids]
            out["xy"] += [[float(x), float(y)] for x, y in state.landmarks]
            out["uv"] += project_features(eyes, np.asarray(state.landmarks),
                                          r.name if several else None)
            out["robot"] += [r.name] * state.n
            history = self._histories.find(r.name)
            if history is not None:
                note = history.renderer.overview_note(settings)
                if note:
                    out["overview"][r.name] = note
                # the stable cluster ids of the view's clustering (to select a cluster)
                known = history.renderer.known_cluster_ids(settings)
                if known is not None:
                    lm, cid = known
                    where = {int(i): int(c) for i, c in zip(lm.tolist(), cid.tolist(),
                                                            strict=True)}
                    out["clusters"][r.name] = [where.get(int(i)) for i in state.landmark_ids]
        return out

    def health(self, robot: str | None = None) -> dict[str, Any]:
        """The latest verdict and the recent violations of ``robot``, newest first."""
        name = self._robot(robot)
        inputs = self._store.snapshot().robot(name)
        health = None if inputs is None else inputs.health
        recent = self._store.recent_violations(name)
        latest = None
        if health is not None:
            latest = {"seq": health.seq, "stamp": health.stamp, "ok": health.ok,
                      "verdict": health.verdict, "verdict_since": health.verdict_since,
                      "verdict_words": WORDS.get(health.verdict, health.verdict),
                      "verdict_text": summary_text(health),
                      "standing": [{**v.to_dict(), "text": violation_text(v)}
                                   for v in health.standing],
                      "suspects": [int(s) for s in health.suspects],
                      "violations": [{**v.to_dict(), "text": violation_text(v)}
                                     for v in health.violations],
                      "statistics": dict(health.statistics)}
        return {"robot": name, "latest": latest, "recent": recent[::-1]}

    def series(self, settings: ViewSettings, pairs: list[tuple[int, int]] | None = None,
               robot: str | None = None) -> dict[str, Any]:
        """Time series of ``robot``'s ``pairs`` (default: the flagged, selected or largest
        pairs)."""
        name = self._robot(robot)
        history = self._histories.find(name)
        if history is None:
            return {"robot": name, **SeriesStore().to_json([])}
        if not pairs:
            inputs = self._store.snapshot().robot(name)
            health = None if inputs is None else inputs.health
            flagged = [] if health is None else [
                (v.ids[0], v.ids[1]) for v in health.violations
                if v.kind == "pair" and len(v.ids) == 2]
            selected = (settings.selected_feature
                        if settings.selected_robot in (None, name) else None)
            pairs = history.series.default_pairs(selected=selected, flagged=flagged)
        return {"robot": name, **history.series.to_json(pairs)}

    def status(self) -> dict[str, Any]:
        now = time.monotonic()
        inputs = self._store.snapshot()
        active = self._clients.looked_at(now)
        render_ms = list(self._pipeline.render_ms)

        def state_of(r: RobotInputs | None) -> dict[str, Any] | None:
            if r is None or r.state is None:
                return None
            state = r.state
            counts = state.diagnostics or {}
            return {"seq": state.seq, "stamp": state.stamp, "step": state.step, "n": state.n,
                    "epoch": state.epoch,
                    "inputs": {k.removeprefix("inputs."): int(v) for k, v in counts.items()
                               if k.startswith("inputs.")},
                    "age_s": None if r.state_received is None else now - r.state_received,
                    "rate_hz": r.state_rate.rate(now)}

        def health_of(r: RobotInputs | None) -> dict[str, Any] | None:
            if r is None or r.health is None:
                return None
            h = r.health
            return {"seq": h.seq, "ok": h.ok, "violations": len(h.violations),
                    "suspects": [int(s) for s in h.suspects], "verdict": h.verdict,
                    "verdict_text": summary_text(h), "standing": len(h.standing)}

        first = inputs.robots[0] if inputs.robots else None
        robots = []
        for r in inputs.robots:
            restarted = (r.restarted_at is not None
                         and now - r.restarted_at < self._restart_note_s)
            robots.append({
                "name": r.name, "colour": self.colour_of(r), "state": state_of(r),
                "health": health_of(r), "restarts": r.restarts,
                "map_restarted": restarted,
                "registration": {c.name: registration_status(c, r) for c in inputs.cameras}})
        return {
            "robot": self.robot, "robots": robots, "discover": self._discovering,
            "view": self._eyes.view, "camera": self._camera,
            "state": state_of(first),
            "cameras": [{
                "name": c.name,
                "frame": None if c.frame is None else {
                    "seq": c.frame.seq, "stamp": c.frame.stamp, "width": c.frame.width,
                    "height": c.frame.height, "rate_hz": c.rate.rate(now),
                    "age_s": None if c.frame_received is None else now - c.frame_received},
                "registration": None if c.registration is None else {
                    "status": c.registration.status, "stamp": c.registration.stamp,
                    "epoch": c.registration.epoch,
                    "reprojection_error_px": c.registration.reprojection_error_px,
                    "reason": c.registration.reason, "moved_m": c.registration.moved_m,
                    "moved_deg": c.registration.moved_deg},
            } for c in inputs.cameras],
            "registrations": self._store.registration_events(),
            "health": health_of(first),
            "fps": max((v.rate.rate(now) for v in active), default=0.0),
            "render_ms_median": float(np.median(render_ms)) if render_ms else None,
            "views_active": len(active), "clients": self._clients.client_count,
            "views": self._clients.memory(),
            "bad_messages": dict(self._bad.counts),
            "failures": dict(self._failures.counts),
            "recording": self._clients.recording(),
        }

    def reregister(self, robot: str | None) -> dict[str, Any]:
        """Ask the camera(s) to register ``robot`` (None: every robot) again; blocks up to
        the viewer's ``reregister_timeout_s``."""
        if self._reregister is None:
            raise ConfigError("this viewer cannot ask for a re-registration")
        return self._reregister(None if robot in (None, "") else self._robot(robot))

    # -- the /ar page: a browser's own camera ------------------------------------
    def robot_names(self) -> tuple[str, ...]:
        """The robots this viewer shows (so far, with ``--robot all``)."""
        return self._store.robot_names

    def draw_over(self, image: np.ndarray, registration: Registration, received: float,
                  robot: str | None, settings: ViewSettings) -> tuple[np.ndarray | None, str]:
        """``robot``'s newest state drawn over ``image`` through ``registration`` (received
        at ``received``, monotonic s) under ``settings``, as the main view draws it over a
        camera; (None, why) if it cannot be: no state yet, or the registration places
        another map (an older epoch)."""
        name = robot or self._store.robot
        inputs = self._store.snapshot().robot(name)
        if inputs is None or inputs.state is None:  # (a robot not discovered yet, too)
            return None, f"waiting for the state of robot {name}"
        if not inputs.registration_usable(registration, received):
            return None, (f"map restarted: waiting for camera {registration.camera} to "
                          f"register the new map of robot {name}")
        history = self._histories.get(name)
        reference, estimate = history.tracked.reference()
        picture = history.renderer.render(
            image, state=inputs.state, camera=CameraModel.from_registration(registration),
            settings=settings, health=inputs.health, reference_pose=reference,
            reference_estimate=estimate)
        return picture, ""

    def state_seq(self, robot: str | None) -> int | None:
        inputs = self._store.snapshot().robot(robot or self._store.robot)
        return None if inputs is None or inputs.state is None else inputs.state.seq

    # -- recordings ---------------------------------------------------------------
    def record_start(self, client: str) -> dict[str, Any]:
        return self._clients.record_start(client)

    def record_stop(self, client: str) -> dict[str, Any] | None:
        return self._clients.record_stop(client)
