"""What to draw for one state and one ``ViewSettings``: pairs, lines and glyphs (pure).

Modes (SPEC §6, paper §3.2):

* ``all``: every pair i < j of features.
* ``inter``: only pairs whose features lie in different clusters.
* ``minmeanmax``: per pair of clusters, a line between the cluster centroids and three
  glyphs: the smallest P_d, the element-wise mean P_d and the largest P_d over the
  inter-cluster pairs of that cluster pair.

"Smallest" and "largest" are by ``common.geometry.pd_size_m``, √λmax of P_d (the 1-σ major
semi-axis, m), the one size measure slamlens uses everywhere (monitor, viewer plots, demo).
It is Loewner-monotone, so a shrinking P_d never looks larger, and it is what the eye reads
from a glyph: its longest axis. The mean glyph is not ranked and, being an element-wise mean,
can be rounder and so smaller than the min glyph when the pairs' P_d point different ways.

Placement in ``minmeanmax``: the mean sits at the middle of the centroid line; the min sits
``spread`` of the line before it and below it (touching it from beneath), the max
``spread`` after it and above it (resting on it). Below/above reads from an oblique camera,
the offset along the line from a camera looking straight down.

A selected feature shows only the pairs containing it (in ``inter``, only its inter-cluster
pairs); ``minmeanmax`` aggregates contain no single feature, so there the selected
feature's individual pairs are shown instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import all_relative_covariances
from common.messages import SlamState
from common.pairs import min_mean_max, pair_size, select_pairs
from services.visualiser.glyphs import Ellipsoids, ellipsoids_from_pd
from services.visualiser.settings import ViewSettings

ROLE_PAIR, ROLE_MIN, ROLE_MEAN, ROLE_MAX = 0, 1, 2, 3
ROLE_NAMES = ("pair", "min", "mean", "max")


@dataclass(frozen=True)
class Scene:
    """Everything a renderer draws for the pairs (robot and cones come from the state)."""

    mode: str  #: the mode actually drawn ("all" when a selection overrides minmeanmax)
    lines_xy: np.ndarray  #: (L, 2, 2) floor segments, map frame, m
    line_ids: np.ndarray  #: (L, 2) feature ids (pairs) or cluster ids (minmeanmax)
    line_violation: np.ndarray  #: (L,) bool
    glyphs: Ellipsoids  #: (G) ellipsoids in the map frame
    glyph_role: np.ndarray  #: (G,) ROLE_PAIR / ROLE_MIN / ROLE_MEAN / ROLE_MAX
    glyph_ids: np.ndarray  #: (G, 2) feature ids of the pair shown (−1, −1 for a mean)
    glyph_clusters: np.ndarray  #: (G, 2) cluster ids (−1 when not clustered)
    glyph_size: np.ndarray  #: (G,) size of the glyph's P_d (√λmax), m
    glyph_violation: np.ndarray  #: (G,) bool
    cluster_ids: np.ndarray | None  #: (n,) stable cluster id per landmark
    centroids: dict[int, np.ndarray]  #: cluster id → centroid (2,), m
    selected_missing: bool  #: a feature is selected but not in the map


def _pair_keys(ids_a: np.ndarray, ids_b: np.ndarray) -> list[tuple[int, int]]:
    return list(zip(np.minimum(ids_a, ids_b).tolist(), np.maximum(ids_a, ids_b).tolist(),
                    strict=True))


def _flags(keys: list[tuple[int, int]], violating: frozenset[tuple[int, int]]) -> np.ndarray:
    if not violating:
        return np.zeros(len(keys), dtype=bool)
    return np.array([k in violating for k in keys], dtype=bool)


def build_scene(state: SlamState, settings: ViewSettings, *,
                cluster_ids: np.ndarray | None = None,
                violating_pairs: frozenset[tuple[int, int]] = frozenset()) -> Scene:
    """Lines and glyphs for ``state`` as ``settings`` asks.

    ``cluster_ids`` (stable ids per landmark) is needed by ``inter`` and ``minmeanmax``;
    ``violating_pairs`` holds (smaller id, larger id) of pairs the monitor flagged.
    """
    n = state.n
    ids = state.landmark_ids
    xy = state.landmarks
    selected_index: int | None = None
    selected_missing = False
    if settings.selected_feature is not None:
        hit = np.flatnonzero(ids == settings.selected_feature)
        if hit.size:
            selected_index = int(hit[0])
        else:
            selected_missing = True
    mode = settings.mode
    if mode == "minmeanmax" and selected_index is not None:
        mode = "all"
    if cluster_ids is None and n < 2:
        cluster_ids = np.zeros(n, dtype=np.int64) if mode != "all" else None
    centroids: dict[int, np.ndarray] = {}
    if cluster_ids is not None:
        for c in np.unique(cluster_ids).tolist():
            centroids[int(c)] = xy[cluster_ids == c].mean(axis=0)

    def glyphs_for(Pd: np.ndarray, centres: np.ndarray) -> Ellipsoids:
        return ellipsoids_from_pd(Pd, centres, glyph=settings.glyph, sigma_k=settings.sigma_k,
                                  scale=settings.scale)

    if selected_missing or n < 2:
        ii = jj = np.zeros(0, dtype=np.int64)
    else:
        ii, jj = select_pairs(n, mode=mode, cluster_ids=cluster_ids, selected_index=selected_index)
    _, _, Pd_all = all_relative_covariances(state.covariance, n) if n >= 2 else (
        None, None, np.zeros((0, 2, 2)))
    # Map (ii, jj) back to the row of Pd_all: row of (i, j) in triu order.
    rows = (ii * (2 * n - ii - 1)) // 2 + (jj - ii - 1)
    Pd = Pd_all[rows] if len(rows) else np.zeros((0, 2, 2))

    if mode != "minmeanmax":
        keys = _pair_keys(ids[ii], ids[jj])
        flags = _flags(keys, violating_pairs)
        mid = 0.5 * (xy[ii] + xy[jj])
        ell = glyphs_for(Pd, mid)
        pair_ids = np.column_stack([ids[ii], ids[jj]]).astype(np.int64).reshape(-1, 2)
        clusters = (np.column_stack([cluster_ids[ii], cluster_ids[jj]]).reshape(-1, 2)
                    if cluster_ids is not None else np.full((len(ii), 2), -1, np.int64))
        return Scene(mode=mode, lines_xy=np.stack([xy[ii], xy[jj]], axis=1).reshape(-1, 2, 2),
                     line_ids=pair_ids, line_violation=flags, glyphs=ell,
                     glyph_role=np.full(len(ii), ROLE_PAIR, np.int64), glyph_ids=pair_ids,
                     glyph_clusters=clusters, glyph_size=pair_size(Pd), glyph_violation=flags,
                     cluster_ids=cluster_ids, centroids=centroids,
                     selected_missing=selected_missing)

    assert cluster_ids is not None  # select_pairs has already insisted
    stats = min_mean_max(ii, jj, Pd, cluster_ids)
    c = len(stats.clusters)
    keys = _pair_keys(ids[ii], ids[jj])
    pair_flags = _flags(keys, violating_pairs)
    group_flag = np.zeros(c, dtype=bool)
    if pair_flags.any():
        lo = np.minimum(cluster_ids[ii], cluster_ids[jj])
        hi = np.maximum(cluster_ids[ii], cluster_ids[jj])
        bad = {(int(a), int(b)) for a, b in zip(lo[pair_flags], hi[pair_flags], strict=True)}
        group_flag = np.array([(int(a), int(b)) in bad for a, b in stats.clusters], dtype=bool)
    start = np.array([centroids[int(a)] for a in stats.clusters[:, 0]]).reshape(-1, 2)
    end = np.array([centroids[int(b)] for b in stats.clusters[:, 1]]).reshape(-1, 2)
    Pd3 = np.concatenate([Pd[stats.min_pair], stats.mean_Pd, Pd[stats.max_pair]])
    ell0 = glyphs_for(Pd3, np.zeros((3 * c, 2)))
    h_min, h_mean, h_max = ell0.h[:c], ell0.h[c:2 * c], ell0.h[2 * c:]
    spread = settings.minmeanmax_spread
    t = np.concatenate([np.full(c, 0.5 - spread), np.full(c, 0.5), np.full(c, 0.5 + spread)])
    z = np.concatenate([-(h_mean + h_min), np.zeros(c), h_mean + h_max])
    seg_start, seg_end = np.tile(start, (3, 1)), np.tile(end, (3, 1))
    centres = np.column_stack([seg_start + t[:, None] * (seg_end - seg_start), z])
    ell = Ellipsoids(centres=centres, a=ell0.a, b=ell0.b, h=ell0.h, yaw=ell0.yaw)
    role = np.concatenate([np.full(c, ROLE_MIN), np.full(c, ROLE_MEAN), np.full(c, ROLE_MAX)])
    min_ids = np.column_stack([ids[ii[stats.min_pair]], ids[jj[stats.min_pair]]])
    max_ids = np.column_stack([ids[ii[stats.max_pair]], ids[jj[stats.max_pair]]])
    glyph_ids = np.concatenate([min_ids, np.full((c, 2), -1), max_ids]).astype(np.int64)
    glyph_flags = np.concatenate([pair_flags[stats.min_pair], group_flag,
                                  pair_flags[stats.max_pair]])
    return Scene(mode=mode, lines_xy=np.stack([start, end], axis=1).reshape(-1, 2, 2),
                 line_ids=stats.clusters, line_violation=group_flag, glyphs=ell,
                 glyph_role=role.astype(np.int64), glyph_ids=glyph_ids.reshape(-1, 2),
                 glyph_clusters=np.tile(stats.clusters, (3, 1)).reshape(-1, 2),
                 glyph_size=pair_size(Pd3), glyph_violation=glyph_flags,
                 cluster_ids=cluster_ids, centroids=centroids,
                 selected_missing=selected_missing)
