"""The picture the viewer draws, as 3D geometry in the map frame, for every 3D exporter.

One state (and the monitor's health) becomes what the viewer draws over the camera, as
numpy arrays in the ``map`` frame (z up, metres), for whatever scene format a consumer
speaks (Foxglove's SceneUpdate, ROS 2 markers, Rerun):

* the pairs of the chosen mode (``all``, ``inter``: pairs in different clusters,
  ``minmeanmax``: per cluster pair the min / mean / max P_d on the line between the
  centroids), each a yellow line and a red ellipsoid;
* each ellipsoid's centre (the pair's midpoint on the floor; in ``minmeanmax`` the mean on
  the centroid line, the min before and below it, the max after and above it), its semi-axes
  (major, minor, height = minor) from the eigenvalues of P_d (k-sigma or the paper's linear
  glyph) and the direction of its major axis;
* which pairs the monitor flagged (magenta).

:func:`summary_glyphs` places a robot's summary (the min / mean / max P_d per pair of
clusters or map tiles, docs/remote_viewers.md) as ``minmeanmax`` places a state's.

:class:`SceneSettings` is the choice of mode, clustering and glyph, as flags and TOML keys of
every exporter. The pair selection, clusters and eigen-decomposition are the viewer's own
helpers (``common/pairs.py``, ``common/clusters.py``, ``common/geometry.py``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from slamlens.common.clusters import cluster_labels
from slamlens.common.config import setting
from slamlens.common.geometry import all_relative_covariances, eig_sym2, pd_size_m, semi_axes
from slamlens.common.messages import Health, SlamState, StateSummary
from slamlens.common.pairs import min_mean_max, select_pairs

MODES = ("all", "inter", "minmeanmax")
GLYPHS = ("sigma", "linear")


@dataclass(frozen=True)
class SceneSettings:
    """What a 3D export draws of a state (paper §3.2; the viewer's defaults)."""

    mode: str = setting("all", doc="pairs drawn: all | inter (pairs in different clusters) | "
                                   "minmeanmax (per cluster pair the min / mean / max P_d)",
                        choices=MODES, group="scene")
    cluster_threshold_m: float = setting(
        0.6, doc="single-linkage cut distance of the clusters (when --cluster-count is 0)",
        unit="m", min=1e-6, flag="--cluster-threshold", metavar="M", group="scene")
    cluster_count: int = setting(0, doc=">0: cut the dendrogram into this many clusters "
                                        "instead", min=0, group="scene")
    glyph: str = setting("sigma", doc="sigma: semi-axes = k·√eigenvalue of P_d | linear: "
                                      "semi-axes = eigenvalues read as metres (the paper's)",
                         choices=GLYPHS, group="scene")
    sigma_k: float = setting(2.0, doc="k of the k-sigma glyph", min=1e-6,
                             group="scene")
    scale: float = setting(1.0, doc="extra factor on every glyph axis", min=1e-6,
                           flag="--glyph-scale", group="scene")
    minmeanmax_spread: float = setting(
        0.15, doc="minmeanmax: the min and max glyphs sit this fraction of the centroid line "
                  "before / after the mean", min=0.0, flag=False, group="scene")
    path_points: int = setting(2000, doc="longest robot path drawn (older points thinned)",
                               min=2, flag=False, group="scene")

    def scene_settings(self) -> SceneSettings:
        """Only the scene's fields (of a subclass's settings)."""
        return SceneSettings(**{f.name: getattr(self, f.name)
                                for f in dataclasses.fields(SceneSettings)})



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
    #: (G, 2) landmark indices (state order, i < j) of each glyph's pair; in minmeanmax the
    #: min / max glyph's pair and (-1, -1) for a mean (exporters key stable ids on it)
    pairs: np.ndarray


def flagged_pairs(health: Health | None) -> frozenset[tuple[int, int]]:
    """(smaller id, larger id) of the pairs the monitor's ``pair`` violations name."""
    if health is None:
        return frozenset()
    return frozenset((min(v.ids), max(v.ids)) for v in health.violations
                     if v.kind == "pair" and len(v.ids) == 2)


def _axes(P: np.ndarray, settings: SceneSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Semi-axes (major, minor) and major-axis direction of the glyphs of P_d (k, 2, 2)."""
    lam1, lam2, yaw = eig_sym2(P)
    a, b = semi_axes(lam1, lam2, glyph=settings.glyph, sigma_k=settings.sigma_k,
                     scale=settings.scale)
    return a, b, yaw


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

    if mode != "minmeanmax" or clusters is None:
        a, b, yaw = _axes(Pd, settings)
        mid = 0.5 * (xy[ii] + xy[jj]) if len(ii) else np.zeros((0, 2))
        return PairGlyphs(
            lines_xy=np.stack([xy[ii], xy[jj]], axis=1).reshape(-1, 2, 2),
            line_flagged=pair_flags, centres=np.column_stack([mid, np.zeros(len(mid))]),
            axes=np.column_stack([a, b, b]).reshape(-1, 3), yaw=yaw.reshape(-1),
            flagged=pair_flags, role=np.zeros(len(ii), np.int64),
            sizes_m=pd_size_m(Pd).reshape(-1),
            pairs=np.column_stack([ii, jj]).astype(np.int64).reshape(-1, 2))
    stats = min_mean_max(ii, jj, Pd, clusters)
    group_flag = np.zeros(len(stats.clusters), dtype=bool)
    if pair_flags.any():
        lo = np.minimum(clusters[ii], clusters[jj])[pair_flags]
        hi = np.maximum(clusters[ii], clusters[jj])[pair_flags]
        bad = set(zip(lo.tolist(), hi.tolist(), strict=True))
        group_flag = np.array([(int(p), int(q)) in bad for p, q in stats.clusters], dtype=bool)
    ij = np.column_stack([ii, jj])
    return _group_glyphs(xy, clusters, stats.clusters, Pd[stats.min_pair], stats.mean_Pd,
                         Pd[stats.max_pair], (pair_flags[stats.min_pair], group_flag,
                                              pair_flags[stats.max_pair]), settings,
                         (ij[stats.min_pair], ij[stats.max_pair]))


def _group_glyphs(xy: np.ndarray, labels: np.ndarray, groups: np.ndarray, Pd_min: np.ndarray,
                  mean_Pd: np.ndarray, Pd_max: np.ndarray,
                  flags: tuple[np.ndarray, np.ndarray, np.ndarray],
                  settings: SceneSettings,
                  extremes: tuple[np.ndarray, np.ndarray]) -> PairGlyphs:
    """The min / mean / max glyphs of each pair of groups ``groups`` (c, 2) on the line
    between the groups' centroids (``labels``: group per landmark; ``extremes``: the
    landmark indices (c, 2) of the min and of the max pairs)."""
    c = len(groups)
    centroids = {int(k): xy[labels == k].mean(axis=0) for k in np.unique(labels).tolist()}
    start = np.array([centroids[int(k)] for k in groups[:, 0]]).reshape(-1, 2)
    end = np.array([centroids[int(k)] for k in groups[:, 1]]).reshape(-1, 2)
    P3 = np.concatenate([Pd_min, mean_Pd, Pd_max]).reshape(-1, 2, 2)
    a, b, yaw = _axes(P3, settings)
    h_min, h_mean, h_max = b[:c], b[c:2 * c], b[2 * c:]
    spread = settings.minmeanmax_spread
    t = np.concatenate([np.full(c, 0.5 - spread), np.full(c, 0.5), np.full(c, 0.5 + spread)])
    z = np.concatenate([-(h_mean + h_min), np.zeros(c), h_mean + h_max])
    s0, s1 = np.tile(start, (3, 1)), np.tile(end, (3, 1))
    centres = np.column_stack([s0 + t[:, None] * (s1 - s0), z])
    return PairGlyphs(
        lines_xy=np.stack([start, end], axis=1).reshape(-1, 2, 2), line_flagged=flags[1],
        centres=centres.reshape(-1, 3), axes=np.column_stack([a, b, b]).reshape(-1, 3),
        yaw=yaw.reshape(-1), flagged=np.concatenate(flags).astype(bool),
        role=np.repeat(np.arange(1, 4), c).astype(np.int64), sizes_m=pd_size_m(P3).reshape(-1),
        pairs=np.concatenate([extremes[0].reshape(-1, 2), np.full((c, 2), -1),
                              extremes[1].reshape(-1, 2)]).astype(np.int64))


def summary_glyphs(summary: StateSummary, settings: SceneSettings,
                   flagged: frozenset[tuple[int, int]] = frozenset()) -> PairGlyphs:
    """The glyphs of a robot's summary (``what = clusters``, docs/remote_viewers.md): per
    pair of its groups the min / mean / max P_d it sent, placed as ``minmeanmax`` places
    them, whatever ``settings.mode`` says; none for a blocks-only summary."""
    groups = summary.groups
    if (summary.group_pairs is None or groups is None or summary.min_pair is None
            or summary.max_pair is None or summary.min_Pd is None or summary.mean_Pd is None
            or summary.max_Pd is None or summary.n < 2):
        return PairGlyphs(np.zeros((0, 2, 2)), np.zeros(0, bool), np.zeros((0, 3)),
                          np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool),
                          np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2), np.int64))
    ids = summary.landmark_ids

    def pair_flag(pairs: np.ndarray) -> np.ndarray:
        a, b = ids[pairs[:, 0]], ids[pairs[:, 1]]
        return np.array([(int(min(x, y)), int(max(x, y))) in flagged
                         for x, y in zip(a.tolist(), b.tolist(), strict=True)], dtype=bool)

    index = {int(v): k for k, v in enumerate(ids.tolist())}
    bad = set()
    for a, b in flagged:
        i, j = index.get(a), index.get(b)
        if i is not None and j is not None and groups[i] != groups[j]:
            bad.add((int(min(groups[i], groups[j])), int(max(groups[i], groups[j]))))
    group_flag = np.array([(int(a), int(b)) in bad for a, b in summary.group_pairs.tolist()],
                          dtype=bool)
    return _group_glyphs(
        summary.landmarks.astype(float), groups, summary.group_pairs,
        summary.min_Pd.astype(float), summary.mean_Pd.astype(float),
        summary.max_Pd.astype(float),
        (pair_flag(summary.min_pair), group_flag, pair_flag(summary.max_pair)), settings,
        (summary.min_pair, summary.max_pair))
