"""The viewer service: bus inputs → rendered, JPEG-encoded views for any number of clients.

It only wires together parts a reader can name, each in its own module (docs/viewer.md):

* :class:`~slamlens.services.visualiser.intake.Intake` — subscriptions, late join, the
  robots discovered (thread ``viewer-discover``), the summary pullers: raw slots only;
* :class:`~slamlens.services.visualiser.store.InputStore` — the newest decoded inputs;
* :class:`~slamlens.services.visualiser.pipeline.RenderPipeline` — a state's way from
  the raw slots to the pictures, and every thread on it (``viewer-decode``,
  ``viewer-prepare``, ``viewer-layers``, ``viewer-render``, ``viewer-encode``,
  ``viewer-plots``);
* :class:`~slamlens.services.visualiser.compose.Composer` — what a picture shows, through
  the eyes an :class:`~slamlens.services.visualiser.views.EyeChooser` picks (camera, map or
  stereo), with each robot's history (:mod:`robots`: path, cluster identities, plots,
  tracked pose);
* :class:`~slamlens.services.visualiser.clients.ClientRegistry` — each client's settings,
  each distinct view's picture, the video recorders;
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
from slamlens.common.messages import CameraControl
from slamlens.common.summary import SummaryQuery
from slamlens.services.visualiser.api import ViewerApi
from slamlens.services.visualiser.clients import ClientRegistry
from slamlens.services.visualiser.compose import Composer
from slamlens.services.visualiser.inputs import Wakeups
from slamlens.services.visualiser.intake import Intake
from slamlens.services.visualiser.pipeline import RenderPipeline
from slamlens.services.visualiser.recording import MB, Recorder, recording_name
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.robots import RobotHistories
from slamlens.services.visualiser.series import SeriesStore
from slamlens.services.visualiser.settings import ViewerConfig, ViewSettings
from slamlens.services.visualiser.store import InputStore
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
        wakeups = Wakeups()  #: what the intake's callbacks wake in the pipeline
        self.store = InputStore(robots=config.robots, cameras=config.cameras)
        self.intake = Intake(bus, keys=keys, wakeups=wakeups, robots=config.robots,
                             cameras=config.cameras,
                             late_join_timeout_s=config.late_join_timeout_s,
                             discover=config.discover, source=config.source,
                             summary_query=SummaryQuery(
                                 what="clusters", budget=config.summary_budget,
                                 threshold_m=ViewSettings().cluster_threshold_m,
                                 count=ViewSettings().cluster_count))
        # one history per robot for every view: the path and the cluster identities (per
        # clustering setting) survive a tab switching modes; a new map empties it
        self.histories = RobotHistories(self._new_series)
        self.eyes = EyeChooser(config.resolved_view, map_width=config.map_width,
                               map_height=config.map_height,
                               stereo_baseline_m=config.stereo_baseline_m)
        self.clients = ClientRegistry(self.default_settings, ttl_s=config.client_ttl_s,
                                      on_new_view=wakeups.input.set,
                                      new_recorder=self._recorder,
                                      max_views=config.max_views,
                                      max_recordings=config.max_recordings)
        self.composer = Composer(self.store, eyes=self.eyes, histories=self.histories,
                                 failures=self.failures,
                                 restart_note_s=config.restart_note_s)
        self.pipeline = RenderPipeline(self.intake, self.composer, self.clients,
                                       drops=self.bad, fps=config.fps,
                                       jpeg_quality=config.jpeg_quality,
                                       other_views_share=config.other_views_share,
                                       max_frame_pixels=config.max_frame_pixels)
        self.api = ViewerApi(store=self.store, eyes=self.eyes, clients=self.clients,
                             pipeline=self.pipeline, histories=self.histories, bad=self.bad,
                             failures=self.failures, camera=config.camera,
                             recordings_dir=config.recordings_dir,
                             discovering=config.discover,
                             restart_note_s=config.restart_note_s,
                             reregister=self.reregister)
        self.started = time.monotonic()

    @property
    def renderer(self) -> Renderer:
        """The first robot's renderer (its path and cluster identities)."""
        return self.histories.get(self.store.robot).renderer

    @property
    def series(self) -> SeriesStore:
        """The first robot's plots."""
        return self.histories.get(self.store.robot).series

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
                        name=recording_name(self.store.robot or "robots", client,
                                            c.record_codec),
                        fps=c.fps, codec=c.record_codec, source=source, settings=settings,
                        max_seconds=c.max_recording_s, max_bytes=c.max_recording_mb * MB,
                        min_free_bytes=c.min_free_disk_mb * MB)

    # -- life cycle ---------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, fetch the latest state and registrations (late join), start threads."""
        self.intake.start()
        self.pipeline.start()
        cameras = self.store.camera_names
        robots = ("every robot whose estimator is alive" if self.config.discover
                  else "robot " + ", ".join(self.config.robots))
        log.info("viewer of %s, %s view%s", robots, self.config.resolved_view,
                 f" over {', '.join(cameras)}" if cameras else "")

    def stop(self) -> None:
        self.intake.stop()
        self.pipeline.stop()
        self.clients.stop_recordings()

    # -- requests -----------------------------------------------------------------
    def reregister(self, robot: str | None) -> dict[str, Any]:
        """Ask the camera's registration service to register ``robot`` (None: every robot)
        again: a Zenoh query carrying a ``CameraControl`` (docs/registration.md), so a
        viewer identity that may publish nothing (docs/security.md) can still ask; the service
        answers ``{"answer": "accepted: …" | "ignored: …" | "refused: …"}``. Blocks up to
        ``reregister_timeout_s``: call it off the web loop."""
        if robot is not None and robot not in self.store.robot_names:
            raise ConfigError(f"robot {robot!r} is not shown by this viewer; shown: "
                              f"{', '.join(self.store.robot_names) or 'none yet'}")
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
