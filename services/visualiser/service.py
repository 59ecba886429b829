"""The viewer service: bus inputs → rendered, JPEG-encoded views for any number of clients.

It is assembled from parts a reader can name, each in its own module:

* :class:`~slamlens.services.visualiser.intake.Intake` — subscriptions, late join, decoding
  (thread ``viewer-decode`` decodes camera frames as they arrive; ``viewer-prepare``
  decodes states and computes the open views' scenes of them, :meth:`_prepare`, and
  ``viewer-layers`` draws each onto its layers, :meth:`_finish`, meanwhile the next is
  decoded, before the render thread takes them in);
* :class:`~slamlens.services.visualiser.series.PlotSampler` — thread ``viewer-plots`` samples
  large maps for the plots;
* :class:`~slamlens.services.visualiser.pipeline.RenderPipeline` — thread ``viewer-render`` takes
  in state / registration / health / tracked pose and renders every *active* view whose
  inputs changed, at most ``fps`` times a second; thread ``viewer-encode`` JPEG-encodes;
* :class:`~slamlens.services.visualiser.compose.Composer` — what a picture shows, through the eyes
  an :class:`~slamlens.services.visualiser.views.EyeChooser` picks (camera, map or stereo), with
  the camera-tracked pose matched by :class:`~slamlens.services.visualiser.tracked.TrackedMatch`;
* :class:`~slamlens.services.visualiser.clients.ClientRegistry` — each client's settings, each
  distinct view's picture, the video recorders;
* :class:`~slamlens.services.visualiser.api.ViewerApi` — what the web layer asks.

None of the threads is a Zenoh callback; callbacks only store bytes (see :mod:`intake`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.clusters import ClusterTracker, cluster_labels
from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError
from slamlens.common.keys import Keys
from slamlens.common.messages import CameraControl, Health, SlamState
from slamlens.common.summary import SummaryQuery
from slamlens.services.visualiser.api import ViewerApi
from slamlens.services.visualiser.clients import ClientRegistry
from slamlens.services.visualiser.compose import Composer
from slamlens.services.visualiser.intake import Intake
from slamlens.services.visualiser.pipeline import RenderPipeline
from slamlens.services.visualiser.recording import MB, Recorder, recording_name
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.robots import RobotHistories
from slamlens.services.visualiser.series import DENSE_PAIRS, PlotSampler, SeriesStore
from slamlens.services.visualiser.settings import ViewerConfig, ViewSettings
from slamlens.services.visualiser.summary_view import SummarisedState
from slamlens.services.visualiser.views import EyeChooser

log = logging.getLogger("slamlens.viewer")

class ViewerService:
    """One viewer: its parts wired together, started and stopped as one."""

    def __init__(self, bus: Bus, *, keys: Keys, config: ViewerConfig,
                 default_settings: ViewSettings | None = None) -> None:
        self.config = config
        self.bus = bus
        self.keys = keys
        self.default_settings = default_settings or ViewSettings()
        self.bad = DropCounter(log)  #: malformed input messages, by input
        self.failures = DropCounter(log)  #: states that could not be drawn or plotted
        # one history per robot for every view: the path and the cluster identities (per
        # clustering setting) survive a tab switching modes; a new map empties it
        self.histories = RobotHistories(self._new_series)
        self.eyes = EyeChooser(config.resolved_view, map_width=config.map_width,
                               map_height=config.map_height,
                               stereo_baseline_m=config.stereo_baseline_m)
        self.clients = ClientRegistry(self.default_settings, ttl_s=config.client_ttl_s,
                                      on_new_view=self._wake, new_recorder=self._recorder,
                                      max_views=config.max_views,
                                      max_recordings=config.max_recordings)
        self.intake = Intake(bus, keys=keys, robots=config.robots, cameras=config.cameras,
                             fps=config.fps, late_join_timeout_s=config.late_join_timeout_s,
                             on_input=self._wake, drops=self.bad, discover=config.discover,
                             max_frame_pixels=config.max_frame_pixels,
                             source=config.source,
                             summary_query=SummaryQuery(
                                 what="clusters", budget=config.summary_budget,
                                 threshold_m=ViewSettings().cluster_threshold_m,
                                 count=ViewSettings().cluster_count),
                             prepare=self._prepare, finish=self._finish)
        self.composer = Composer(self.intake, eyes=self.eyes, histories=self.histories,
                                 failures=self.failures,
                                 restart_note_s=config.restart_note_s)
        self.pipeline = RenderPipeline(self.composer, self.clients, ingest=self._ingest,
                                       fps=config.fps, jpeg_quality=config.jpeg_quality,
                                       other_views_share=config.other_views_share)
        self.api = ViewerApi(intake=self.intake, eyes=self.eyes, clients=self.clients,
                             pipeline=self.pipeline, histories=self.histories,
                             failures=self.failures, camera=config.camera,
                             recordings_dir=config.recordings_dir,
                             restart_note_s=config.restart_note_s,
                             reregister=self.reregister)
        #: a large map's plot samples are taken off the render thread (series.py)
        self.plots = PlotSampler(lambda state, exc: self.failures.drop(
            "plots", f"state seq {state.seq}: {exc!r}"))
        #: --source summary: the selection whose pairs the summary queries ask for
        self._summary_selection: tuple[str | None, int | None, int | None] | None = None
        self.started = time.monotonic()

    @property
    def renderer(self) -> Renderer:
        """The first robot's renderer (its path and cluster identities)."""
        return self.histories.get(self.intake.robot).renderer

    @property
    def series(self) -> SeriesStore:
        """The first robot's plots."""
        return self.histories.get(self.intake.robot).series

    def _wake(self) -> None:
        self.pipeline.wake()

    def _new_series(self) -> SeriesStore:
        """A robot's plots: its clusters for min/mean/max cut as the default settings cut
        them, with stable ids (of its current map)."""
        tracker = ClusterTracker()
        threshold, count = (self.default_settings.cluster_threshold_m,
                            self.default_settings.cluster_count)

        def clusters(xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
            return tracker.update(ids, cluster_labels(xy, threshold_m=threshold, count=count))

        return SeriesStore(length=self.config.series_length,
                           min_interval_s=self.config.series_interval_s, cluster=clusters)

    def _recorder(self, client: str, source: Callable[[], np.ndarray | None],
                  settings: Callable[[], ViewSettings]) -> Recorder:
        c = self.config
        return Recorder(directory=c.recordings_dir,
                        name=recording_name(self.intake.robot or "robots", client,
                                            c.record_codec),
                        fps=c.fps, codec=c.record_codec, source=source, settings=settings,
                        max_seconds=c.max_recording_s, max_bytes=c.max_recording_mb * MB,
                        min_free_bytes=c.min_free_disk_mb * MB)

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, fetch the latest state and registrations (late join), start threads."""
        self.intake.start()
        self.plots.start()
        self.pipeline.start()
        cameras = self.intake.camera_names
        robots = ("every robot whose estimator is alive" if self.config.discover
                  else "robot " + ", ".join(self.config.robots))
        log.info("viewer of %s, %s view%s", robots, self.config.resolved_view,
                 f" over {', '.join(cameras)}" if cameras else "")

    def stop(self) -> None:
        self.intake.stop()
        self.pipeline.stop()
        self.plots.stop()
        self.clients.stop_recordings()

    # -- the render thread's intake step ------------------------------------------
    def _ingest(self) -> None:
        """Take in what arrived; hand it to the parts that keep a history of it."""
        now = time.monotonic()
        if self.config.source == "summary":
            self._select_summary()
        new = self.intake.ingest()
        for arrived in new.robots:
            history = self.histories.get(arrived.robot)
            state = arrived.state
            if state is not None:
                if arrived.restarted:
                    history.new_map()  # a new map: its path, clusters and plots start over
                    self.eyes.restart()
                # the path remembers every state taken in, drawn or not: views render
                # only on demand, and a path started at the first render would be short
                history.renderer.track(state.robot, state.seq, state.pose[:2], state.epoch)
                history.tracked.add_estimate(state.stamp, state.pose)
                try:
                    if isinstance(state, SummarisedState):  # no cross terms: no P_d
                        pass
                    elif state.n * (state.n - 1) // 2 > DENSE_PAIRS:  # a large map
                        if history.series.due(now):  # off this thread: it only hands over
                            self.plots.offer(history.series, state, now)
                    else:
                        history.series.add_state(state, now=now)
                except Exception as exc:  # the plots are optional; the picture is not
                    self.failures.drop("plots", f"state seq {state.seq}: {exc!r}")
            if arrived.tracked is not None:
                history.tracked.set_tracked(arrived.tracked)
            for health in arrived.healths:
                history.series.add_health(health, now=now)

    def _prepare(self, robot: str, state: SlamState) -> None:
        """On the ``viewer-prepare`` thread, the first stage of a new state: the scenes of
        the views looked at (clusters, the overview, glyphs: the heavier half of a picture
        at n = 1000). One robot only (several draw under per-robot settings)."""
        if len(self.intake.robot_names) != 1:
            return
        health = self._health_of(robot)
        for view in self.clients.looked_at():
            self.composer.prepare_scene(robot, state, view.settings, health)

    def _finish(self, robot: str, state: SlamState) -> None:
        """On the ``viewer-layers`` thread, the second stage, while ``viewer-prepare``
        decodes the next state: over a camera, the state drawn on layers
        (:meth:`Composer.prepare_layers`), so the render thread only puts them over camera
        frames — of the previous state, meanwhile."""
        if len(self.intake.robot_names) != 1:
            return
        health = self._health_of(robot)
        frame = self.pipeline.last_frame
        for view in self.clients.looked_at():
            self.composer.prepare_layers(frame, robot, state, view.settings, health)

    def _health_of(self, robot: str) -> Health | None:
        return next((r.health for r in self.intake.snapshot().robots if r.name == robot),
                    None)

    def _select_summary(self) -> None:
        """``--source summary``: the summary queries ask for the pairs of the selection
        (a feature or a cluster) of the open view touched last that has one (issue 13
        item 3: full detail from the robot), else for the clusters."""
        selected = [v for v in self.clients.looked_at()
                    if v.settings.selected_feature is not None
                    or v.settings.selected_cluster is not None]
        choice: tuple[str | None, int | None, int | None] = (None, None, None)
        if selected:
            s = max(selected, key=lambda v: v.touched).settings
            choice = (s.selected_robot, s.selected_feature, s.selected_cluster)
        if choice != self._summary_selection:
            self._summary_selection = choice
            self.intake.summary_selection(choice[0], feature=choice[1], cluster=choice[2])

    # -- requests -----------------------------------------------------------------
    def reregister(self, robot: str | None) -> dict[str, Any]:
        """Ask the camera's registration service to register ``robot`` (None: every robot)
        again: a Zenoh query carrying a ``CameraControl`` (docs/registration.md), so a
        viewer identity that may publish nothing (SPEC §7b) can still ask; the service
        answers ``{"answer": "accepted: …" | "ignored: …" | "refused: …"}``. Blocks up to
        ``reregister_timeout_s``: call it off the web loop."""
        if robot is not None and robot not in self.intake.robot_names:
            raise ConfigError(f"robot {robot!r} is not shown by this viewer; shown: "
                              f"{', '.join(self.intake.robot_names) or 'none yet'}")
        camera = self.config.camera  # a stereo pair C-left / C-right is asked as C
        if camera is None:
            raise ConfigError("this viewer draws over no camera (the map view): nothing to "
                              "re-register")
        request = CameraControl(command="reregister", robot=robot,
                                requester=f"the web viewer at {self.config.http}").to_bytes()
        timeout = self.config.reregister_timeout_s
        try:
            replies = self.bus.get(self.keys.camera_control(camera), payload=request,
                                   timeout=timeout)
        except Exception as exc:  # the session closing, no route: say so
            replies, failure = [], str(exc)
        else:
            failure = (f"no registration service of camera {camera} answered within "
                       f"{timeout:g} s")
        answers = [_answer_text(r.payload) for r in replies]
        accepted = any(a.startswith("accepted") for a in answers)
        detail = "; ".join(answers) if answers else failure
        log.info("re-register %s on camera %s: %s", robot or "every robot", camera, detail)
        return {"robot": robot, "answered": bool(answers), "accepted": accepted,
                "cameras": [{"camera": camera, "answered": bool(answers), "detail": detail}]}


def _answer_text(payload: bytes) -> str:
    """The registration service's answer (``{"schema": 1, "answer": …}``) as one line."""
    try:
        answer = msgpack.unpackb(payload, raw=False)
    except Exception:  # not msgpack: show it as text
        return payload.decode("utf-8", "replace")[:200]
    if isinstance(answer, dict) and isinstance(answer.get("answer"), str):
        return answer["answer"][:200]
    return repr(answer)[:200]
