"""Where ``slamlens rerun`` puts things in a Rerun recording: entity paths, timelines, the
blueprint (pure; docs/rerun.md).

* ``world`` — the map frame, z up (``ViewCoordinates.RIGHT_HAND_Z_UP``):
  ``world/R/ellipsoids`` (the P_d glyphs of the mode), ``world/R/pairs`` (their lines),
  ``world/R/features`` (ids as labels), ``world/R/suspects``, ``world/R/robot``,
  ``world/R/path``, the ground truth under ``world/R/truth/`` (``robot``, ``path``,
  ``features``); a camera C is ``world/camera/C`` (its pose, ``Transform3D``) with
  ``world/camera/C/image`` (``Pinhole`` and the ``EncodedImage``): its 2D view shows the
  scene projected into the picture.
* ``plots/R/nees/…``, ``plots/R/nis/…`` (value, χ² band ``lo`` / ``hi``, window mean and
  its band), ``plots/R/pd/{min,mean,max}`` — ``Scalars``.
* ``log/R`` — the verdict and the violations, ``TextLog``.

Timelines: ``stamp`` (the data's own stamps: a duration from 0 for a simulated or dataset
clock, a date for Unix time) and ``seq`` (the estimator's state seq; what is not a state
carries the seq of the newest state seen).
"""

from __future__ import annotations

import rerun as rr
import rerun.blueprint as rrb

ROOT = "world"
TIMELINE_STAMP = "stamp"
TIMELINE_SEQ = "seq"
#: stamps at or above this (s, ≈ 3 years) are read as Unix time and shown as dates
UNIX_STAMP_S = 1e8
#: the statistics plotted, by group: Health.statistics key → series name
PLOTTED = {
    "nees": {"nees_pose": "value", "nees_pose_lo": "lo", "nees_pose_hi": "hi",
             "nees_pose_window_mean": "window_mean", "nees_pose_window_lo": "window_lo",
             "nees_pose_window_hi": "window_hi", "nees_features_mean": "features_mean"},
    "nis": {"nis": "value", "nis_lo": "lo", "nis_hi": "hi", "nis_window_mean": "window_mean",
            "nis_window_lo": "window_lo", "nis_window_hi": "window_hi"},
}
PD_SERIES = ("min", "mean", "max")


def part(name: str) -> str:
    """A robot or camera name as one entity path part."""
    return str(rr.escape_entity_path_part(name))


def robot_path(robot: str, leaf: str) -> str:
    return f"{ROOT}/{part(robot)}/{leaf}"


def truth_path(robot: str, leaf: str) -> str:
    return f"{ROOT}/{part(robot)}/truth/{leaf}"


def camera_path(camera: str) -> str:
    return f"{ROOT}/camera/{part(camera)}"


def image_path(camera: str) -> str:
    return f"{camera_path(camera)}/image"


def plot_path(robot: str, group: str, series: str = "") -> str:
    base = f"plots/{part(robot)}/{group}"
    return f"{base}/{series}" if series else base


def log_path(robot: str) -> str:
    return f"log/{part(robot)}"


def blueprint(robot: str, cameras: tuple[str, ...]) -> rrb.Blueprint:
    """The views a user opening the recording sees: the 3D map, each camera's picture with
    the scene projected into it, NEES, NIS and the P_d sizes over time, the text log."""
    world = rrb.Spatial3DView(name="map", origin=ROOT)
    pictures = [rrb.Spatial2DView(name=f"camera {c}", origin=image_path(c),
                                  contents=["$origin/**", f"{ROOT}/**"]) for c in cameras]
    plots = [rrb.TimeSeriesView(name=title, origin=plot_path(robot, group))
             for group, title in (("nees", "NEES (pose) and its χ² band"),
                                  ("nis", "NIS and its χ² band"),
                                  ("pd", "P_d size √λmax, m"))]
    text = rrb.TextLogView(name="verdict and violations", origin=log_path(robot))
    left: rrb.Container | rrb.View = (
        rrb.Vertical(world, *pictures) if pictures else world)
    return rrb.Blueprint(
        rrb.Horizontal(left, rrb.Vertical(*plots, text), column_shares=[3, 2]),
        collapse_panels=False)
