"""``slamlens figures``: regenerate the paper's Figs. 3-8 into ``docs/figures/``.

Paper §4: the simulated 15-feature, three-cluster world (``services/slam/worlds/paper.toml``)
run twice, once correct and once with the planted programming fault, each shown at the start
and at the end of the simulation in the three modes:

====  ==========  =======  =====================================
fig   mode        run      what it must show
====  ==========  =======  =====================================
3     all         correct  glyphs shrink from (a) to (b)
4     inter       correct  inter-cluster glyphs shrink
5     minmeanmax  correct  min / mean / max shrink
6     all         faulty   glyphs of the faulty features grow
7     inter       faulty   grow, cluttered
8     minmeanmax  faulty   the max grows while the min shrinks
====  ==========  =======  =====================================

"Start" is the first state in which every feature is mapped (so (a) and (b) show the same
pairs); "end" is the last state. The fault (``map-update`` on features 3 and 12 by default)
acts from ``fault_onset_s``, after the start picture, so (a) is the same picture in both runs
and only (b) differs, as in the paper. The picture behind the overlay is the synthetic
overhead camera (``services/registration/synthetic.py``) seeing the true robot and the true
features as posts, so estimated cones can be compared with the truth as in the paper's
photographs.

This is a composition-level tool, like ``services/commands/demo.py``: it joins the simulator and the
estimator (SLAM), the synthetic camera (registration) and the renderer (viewer) in one
process, which no service may do. Its settings are
:class:`slamlens.services.commands.settings.FigureSettings`.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slamlens.common.cli import setup_logging
from slamlens.common.config import settings_from_args
from slamlens.common.errors import RenderError
from slamlens.common.geometry import invert_T
from slamlens.common.messages import SlamState, Truth
from slamlens.services.commands.settings import FigureSettings
from slamlens.services.registration.synthetic import (
    ImagingSettings,
    SceneSettings,
    SyntheticCamera,
    look_at,
)
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.draw import text
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.settings import ViewSettings

log = logging.getLogger("slamlens.figures")

#: figure number → (mode, faulty run)
FIGURES: dict[int, tuple[str, bool]] = {
    3: ("all", False), 4: ("inter", False), 5: ("minmeanmax", False),
    6: ("all", True), 7: ("inter", True), 8: ("minmeanmax", True),
}


@dataclass(frozen=True)
class Snapshot:
    """One state to draw, with the truth at that time and the estimated path up to it."""

    state: SlamState
    truth: Truth
    path_xy: np.ndarray


def simulate(settings: FigureSettings, *, faulty: bool) -> tuple[Snapshot, Snapshot]:
    """Run the simulator into the estimator; return the (start, end) snapshots."""
    world = load_world(settings.world)
    sim = Simulator(world, seed=settings.seed)
    est_settings = (EstimatorSettings(fault=settings.fault,
                                      faulty_features=settings.faulty_features,
                                      fault_onset=settings.fault_onset_s)
                    if faulty else EstimatorSettings())
    est = Estimator(est_settings)
    truth: Truth | None = None
    path: list[np.ndarray] = []
    start: Snapshot | None = None
    last: Snapshot | None = None
    seq = 0
    for event in sim.events():
        if isinstance(event, Truth):
            truth = event
            continue
        seq += 1
        report = est.apply(event)
        if report is None:  # an odometry step
            path.append(est.pose[:2].copy())
            continue
        assert truth is not None  # the simulator sends truth first
        state = est.to_state(seq=seq, stamp=event.stamp, step="update", report=report)
        last = Snapshot(state, truth, np.array(path))
        if start is None and state.n == world.n_landmarks:
            start = last
    if start is None or last is None:
        raise RenderError("the simulated run never mapped every feature")
    return start, last


def overhead_camera(settings: FigureSettings) -> tuple[SyntheticCamera, CameraModel]:
    """The synthetic ceiling camera and the same camera as a CameraModel."""
    T_world_from_camera = look_at(settings.eye_m, settings.target_m)
    f = 0.62 * settings.width  # ~78° horizontal field of view: the arena fills the frame
    K = np.array([[f, 0.0, settings.width / 2], [0.0, f, settings.height / 2], [0, 0, 1.0]])
    synthetic = SyntheticCamera(K, settings.width, settings.height,
                                T_world_from_camera=T_world_from_camera,
                                scene=SceneSettings(),
                                imaging=ImagingSettings(blur_kernel=settings.blur_px))
    # With the simulator the world frame is the map frame (the robot starts at the origin).
    camera = CameraModel(K=K, dist=np.zeros(5), width=settings.width, height=settings.height,
                         T_camera_from_map=invert_T(T_world_from_camera))
    return synthetic, camera


def draw_snapshot(snapshot: Snapshot, *, mode: str, synthetic: SyntheticCamera,
                  camera: CameraModel,
                  view: ViewSettings, caption: str) -> np.ndarray:
    """One figure panel: the camera picture with the state drawn over it."""
    frame = synthetic.render(robot_pose=snapshot.truth.pose,
                             landmarks_xy=snapshot.truth.landmarks)
    renderer = Renderer()
    for k, xy in enumerate(snapshot.path_xy):
        renderer.track(snapshot.state.robot, k, xy)
    image = renderer.render(frame, state=snapshot.state, camera=camera,
                            settings=view.replace(mode=mode))
    scale = 0.6 * camera.height / 720
    text(image, caption, (12, camera.height - 14), scale=scale, thickness=1)
    return image


def generate_figures(output_dir: str | Path, settings: FigureSettings | None = None
                     ) -> list[Path]:
    """Write fig3a.png … fig8b.png into ``output_dir``; return the paths."""
    settings = settings or FigureSettings()
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs = {False: simulate(settings, faulty=False), True: simulate(settings, faulty=True)}
    synthetic, camera = overhead_camera(settings)
    written: list[Path] = []
    for number, (mode, faulty) in FIGURES.items():
        run = "faulty" if faulty else "correct"
        for letter, snap in zip("ab", runs[faulty], strict=True):
            when = "start" if letter == "a" else "end"
            caption = (f"Fig. {number}({letter}) {run} run, {when}: t = "
                       f"{snap.state.stamp:.1f} s")
            image = draw_snapshot(snap, mode=mode, synthetic=synthetic, camera=camera,
                                  view=settings.view, caption=caption)
            path = out / f"fig{number}{letter}.png"
            cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            written.append(path)
            log.info("wrote %s", path)
    return written


def run(command: str, args: argparse.Namespace) -> int:
    """``slamlens figures``: settings from ``--config`` and the flags, then the twelve PNGs."""
    setup_logging(args, "figures")
    settings = settings_from_args(FigureSettings, args)
    paths = generate_figures(settings.output_dir, settings)
    print(f"wrote {len(paths)} images to {Path(paths[0]).parent}")
    return 0
