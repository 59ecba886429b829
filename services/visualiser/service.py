"""The viewer service: bus inputs → rendered, JPEG-encoded views for any number of clients.

It is assembled from parts a reader can name, each in its own module:

* :class:`~services.visualiser.intake.Intake` — subscriptions, late join, decoding
  (thread ``viewer-decode`` decodes camera frames as they arrive);
* :class:`~services.visualiser.pipeline.RenderPipeline` — thread ``viewer-render`` takes
  in state / registration / health / tracked pose and renders every *active* view whose
  inputs changed, at most ``fps`` times a second; thread ``viewer-encode`` JPEG-encodes;
* :class:`~services.visualiser.compose.Composer` — what a picture shows, through the eyes
  an :class:`~services.visualiser.views.EyeChooser` picks (camera, map or stereo), with
  the camera-tracked pose matched by :class:`~services.visualiser.tracked.TrackedMatch`;
* :class:`~services.visualiser.clients.ClientRegistry` — each client's settings, each
  distinct view's picture, the video recorders;
* :class:`~services.visualiser.api.ViewerApi` — what the web layer asks.

None of the threads is a Zenoh callback; callbacks only store bytes (see :mod:`intake`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from common.bus import Bus
from common.drops import DropCounter
from common.keys import Keys
from services.visualiser.api import ViewerApi
from services.visualiser.clients import ClientRegistry
from services.visualiser.clusters import ClusterTracker, cluster_labels
from services.visualiser.compose import Composer
from services.visualiser.intake import Intake
from services.visualiser.pipeline import RenderPipeline
from services.visualiser.recording import MB, Recorder, recording_name
from services.visualiser.render import Renderer
from services.visualiser.series import SeriesStore
from services.visualiser.settings import ViewerConfig, ViewSettings
from services.visualiser.tracked import TrackedMatch
from services.visualiser.views import EyeChooser

log = logging.getLogger("slamlens.viewer")

class ViewerService:
    """One viewer: its parts wired together, started and stopped as one."""

    def __init__(self, bus: Bus, *, keys: Keys, config: ViewerConfig,
                 default_settings: ViewSettings | None = None) -> None:
        self.config = config
        self.default_settings = default_settings or ViewSettings()
        self.bad = DropCounter(log)  #: malformed input messages, by input
        self.failures = DropCounter(log)  #: states that could not be drawn or plotted
        self.series = SeriesStore(length=config.series_length,
                                  min_interval_s=config.series_interval_s,
                                  cluster=self._series_clusters())
        # one renderer for every view: it keeps the robot's path and the cluster identities
        # (per clustering setting), so switching a tab's mode keeps the path and colours
        self.renderer = Renderer()
        self.tracked = TrackedMatch()
        self.eyes = EyeChooser(config.resolved_view, robot=config.robot,
                               map_width=config.map_width, map_height=config.map_height,
                               stereo_baseline_m=config.stereo_baseline_m)
        self.clients = ClientRegistry(self.default_settings, ttl_s=config.client_ttl_s,
                                      on_new_view=self._wake, new_recorder=self._recorder,
                                      max_views=config.max_views,
                                      max_recordings=config.max_recordings)
        self.intake = Intake(bus, keys=keys, robot=config.robot, cameras=config.cameras,
                             fps=config.fps, late_join_timeout_s=config.late_join_timeout_s,
                             on_input=self._wake, drops=self.bad,
                             max_frame_pixels=config.max_frame_pixels)
        self.composer = Composer(self.intake, eyes=self.eyes, renderer=self.renderer,
                                 tracked=self.tracked, failures=self.failures)
        self.pipeline = RenderPipeline(self.composer, self.clients, ingest=self._ingest,
                                       fps=config.fps, jpeg_quality=config.jpeg_quality,
                                       other_views_share=config.other_views_share)
        self.api = ViewerApi(intake=self.intake, eyes=self.eyes, clients=self.clients,
                             pipeline=self.pipeline, series=self.series,
                             failures=self.failures, camera=config.camera,
                             recordings_dir=config.recordings_dir)
        self.started = time.monotonic()

    def _wake(self) -> None:
        self.pipeline.wake()

    def _series_clusters(self) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """Clusters of the plots' min/mean/max: the default settings' cut, stable ids."""
        tracker = ClusterTracker()
        threshold, count = (self.default_settings.cluster_threshold_m,
                            self.default_settings.cluster_count)

        def clusters(xy: np.ndarray, ids: np.ndarray) -> np.ndarray:
            return tracker.update(ids, cluster_labels(xy, threshold_m=threshold, count=count))

        return clusters

    def _recorder(self, client: str, source: Callable[[], np.ndarray | None],
                  settings: Callable[[], ViewSettings]) -> Recorder:
        c = self.config
        return Recorder(directory=c.recordings_dir,
                        name=recording_name(c.robot, client, c.record_codec),
                        fps=c.fps, codec=c.record_codec, source=source, settings=settings,
                        max_seconds=c.max_recording_s, max_bytes=c.max_recording_mb * MB,
                        min_free_bytes=c.min_free_disk_mb * MB)

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, fetch the latest state and registrations (late join), start threads."""
        self.intake.start()
        self.pipeline.start()
        cameras = self.intake.camera_names
        log.info("viewer of robot %s, %s view%s", self.config.robot, self.config.resolved_view,
                 f" over {', '.join(cameras)}" if cameras else "")

    def stop(self) -> None:
        self.intake.stop()
        self.pipeline.stop()
        self.clients.stop_recordings()

    # -- the render thread's intake step ------------------------------------------
    def _ingest(self) -> None:
        """Take in what arrived; hand it to the parts that keep a history of it."""
        now = time.monotonic()
        new = self.intake.ingest()
        state = new.state
        if state is not None:
            if new.restarted:
                self.eyes.restart()  # a new run: the map view starts over
            # the path remembers every state taken in, drawn or not: views render
            # only on demand, and a path started at the first render would be short
            self.renderer.track(state.robot, state.seq, state.pose[:2])
            self.tracked.add_estimate(state.stamp, state.pose)
            try:
                self.series.add_state(state, now=now)
            except Exception as exc:  # the plots are optional; the picture is not
                self.failures.drop("plots", f"state seq {state.seq}: {exc!r}")
        if new.tracked is not None:
            self.tracked.set_tracked(new.tracked)
        for health in new.healths:
            self.series.add_health(health, now=now)
