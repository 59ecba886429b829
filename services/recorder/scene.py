"""The viewer's picture as a Foxglove ``SceneUpdate``, built from one state (pure).

The geometry (pairs of the mode, glyph centres, axes, flags, colours) is
:mod:`slamlens.common.scene3d`'s; this module turns it into Foxglove's 3D entities in the
``map`` frame (z up):

* ``robot``: a green cone whose tip is the 2D estimate, and a flat yellow heading arrow;
* ``path``: the green line of the estimated positions so far (thinned beyond a length),
  sent at most once a second of robot time (an entity stays until it is replaced);
* ``features``: cyan cones, tips at the estimates, magenta for the monitor's suspects, and
  their ids as labels;
* ``pairs``: a yellow line per pair drawn, magenta for a pair the monitor flagged;
* ``ellipsoids``: the correlation glyphs as scaled spheres (semi-axes and yaw from
  ``scene3d``), red, magenta when flagged.

:func:`truth_update` is the ground truth beside it, as entities of their own
(``truth/robot``, ``truth/features``, ``truth/path``, light grey), on its own topic.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CylinderPrimitive,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from slamlens.common.messages import Health, SlamState, Truth
from slamlens.common.scene3d import (
    CONE_HEIGHT_M,
    CONE_RADIUS_M,
    ELLIPSOID,
    FEATURE,
    HEADING,
    LINE,
    MAP_FRAME,
    PATH,
    RGB,
    ROBOT,
    VIOLATION,
    PairGlyphs,
    SceneSettings,
    flagged_pairs,
    pair_glyphs,
)


def timestamp(ns: int) -> Timestamp:
    return Timestamp(int(ns // 1_000_000_000), int(ns % 1_000_000_000))


def _colour(rgb: RGB, a: float = 1.0) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def _yaw(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


_UPRIGHT = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def _cone(x: float, y: float, height: float, radius: float, rgb: RGB) -> CylinderPrimitive:
    """A cone standing on its tip at (x, y, 0): tip = the estimate (paper Fig. 3)."""
    return CylinderPrimitive(
        pose=Pose(position=Vector3(x=x, y=y, z=0.5 * height), orientation=_UPRIGHT),
        size=Vector3(x=2 * radius, y=2 * radius, z=height), bottom_scale=0.0, top_scale=1.0,
        color=_colour(rgb))


def _robot(pose: np.ndarray, rgb: RGB, arrow: Color, *, shaft: float, head_length: float,
           head_diameter: float) -> dict[str, list[Any]]:
    """A robot's primitives: a cone on its position and an arrow along its heading."""
    x, y, theta = (float(v) for v in pose)
    return {"cylinders": [_cone(x, y, 1.4 * CONE_HEIGHT_M, 1.4 * CONE_RADIUS_M, rgb)],
            "arrows": [ArrowPrimitive(
                pose=Pose(position=Vector3(x=x, y=y, z=0.01), orientation=_yaw(theta)),
                shaft_length=0.22, shaft_diameter=shaft, head_length=head_length,
                head_diameter=head_diameter, color=arrow)]}


def _path_line(points: list[Point3], thickness: float, colour: Color) -> dict[str, list[Any]]:
    """A path's primitives: one line strip, or none for fewer than two points."""
    return {"lines": [LinePrimitive(
        type=LinePrimitiveLineType.LineStrip, thickness=thickness, scale_invariant=False,
        points=points, color=colour)] if len(points) >= 2 else []}


def path_points(path_xy: np.ndarray) -> list[Point3]:
    """The robot path (k, 2) as Foxglove points on the floor."""
    return [Point3(x=x, y=y, z=0.0) for x, y in np.asarray(path_xy).reshape(-1, 2).tolist()]


def scene_update(state: SlamState, settings: SceneSettings, *, log_time_ns: int,
                 path_xy: np.ndarray | list[Point3] | None, health: Health | None = None,
                 new_map: bool = False) -> tuple[bytes, PairGlyphs]:
    """The encoded ``foxglove.SceneUpdate`` of ``state`` (and the glyphs it holds).

    ``path_xy`` is the path (k, 2) or already as points (:func:`path_points`, which a
    caller drawing many scenes keeps); None leaves the path entity out (Foxglove keeps
    showing the last one sent: it is the biggest entity, so it is sent less often).
    ``new_map`` first deletes everything shown (a new epoch: nothing of the old map stays).
    """
    stamp = timestamp(log_time_ns)
    meta = [KeyValuePair(key="robot", value=state.robot),
            KeyValuePair(key="seq", value=str(state.seq)),
            KeyValuePair(key="step", value=state.step),
            KeyValuePair(key="epoch", value=str(state.epoch)),
            KeyValuePair(key="mode", value=settings.mode)]

    def entity(name: str, **primitives: object) -> SceneEntity:
        return SceneEntity(timestamp=stamp, frame_id=MAP_FRAME, id=f"{state.robot}/{name}",
                           frame_locked=False, metadata=meta, **primitives)  # type: ignore

    robot = entity("robot", **_robot(state.pose, ROBOT, _colour(HEADING), shaft=0.02,
                                     head_length=0.08, head_diameter=0.07))
    points_of_path = [] if path_xy is None else (
        path_points(path_xy) if isinstance(path_xy, np.ndarray) else path_xy)
    path = None if path_xy is None else entity(
        "path", **_path_line(points_of_path, 0.015, _colour(PATH)))
    suspects = set() if health is None else set(health.suspects.tolist())
    lm_ids = state.landmark_ids.tolist()
    lm_xy = state.landmarks.tolist()
    white = _colour((1.0, 1.0, 1.0))
    features = entity(
        "features",
        cylinders=[_cone(p[0], p[1], CONE_HEIGHT_M, CONE_RADIUS_M,
                         VIOLATION if i in suspects else FEATURE)
                   for i, p in zip(lm_ids, lm_xy, strict=True)],
        texts=[TextPrimitive(pose=Pose(position=Vector3(x=p[0], y=p[1],
                                                        z=CONE_HEIGHT_M + 0.05),
                                       orientation=_UPRIGHT),
                             billboard=True, font_size=14.0, scale_invariant=True,
                             color=white, text=str(i))
               for i, p in zip(lm_ids, lm_xy, strict=True)])
    glyphs = pair_glyphs(state, settings, flagged_pairs(health))
    points: list[Point3] = []
    colours: list[Color] = []
    line, bad_line = _colour(LINE), _colour(VIOLATION)
    for seg, bad in zip(glyphs.lines_xy.tolist(), glyphs.line_flagged.tolist(), strict=True):
        c = bad_line if bad else line
        points += [Point3(x=seg[0][0], y=seg[0][1], z=0.0), Point3(x=seg[1][0], y=seg[1][1],
                                                                   z=0.0)]
        colours += [c, c]
    pairs = entity("pairs", lines=[LinePrimitive(
        type=LinePrimitiveLineType.LineList, thickness=0.01, scale_invariant=False,
        points=points, colors=colours, color=_colour(LINE))] if points else [])
    red, magenta = _colour(ELLIPSOID, 0.8), _colour(VIOLATION, 0.8)
    half = 0.5 * glyphs.yaw
    spheres = [SpherePrimitive(
        pose=Pose(position=Vector3(x=c[0], y=c[1], z=c[2]),
                  orientation=Quaternion(x=0.0, y=0.0, z=s, w=w)),
        size=Vector3(x=2 * ax[0], y=2 * ax[1], z=2 * ax[2]), color=magenta if bad else red)
        for c, ax, s, w, bad in zip(glyphs.centres.tolist(), glyphs.axes.tolist(),
                                    np.sin(half).tolist(), np.cos(half).tolist(),
                                    glyphs.flagged.tolist(), strict=True)]
    ellipsoids = entity("ellipsoids", spheres=spheres)
    deletions = [SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)] \
        if new_map else []
    entities = [robot, features, pairs, ellipsoids] + ([path] if path is not None else [])
    update = SceneUpdate(deletions=deletions, entities=entities)
    return update.encode(), glyphs


TRUTH: RGB = (0.85, 0.85, 0.85)  #: the ground truth, light grey beside the estimate


def truth_update(truth: Truth, *, log_time_ns: int, path: list[Point3]) -> bytes:
    """The encoded ``foxglove.SceneUpdate`` of the ground truth: the true robot (a grey cone
    and heading arrow), the true landmarks (small grey cones) and the true path so far."""
    stamp = timestamp(log_time_ns)
    meta = [KeyValuePair(key="robot", value=truth.robot),
            KeyValuePair(key="stamp", value=repr(float(truth.stamp)))]
    grey = _colour(TRUTH, 0.9)

    def entity(name: str, **primitives: object) -> SceneEntity:
        return SceneEntity(timestamp=stamp, frame_id=MAP_FRAME, id=f"{truth.robot}/truth/{name}",
                           frame_locked=False, metadata=meta, **primitives)  # type: ignore

    robot = entity("robot", **_robot(truth.pose, TRUTH, grey, shaft=0.015, head_length=0.07,
                                     head_diameter=0.05))
    features = entity("features", cylinders=[
        _cone(p[0], p[1], 0.6 * CONE_HEIGHT_M, 0.6 * CONE_RADIUS_M, TRUTH)
        for p in truth.landmarks.tolist()])
    line = entity("path", **_path_line(path, 0.01, grey))
    return SceneUpdate(entities=[robot, features, line]).encode()
