"""What to draw for one state and one ``ViewSettings``: pairs, lines and glyphs (pure).

Modes (docs/visualisation.md, paper §3.2):

* ``all``: every pair i < j of features.
* ``inter``: only pairs whose features lie in different clusters.
* ``minmeanmax``: per pair of clusters, a line between the cluster centroids and three
  glyphs: the smallest P_d, the element-wise mean P_d and the largest P_d over the
  inter-cluster pairs of that cluster pair.

"Smallest" and "largest" are by ``slamlens.common.geometry.pd_size_m``, √λmax of P_d (the 1-σ major
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

from slamlens.common import overview
from slamlens.common.errors import RenderError
from slamlens.common.geometry import all_relative_covariances
from slamlens.common.messages import SlamState
from slamlens.common.pairs import min_mean_max, pair_size, select_pairs
from slamlens.services.visualiser.glyphs import Ellipsoids, ellipsoids_from_pd
from slamlens.services.visualiser.settings import ViewSettings

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
    #: above the glyph budget: what the picture shows instead, for the legend and the page
    overview: str = ""
    tile_m: float | None = None  #: the overview's groups are map tiles of this side, m


def _pair_keys(ids_a: np.ndarray, ids_b: np.ndarray) -> list[tuple[int, int]]:
    return list(zip(np.minimum(ids_a, ids_b).tolist(), np.maximum(ids_a, ids_b).tolist(),
                    strict=True))


def _flags(keys: list[tuple[int, int]], violating: frozenset[tuple[int, int]]) -> np.ndarray:
    if not violating:
        return np.zeros(len(keys), dtype=bool)
    return np.array([k in violating for k in keys], dtype=bool)


@dataclass(frozen=True)
class Overview:
    """A picture above its glyph budget: min / mean / max over these groups instead."""

    groups: np.ndarray  #: (n,) group id per landmark (stable cluster ids, or tile ids)
    note: str  #: what is shown and why, for the legend and the page
    tile_m: float | None = None  #: tiles of this side (None: the view's clusters)


def plan_overview(state: SlamState, settings: ViewSettings,
                  cluster_ids: np.ndarray | None) -> Overview | None:
    """The glyph budget rule (``slamlens.common.overview``): None when the mode's
    pairs fit ``settings.glyph_budget`` (or a feature or a cluster is selected, or the
    budget is 0 = off); else the groups of the min/mean/max overview and the note.
    ``cluster_ids`` (stable, the view's clustering) must be given for every mode here."""
    budget, n = settings.glyph_budget, state.n
    if budget <= 0 or n < 2 or cluster_ids is None or (
            settings.selected_feature is not None or settings.selected_cluster is not None):
        return None
    k = len(np.unique(cluster_ids))
    if settings.mode == "minmeanmax":
        wanted = overview.overview_glyphs(k)
    else:
        wanted = overview.pair_count(n, cluster_ids, inter=settings.mode == "inter")
    if wanted <= budget:
        return None
    what = {"all": "pairs", "inter": "inter-cluster pairs",
            "minmeanmax": "min/mean/max glyphs"}[settings.mode]
    head = f"{wanted:,} {what} > budget {budget:,}: ".replace(",", " ")
    tail = "; select a feature or a cluster for all its pairs"
    if k <= overview.max_groups(budget):
        return Overview(cluster_ids, head + f"min/mean/max per pair of its {k} clusters"
                        + tail)
    tiles, side = overview.tile_groups(state.landmarks, budget)
    count = len(np.unique(tiles))
    return Overview(tiles, head + f"min/mean/max per pair of {count} map tiles of "
                                  f"{side:g} m" + tail, tile_m=side)


def build_scene(state: SlamState, settings: ViewSettings, *,
                cluster_ids: np.ndarray | None = None,
                violating_pairs: frozenset[tuple[int, int]] = frozenset(),
                plan: Overview | None = None) -> Scene:
    """Lines and glyphs for ``state`` as ``settings`` asks.

    ``cluster_ids`` (stable ids per landmark) is needed by ``inter`` and ``minmeanmax``
    and by a selected cluster; ``violating_pairs`` holds (smaller id, larger id) of pairs
    the monitor flagged; ``plan`` (:func:`plan_overview`) replaces the mode's pairs by the
    min/mean/max overview over its groups (above the glyph budget).
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
    if plan is not None:
        return _min_mean_max_scene(state, settings, plan.groups, violating_pairs,
                                   selected_missing=False, fast=True, plan=plan)
    mode = settings.mode
    if mode == "minmeanmax" and (selected_index is not None
                                 or settings.selected_cluster is not None):
        mode = "all"
    if cluster_ids is None and n < 2:
        cluster_ids = np.zeros(n, dtype=np.int64) if mode != "all" else None
    if mode == "minmeanmax":
        if cluster_ids is None:
            raise RenderError("mode 'minmeanmax' needs cluster ids")
        return _min_mean_max_scene(state, settings, cluster_ids, violating_pairs,
                                   selected_missing=selected_missing,
                                   fast=n * (n - 1) // 2 > overview.FAST_PAIRS)
    centroids = _centroids(xy, cluster_ids)

    def glyphs_for(Pd: np.ndarray, centres: np.ndarray) -> Ellipsoids:
        return ellipsoids_from_pd(Pd, centres, glyph=settings.glyph, sigma_k=settings.sigma_k,
                                  scale=settings.scale)

    note = ""
    if selected_missing or n < 2:
        ii = jj = np.zeros(0, dtype=np.int64)
    elif settings.selected_cluster is not None:
        ii, jj, note = _cluster_pairs(state, settings, cluster_ids)
    else:
        ii, jj = select_pairs(n, mode=mode, cluster_ids=cluster_ids,
                              selected_index=selected_index)
    if n * (n - 1) // 2 > overview.FAST_PAIRS:  # only the pairs drawn, not all of them
        Pd = overview.pair_relative_covariances(state.covariance, ii, jj)
    else:
        _, _, Pd_all = all_relative_covariances(state.covariance, n) if n >= 2 else (
            None, None, np.zeros((0, 2, 2)))
        # Map (ii, jj) back to the row of Pd_all: row of (i, j) in triu order.
        rows = (ii * (2 * n - ii - 1)) // 2 + (jj - ii - 1)
        Pd = Pd_all[rows] if len(rows) else np.zeros((0, 2, 2))
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
                 selected_missing=selected_missing, overview=note)


def _centroids(xy: np.ndarray, cluster_ids: np.ndarray | None) -> dict[int, np.ndarray]:
    centroids: dict[int, np.ndarray] = {}
    if cluster_ids is not None:
        for c in np.unique(cluster_ids).tolist():
            centroids[int(c)] = xy[cluster_ids == c].mean(axis=0)
    return centroids


def _cluster_pairs(state: SlamState, settings: ViewSettings, cluster_ids: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, str]:
    """The pairs inside the selected cluster (all of them, up to ``SELECTED_CAP`` times the
    budget: then its largest), and a note when it was capped or is not in the map."""
    empty = np.zeros(0, dtype=np.int64)
    if cluster_ids is None:
        raise RenderError("a selected cluster needs cluster ids")
    members = np.flatnonzero(cluster_ids == settings.selected_cluster)
    if len(members) < 2:
        return empty, empty, (f"cluster {settings.selected_cluster} is not in the map"
                              if not len(members) else "")
    a, b = np.triu_indices(len(members), k=1)
    ii, jj = members[a], members[b]
    cap = overview.SELECTED_CAP * settings.glyph_budget
    if settings.glyph_budget > 0 and len(ii) > cap:
        sizes = pair_size(overview.pair_relative_covariances(state.covariance, ii, jj))
        keep = np.sort(np.argsort(-sizes, kind="stable")[:cap])
        note = (f"cluster {settings.selected_cluster}: its {cap} largest of {len(ii)} pairs "
                f"(at most {overview.SELECTED_CAP} x the glyph budget)")
        return ii[keep], jj[keep], note
    return ii, jj, ""


def _min_mean_max_scene(state: SlamState, settings: ViewSettings, cluster_ids: np.ndarray,
                        violating_pairs: frozenset[tuple[int, int]], *,
                        selected_missing: bool, fast: bool,
                        plan: Overview | None = None) -> Scene:
    """Per pair of groups (clusters, or the overview's tiles) a line between their
    centroids and the min / mean / max glyphs (module docstring)."""
    n = state.n
    ids, P = state.landmark_ids, state.covariance
    if fast:
        # whole-matrix kernel: no per-pair Python work for n(n−1)/2 pairs
        gp = overview.group_min_mean_max(P, cluster_ids)
        groups, min_ij, max_ij, mean_Pd = gp.groups, gp.min_pair, gp.max_pair, gp.mean_Pd
        bad = set()
        index = {int(v): k for k, v in enumerate(ids.tolist())}
        for a, b in violating_pairs:
            i, j = index.get(a), index.get(b)
            if i is not None and j is not None and cluster_ids[i] != cluster_ids[j]:
                bad.add((int(min(cluster_ids[i], cluster_ids[j])),
                         int(max(cluster_ids[i], cluster_ids[j]))))
        group_flag = np.array([(int(a), int(b)) in bad for a, b in groups], dtype=bool)
        min_flag = np.array(_flags(_pair_keys(ids[min_ij[:, 0]], ids[min_ij[:, 1]]),
                                   violating_pairs), dtype=bool).reshape(-1)
        max_flag = np.array(_flags(_pair_keys(ids[max_ij[:, 0]], ids[max_ij[:, 1]]),
                                   violating_pairs), dtype=bool).reshape(-1)
        Pd_min = overview.pair_relative_covariances(P, min_ij[:, 0], min_ij[:, 1])
        Pd_max = overview.pair_relative_covariances(P, max_ij[:, 0], max_ij[:, 1])
    else:
        ii, jj = (np.zeros(0, dtype=np.int64),) * 2
        if not selected_missing and n >= 2:
            ii, jj = select_pairs(n, mode="minmeanmax", cluster_ids=cluster_ids)
        _, _, Pd_all = all_relative_covariances(P, n) if n >= 2 else (
            None, None, np.zeros((0, 2, 2)))
        rows = (ii * (2 * n - ii - 1)) // 2 + (jj - ii - 1)
        Pd = Pd_all[rows] if len(rows) else np.zeros((0, 2, 2))
        stats = min_mean_max(ii, jj, Pd, cluster_ids)
        groups, mean_Pd = stats.clusters, stats.mean_Pd
        min_ij = np.column_stack([ii[stats.min_pair], jj[stats.min_pair]]).reshape(-1, 2)
        max_ij = np.column_stack([ii[stats.max_pair], jj[stats.max_pair]]).reshape(-1, 2)
        pair_flags = _flags(_pair_keys(ids[ii], ids[jj]), violating_pairs)
        group_flag = np.zeros(len(groups), dtype=bool)
        if pair_flags.any():
            lo = np.minimum(cluster_ids[ii], cluster_ids[jj])
            hi = np.maximum(cluster_ids[ii], cluster_ids[jj])
            bad = {(int(a), int(b)) for a, b in zip(lo[pair_flags], hi[pair_flags],
                                                     strict=True)}
            group_flag = np.array([(int(a), int(b)) in bad for a, b in groups], dtype=bool)
        min_flag, max_flag = pair_flags[stats.min_pair], pair_flags[stats.max_pair]
        Pd_min, Pd_max = Pd[stats.min_pair], Pd[stats.max_pair]
    return group_scene(state, settings, cluster_ids, groups=groups, min_ij=min_ij,
                       max_ij=max_ij, Pd_min=Pd_min, mean_Pd=mean_Pd, Pd_max=Pd_max,
                       flags=(min_flag, group_flag, max_flag),
                       selected_missing=selected_missing,
                       note="" if plan is None else plan.note,
                       tile_m=None if plan is None else plan.tile_m)


def group_scene(state: SlamState, settings: ViewSettings, cluster_ids: np.ndarray, *,
                groups: np.ndarray, min_ij: np.ndarray, max_ij: np.ndarray,
                Pd_min: np.ndarray, mean_Pd: np.ndarray, Pd_max: np.ndarray,
                flags: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                selected_missing: bool = False, note: str = "",
                tile_m: float | None = None) -> Scene:
    """The min / mean / max picture of given per-group-pair statistics (module docstring):
    ``groups`` (c, 2) group ids, ``min_ij`` / ``max_ij`` (c, 2) landmark indices of the
    smallest / largest pair and their ``Pd_min`` / ``Pd_max``, ``mean_Pd`` (c, 2, 2);
    ``flags`` the (min, group, max) violation flags (none: all clear). Also what a
    viewer draws from a robot's summary (``summary_view``)."""
    ids, xy = state.landmark_ids, state.landmarks
    centroids = _centroids(xy, cluster_ids)
    c = len(groups)
    if flags is None:
        flags = (np.zeros(c, bool),) * 3
    min_flag, group_flag, max_flag = flags
    start = np.array([centroids[int(a)] for a in groups[:, 0]]).reshape(-1, 2)
    end = np.array([centroids[int(b)] for b in groups[:, 1]]).reshape(-1, 2)
    Pd3 = np.concatenate([Pd_min, mean_Pd, Pd_max])
    ell0 = ellipsoids_from_pd(Pd3, np.zeros((3 * c, 2)), glyph=settings.glyph,
                              sigma_k=settings.sigma_k, scale=settings.scale)
    h_min, h_mean, h_max = ell0.h[:c], ell0.h[c:2 * c], ell0.h[2 * c:]
    spread = settings.minmeanmax_spread
    t = np.concatenate([np.full(c, 0.5 - spread), np.full(c, 0.5), np.full(c, 0.5 + spread)])
    z = np.concatenate([-(h_mean + h_min), np.zeros(c), h_mean + h_max])
    seg_start, seg_end = np.tile(start, (3, 1)), np.tile(end, (3, 1))
    centres = np.column_stack([seg_start + t[:, None] * (seg_end - seg_start), z])
    ell = Ellipsoids(centres=centres, a=ell0.a, b=ell0.b, h=ell0.h, yaw=ell0.yaw)
    role = np.concatenate([np.full(c, ROLE_MIN), np.full(c, ROLE_MEAN), np.full(c, ROLE_MAX)])
    min_ids = np.column_stack([ids[min_ij[:, 0]], ids[min_ij[:, 1]]]).reshape(-1, 2)
    max_ids = np.column_stack([ids[max_ij[:, 0]], ids[max_ij[:, 1]]]).reshape(-1, 2)
    glyph_ids = np.concatenate([min_ids, np.full((c, 2), -1), max_ids]).astype(np.int64)
    glyph_flags = np.concatenate([min_flag, group_flag, max_flag])
    return Scene(mode="minmeanmax", lines_xy=np.stack([start, end], axis=1).reshape(-1, 2, 2),
                 line_ids=groups, line_violation=group_flag, glyphs=ell,
                 glyph_role=role.astype(np.int64), glyph_ids=glyph_ids.reshape(-1, 2),
                 glyph_clusters=np.tile(groups, (3, 1)).reshape(-1, 2),
                 glyph_size=pair_size(Pd3), glyph_violation=glyph_flags,
                 cluster_ids=cluster_ids, centroids=centroids,
                 selected_missing=selected_missing, overview=note, tile_m=tile_m)
