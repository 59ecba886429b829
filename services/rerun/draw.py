"""One state, summary, truth, health, registration or camera frame as Rerun archetypes
(pure; where each goes: :mod:`.entities`).

The 3D geometry is :mod:`slamlens.common.scene3d`'s — the pairs of the mode, each glyph's
centre, semi-axes and major-axis direction, the flags — the same as the viewer's and the
Foxglove scene's. Here it becomes ``Ellipsoids3D`` (centres, half sizes = the semi-axes,
a rotation about z by the major axis's direction), ``LineStrips3D`` (pair lines, paths),
``Points3D`` (features with their ids as labels, suspects), ``Arrows3D`` (headings),
``Transform3D`` + ``Pinhole`` (a camera, from its registration), ``EncodedImage`` (its
JPEG), ``Scalars`` and ``TextLog``. Rerun stores positions as float32.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import rerun as rr

from slamlens.common.errors import MessageError
from slamlens.common.messages import CameraFrame, Health, Registration
from slamlens.common.scene3d import (
    ELLIPSOID,
    FEATURE,
    HEADING,
    LINE,
    PATH,
    RGB,
    ROBOT,
    VIOLATION,
    PairGlyphs,
)
from slamlens.common.verdict import summary_text, violation_text
from slamlens.services.rerun.entities import (
    PD_SERIES,
    PLOTTED,
    camera_path,
    image_path,
    log_path,
    plot_path,
    robot_path,
    truth_path,
)

TRUTH: RGB = (0.85, 0.85, 0.85)  #: the ground truth: light grey beside the estimate
HEADING_M = 0.25  #: length of a heading arrow
FEATURE_RADIUS_M = 0.03
SUSPECT_RADIUS_M = 0.07
ROBOT_RADIUS_M = 0.06
LINE_RADIUS_M = 0.004
PATH_RADIUS_M = 0.008
GLYPH_ALPHA = 0.8
MAX_VIOLATION_LINES = 10  #: per health; the rest is one "… and N more" line
JPEG_MAGIC = b"\xff\xd8\xff"


@dataclass(frozen=True)
class Log:
    """One ``RecordingStream.log`` call: the archetypes logged together at ``path``."""

    path: str
    parts: tuple[Any, ...]
    static: bool = False


def rgba(rgb: RGB, alpha: float = 1.0) -> np.ndarray:
    """An RGB 0–1 colour as Rerun's RGBA uint8."""
    return np.array([round(255 * c) for c in (*rgb, alpha)], dtype=np.uint8)


def colours(flags: np.ndarray, normal: RGB, flagged: RGB, alpha: float = 1.0) -> np.ndarray:
    """(k, 4) uint8: ``flagged`` where ``flags``, else ``normal``."""
    return np.where(np.asarray(flags, bool).reshape(-1, 1), rgba(flagged, alpha),
                    rgba(normal, alpha)).astype(np.uint8).reshape(-1, 4)


def on_floor(xy: np.ndarray) -> np.ndarray:
    """(k, 2) map points as (k, 3) with z = 0."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return np.column_stack([xy, np.zeros(len(xy))])


def yaw_quaternions(yaw: np.ndarray) -> np.ndarray:
    """(k, 4) quaternions (x, y, z, w) of rotations by ``yaw`` about z."""
    half = 0.5 * np.asarray(yaw, dtype=float).reshape(-1)
    zeros = np.zeros_like(half)
    return np.column_stack([zeros, zeros, np.sin(half), np.cos(half)])


def glyph_logs(robot: str, glyphs: PairGlyphs) -> list[Log]:
    """The P_d ellipsoids and the pair lines of one picture."""
    ellipsoids = rr.Ellipsoids3D(
        centers=glyphs.centres, half_sizes=glyphs.axes, quaternions=yaw_quaternions(glyphs.yaw),
        colors=colours(glyphs.flagged, ELLIPSOID, VIOLATION, GLYPH_ALPHA),
        fill_mode=rr.components.FillMode.Solid)
    segments = np.concatenate([glyphs.lines_xy, np.zeros((len(glyphs.lines_xy), 2, 1))],
                              axis=2) if len(glyphs.lines_xy) else np.zeros((0, 2, 3))
    lines = rr.LineStrips3D(segments,  # type: ignore[arg-type]  # (k, 2, 3): the SDK's fast path
                            radii=LINE_RADIUS_M,
                            colors=colours(glyphs.line_flagged, LINE, VIOLATION))
    return [Log(robot_path(robot, "ellipsoids"), (ellipsoids,)),
            Log(robot_path(robot, "pairs"), (lines,))]


def features_logs(robot: str, ids: np.ndarray, xy: np.ndarray,
                  suspects: Sequence[int]) -> list[Log]:
    """The features (ids as labels; the monitor's suspects magenta) and the suspects."""
    ids_list = [int(i) for i in np.asarray(ids).reshape(-1).tolist()]
    blamed = set(suspects)
    flags = np.array([i in blamed for i in ids_list], dtype=bool)
    points = on_floor(xy)
    features = rr.Points3D(points, radii=FEATURE_RADIUS_M, labels=[str(i) for i in ids_list],
                           colors=colours(flags, FEATURE, VIOLATION))
    suspect = rr.Points3D(points[flags], radii=SUSPECT_RADIUS_M,
                          labels=[f"suspect {i}" for i, f in zip(ids_list, flags, strict=True)
                                  if f], colors=rgba(VIOLATION, 0.5))
    return [Log(robot_path(robot, "features"), (features,)),
            Log(robot_path(robot, "suspects"), (suspect,))]


def pose_log(path: str, pose: np.ndarray, body: RGB, heading: RGB, label: str) -> Log:
    """A robot: a point at its position and an arrow along its heading."""
    x, y, theta = (float(v) for v in np.asarray(pose).reshape(3))
    at = np.array([[x, y, 0.0]])
    return Log(path, (rr.Points3D(at, radii=ROBOT_RADIUS_M, colors=rgba(body), labels=[label]),
                      rr.Arrows3D(origins=at, vectors=[[HEADING_M * math.cos(theta),
                                                        HEADING_M * math.sin(theta), 0.0]],
                                  colors=rgba(heading))))


def robot_log(robot: str, pose: np.ndarray) -> Log:
    return pose_log(robot_path(robot, "robot"), pose, ROBOT, HEADING, robot)


def path_log(path: str, xy: Sequence[tuple[float, float]], rgb: RGB) -> Log:
    """A path on the floor (one line strip; empty below two points)."""
    points = on_floor(np.asarray(xy, dtype=float).reshape(-1, 2))
    strips = [points] if len(points) >= 2 else []
    return Log(path, (rr.LineStrips3D(strips, radii=PATH_RADIUS_M, colors=rgba(rgb)),))


def robot_path_log(robot: str, xy: Sequence[tuple[float, float]]) -> Log:
    return path_log(robot_path(robot, "path"), xy, PATH)


def truth_logs(robot: str, pose: np.ndarray | None = None, *, ids: np.ndarray | None = None,
               xy: np.ndarray | None = None) -> list[Log]:
    """The ground truth: the true pose, and the true landmarks when given."""
    out = []
    if pose is not None:
        out.append(pose_log(truth_path(robot, "robot"), pose, TRUTH, TRUTH, f"{robot} truth"))
    if ids is not None and xy is not None:
        out.append(Log(truth_path(robot, "features"), (rr.Points3D(
            on_floor(xy), radii=0.6 * FEATURE_RADIUS_M, colors=rgba(TRUTH),
            labels=[str(int(i)) for i in np.asarray(ids).reshape(-1).tolist()],
            show_labels=False),)))
    return out


def pd_logs(robot: str, sizes_m: np.ndarray) -> list[Log]:
    """min / mean / max of the P_d sizes (√λmax, m) of the glyphs drawn (none: nothing)."""
    sizes = np.asarray(sizes_m, dtype=float).reshape(-1)
    if not sizes.size:
        return []
    values = (float(sizes.min()), float(sizes.mean()), float(sizes.max()))
    return [Log(plot_path(robot, "pd", name), (rr.Scalars(v),))
            for name, v in zip(PD_SERIES, values, strict=True)]


def health_logs(robot: str, health: Health, previous_verdict: str | None) -> list[Log]:
    """NEES, NIS and their χ² bands as scalars; the verdict when it changes and the state's
    violations as text."""
    out = []
    for group, names in PLOTTED.items():
        for key, series in names.items():
            value = health.statistics.get(key)
            if value is not None and math.isfinite(value):
                out.append(Log(plot_path(robot, group, series), (rr.Scalars(float(value)),)))
    if health.verdict != previous_verdict:
        level = {"ok": rr.TextLogLevel.INFO, "tuning": rr.TextLogLevel.WARN}.get(
            health.verdict, rr.TextLogLevel.ERROR)
        out.append(Log(log_path(robot), (rr.TextLog(
            f"verdict at seq {health.seq}: {summary_text(health)}", level=level),)))
    lines = [violation_text(v) for v in health.violations[:MAX_VIOLATION_LINES]]
    if len(health.violations) > MAX_VIOLATION_LINES:
        lines.append(f"… and {len(health.violations) - MAX_VIOLATION_LINES} more violations "
                     f"at seq {health.seq}")
    for text, v in zip(lines, [*health.violations[:MAX_VIOLATION_LINES], None], strict=False):
        level = (rr.TextLogLevel.WARN if v is not None and v.kind in ("nees", "nis")
                 else rr.TextLogLevel.ERROR)
        out.append(Log(log_path(robot), (rr.TextLog(f"seq {health.seq}: {text}",
                                                    level=level),)))
    return out


def camera_logs(reg: Registration) -> list[Log]:
    """A camera's pose in the map (``T_camera_from_map``) and its pinhole model (K, size).
    Rerun's pinhole has no lens distortion: the projected scene ignores ``dist``."""
    T = np.asarray(reg.T_camera_from_map, dtype=float)
    if not np.all(np.isfinite(T)) or abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-3:
        raise MessageError("Registration", "T_camera_from_map", "a rigid transform",
                           "not a rotation")
    pose = rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3],
                          relation=rr.TransformRelation.ChildFromParent)
    pinhole = rr.Pinhole(image_from_camera=np.asarray(reg.K, dtype=float),
                         resolution=[int(reg.width), int(reg.height)],
                         camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.5)
    return [Log(camera_path(reg.camera), (pose,)), Log(image_path(reg.camera), (pinhole,))]


def image_log(frame: CameraFrame) -> Log:
    """A camera frame's JPEG, as it is (Rerun decodes it)."""
    if not bytes(frame.data[:3]) == JPEG_MAGIC:
        raise MessageError("CameraFrame", "data", "a JPEG (FF D8 FF …)",
                           bytes(frame.data[:3]).hex() or "empty")
    return Log(image_path(frame.camera), (rr.EncodedImage(contents=bytes(frame.data),
                                                          media_type="image/jpeg"),))


#: how each plotted series looks: (RGB, width px)
_BAND: tuple[RGB, float] = ((0.6, 0.6, 0.6), 1.0)
SERIES_STYLE: dict[str, tuple[RGB, float]] = {
    "value": ((0.1, 0.45, 0.9), 1.5), "lo": _BAND, "hi": _BAND,
    "window_mean": ((0.95, 0.55, 0.1), 2.0), "window_lo": ((0.8, 0.7, 0.55), 1.0),
    "window_hi": ((0.8, 0.7, 0.55), 1.0), "features_mean": ((0.2, 0.7, 0.3), 1.0),
    "min": ((0.2, 0.7, 0.3), 1.5), "mean": ((0.1, 0.45, 0.9), 1.5), "max": (ELLIPSOID, 1.5),
}


def static_logs(robot: str) -> list[Log]:
    """What never changes: the map frame's axes (z up) and how each plotted series looks."""
    out = [Log("world", (rr.ViewCoordinates.RIGHT_HAND_Z_UP,), static=True)]
    groups = {**{g: list(names.values()) for g, names in PLOTTED.items()},
              "pd": list(PD_SERIES)}
    for group, series in groups.items():
        for name in series:
            rgb, width = SERIES_STYLE[name]
            out.append(Log(plot_path(robot, group, name), (rr.SeriesLines(
                colors=rgba(rgb), widths=width, names=f"{group} {name}"),), static=True))
    return out
