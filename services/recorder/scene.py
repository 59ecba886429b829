"""The SPEC §6 picture as a Foxglove ``SceneUpdate``, built from one state (pure).

What the viewer draws over the camera, as 3D entities in the ``map`` frame (z up):

* ``robot``: a green cone whose tip is the 2D estimate, and a flat yellow heading arrow;
* ``path``: the green line of the estimated positions so far (thinned beyond a length),
  sent at most once a second of robot time (an entity stays until it is replaced);
* ``features``: cyan cones, tips at the estimates, magenta for the monitor's suspects, and
  their ids as labels;
* ``pairs``: a yellow line per pair drawn (per cluster pair, between the centroids, in
  ``minmeanmax``), magenta for a pair the monitor flagged;
* ``ellipsoids``: the correlation glyphs as scaled spheres: axes along the eigenvectors of
  P_d, semi-axes from its eigenvalues (k-sigma or the paper's linear), the minor axis as the
  height, centred at the pair's midpoint on the floor; red, magenta when flagged. In
  ``minmeanmax`` the mean sits on the centroid line, the min before and below it, the max
  after and above it, as in the viewer (docs/visualisation.md).

The pair selection, clusters and eigen-decomposition are the viewer's own helpers
(``common/pairs.py``, ``common/clusters.py``, ``common/geometry.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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

from slamlens.common.clusters import cluster_labels
from slamlens.common.geometry import all_relative_covariances, eig_sym2, pd_size_m, semi_axes
from slamlens.common.messages import Health, SlamState
from slamlens.common.pairs import min_mean_max, select_pairs
from slamlens.services.recorder.settings import SceneSettings

MAP_FRAME = "map"
RGB = tuple[float, float, float]
#: the paper's colours (the viewer's defaults, as RGB 0-1)
ROBOT: RGB = (40 / 255, 200 / 255, 40 / 255)
HEADING: RGB = (1.0, 230 / 255, 0.0)
PATH: RGB = ROBOT
FEATURE: RGB = (0.0, 230 / 255, 230 / 255)
LINE: RGB = (1.0, 230 / 255, 0.0)
ELLIPSOID: RGB = (220 / 255, 30 / 255, 30 / 255)
VIOLATION: RGB = (1.0, 0.0, 1.0)
CONE_HEIGHT_M = 0.15
CONE_RADIUS_M = 0.045
ROLE_NAMES = ("pair", "min", "mean", "max")


@dataclass(frozen=True)
class PairGlyphs:
    """Lines and ellipsoids of the pairs one mode draws (numpy, map frame, m)."""

    lines_xy: np.ndarray  #: (L, 2, 2) segment end points
    line_flagged: np.ndarray  #: (L,) bool: the monitor flagged the pair (or cluster pair)
    centres: np.ndarray  #: (G, 3) ellipsoid centres
    axes: np.ndarray  #: (G, 3) semi-axes: major, minor, height (= minor)
    yaw: np.ndarray  #: (G,) direction of the major axis, rad
    flagged: np.ndarray  #: (G,) bool
    role: np.ndarray  #: (G,) 0 pair, 1 min, 2 mean, 3 max
    sizes_m: np.ndarray  #: (G,) √λmax of each glyph's P_d


def flagged_pairs(health: Health | None) -> frozenset[tuple[int, int]]:
    """(smaller id, larger id) of the pairs the monitor's ``pair`` violations name."""
    if health is None:
        return frozenset()
    return frozenset((min(v.ids), max(v.ids)) for v in health.violations
                     if v.kind == "pair" and len(v.ids) == 2)


def pair_glyphs(state: SlamState, settings: SceneSettings,
                flagged: frozenset[tuple[int, int]] = frozenset()) -> PairGlyphs:
    """The pairs ``settings.mode`` draws for ``state``, with their glyphs."""
    n = state.n
    ids, xy = state.landmark_ids, state.landmarks
    mode = settings.mode
    clusters = None
    if mode != "all":
        clusters = cluster_labels(xy, threshold_m=settings.cluster_threshold_m,
                                  count=settings.cluster_count)
    if n < 2:
        ii = jj = np.zeros(0, dtype=np.int64)
        Pd = np.zeros((0, 2, 2))
    else:
        ii, jj = select_pairs(n, mode=mode, cluster_ids=clusters)
        _, _, Pd_all = all_relative_covariances(state.covariance, n)
        Pd = Pd_all[(ii * (2 * n - ii - 1)) // 2 + (jj - ii - 1)]
    keys = list(zip(np.minimum(ids[ii], ids[jj]).tolist(),
                    np.maximum(ids[ii], ids[jj]).tolist(), strict=True))
    pair_flags = np.array([k in flagged for k in keys], dtype=bool)

    def axes_of(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lam1, lam2, yaw = eig_sym2(P)
        a, b = semi_axes(lam1, lam2, glyph=settings.glyph, sigma_k=settings.sigma_k,
                         scale=settings.scale)
        return a, b, yaw

    if mode != "minmeanmax" or clusters is None:
        a, b, yaw = axes_of(Pd)
        mid = 0.5 * (xy[ii] + xy[jj]) if len(ii) else np.zeros((0, 2))
        return PairGlyphs(
            lines_xy=np.stack([xy[ii], xy[jj]], axis=1).reshape(-1, 2, 2),
            line_flagged=pair_flags, centres=np.column_stack([mid, np.zeros(len(mid))]),
            axes=np.column_stack([a, b, b]).reshape(-1, 3), yaw=yaw.reshape(-1),
            flagged=pair_flags, role=np.zeros(len(ii), np.int64),
            sizes_m=pd_size_m(Pd).reshape(-1))
    stats = min_mean_max(ii, jj, Pd, clusters)
    c = len(stats.clusters)
    centroids = {int(k): xy[clusters == k].mean(axis=0) for k in np.unique(clusters).tolist()}
    start = np.array([centroids[int(k)] for k in stats.clusters[:, 0]]).reshape(-1, 2)
    end = np.array([centroids[int(k)] for k in stats.clusters[:, 1]]).reshape(-1, 2)
    group_flag = np.zeros(c, dtype=bool)
    if pair_flags.any():
        lo = np.minimum(clusters[ii], clusters[jj])[pair_flags]
        hi = np.maximum(clusters[ii], clusters[jj])[pair_flags]
        bad = set(zip(lo.tolist(), hi.tolist(), strict=True))
        group_flag = np.array([(int(p), int(q)) in bad for p, q in stats.clusters], dtype=bool)
    P3 = np.concatenate([Pd[stats.min_pair], stats.mean_Pd, Pd[stats.max_pair]])
    a, b, yaw = axes_of(P3)
    h_min, h_mean, h_max = b[:c], b[c:2 * c], b[2 * c:]
    spread = settings.minmeanmax_spread
    t = np.concatenate([np.full(c, 0.5 - spread), np.full(c, 0.5), np.full(c, 0.5 + spread)])
    z = np.concatenate([-(h_mean + h_min), np.zeros(c), h_mean + h_max])
    s0, s1 = np.tile(start, (3, 1)), np.tile(end, (3, 1))
    centres = np.column_stack([s0 + t[:, None] * (s1 - s0), z])
    flags = np.concatenate([pair_flags[stats.min_pair], group_flag, pair_flags[stats.max_pair]])
    return PairGlyphs(
        lines_xy=np.stack([start, end], axis=1).reshape(-1, 2, 2), line_flagged=group_flag,
        centres=centres.reshape(-1, 3), axes=np.column_stack([a, b, b]).reshape(-1, 3),
        yaw=yaw.reshape(-1), flagged=flags.astype(bool),
        role=np.repeat(np.arange(1, 4), c).astype(np.int64), sizes_m=pd_size_m(P3).reshape(-1))


# -------------------------------------------------------------------------- Foxglove


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

    x, y, theta = (float(v) for v in state.pose)
    robot = entity("robot", cylinders=[_cone(x, y, 1.4 * CONE_HEIGHT_M, 1.4 * CONE_RADIUS_M,
                                             ROBOT)],
                   arrows=[ArrowPrimitive(
                       pose=Pose(position=Vector3(x=x, y=y, z=0.01), orientation=_yaw(theta)),
                       shaft_length=0.22, shaft_diameter=0.02, head_length=0.08,
                       head_diameter=0.07, color=_colour(HEADING))])
    points_of_path = [] if path_xy is None else (
        path_points(path_xy) if isinstance(path_xy, np.ndarray) else path_xy)
    path = None if path_xy is None else entity("path", lines=[LinePrimitive(
        type=LinePrimitiveLineType.LineStrip, thickness=0.015, scale_invariant=False,
        points=points_of_path, color=_colour(PATH))] if len(points_of_path) >= 2 else [])
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
