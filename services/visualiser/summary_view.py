"""A picture from a robot's summary instead of its full state (``--source summary``, pure).

A viewer behind a slow link pulls a :class:`~slamlens.common.messages.StateSummary` (
docs/remote_viewers.md): the map's blocks and the clustered min / mean / max of the
relative covariances, never the whole matrix. :func:`summarised_state` makes of it a
:class:`SummarisedState` — a ``SlamState`` whose covariance holds only what arrived (the
robot's 3×3 block and each feature's 2×2 block; every cross term zero), carrying the
summary — so the rest of the viewer (path, cones, legend, map bounds, health) works
unchanged; :func:`summary_scene` is its picture: the robot's min / mean / max glyphs
between the group centroids whatever mode the view asks for, or — when a view selects a
feature or a cluster, the viewer asks for ``what=pairs`` of it — that selection's pairs
at full detail, each from its own P_d. Relative covariances are never computed from the
block-diagonal matrix: its cross terms are absent, not zero (``Renderer.draw`` takes the
scene from here, and the plots of individual pairs are not fed by summarised states).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slamlens.common.messages import SlamState, StateSummary
from slamlens.common.pairs import pair_size
from slamlens.services.visualiser.glyphs import ellipsoids_from_pd
from slamlens.services.visualiser.scene import ROLE_PAIR, Scene, group_scene
from slamlens.services.visualiser.settings import ViewSettings


@dataclass(frozen=True, eq=False)
class SummarisedState(SlamState):
    """A state rebuilt from a summary: blocks only (module docstring)."""

    summary: StateSummary | None = field(default=None, metadata={"kind": "local"})


def summarised_state(summary: StateSummary) -> SummarisedState:
    """The :class:`SummarisedState` of ``summary`` (block-diagonal covariance)."""
    n = summary.n
    N = 3 + 2 * n
    P = np.zeros((N, N))
    P[:3, :3] = summary.pose_covariance
    lm = 3 + 2 * np.arange(n)
    blocks = summary.landmark_covariances.astype(float)
    P[lm, lm] = blocks[:, 0, 0]
    P[lm, lm + 1] = blocks[:, 0, 1]
    P[lm + 1, lm] = blocks[:, 1, 0]
    P[lm + 1, lm + 1] = blocks[:, 1, 1]
    P.setflags(write=False)  # frozen already: the message keeps it without a 32 MB copy
    return SummarisedState(
        robot=summary.robot, seq=summary.seq, stamp=summary.stamp, step=summary.step,
        pose=summary.pose, landmark_ids=summary.landmark_ids,
        landmarks=summary.landmarks.astype(float), covariance=P, epoch=summary.epoch,
        input_stamp=summary.input_stamp, summary=summary)


def decode_summary_state(payload: bytes) -> SummarisedState:
    """A summary's payload as the state the viewer draws (MessageError if malformed)."""
    return summarised_state(StateSummary.from_bytes(payload))


def summary_of(state: SlamState) -> StateSummary | None:
    """The summary a state was rebuilt from, or None for a full state."""
    return state.summary if isinstance(state, SummarisedState) else None


def summary_scene(state: SummarisedState, settings: ViewSettings,
                  violating_pairs: frozenset[tuple[int, int]] = frozenset()) -> Scene:
    """The min / mean / max picture the robot summarised (module docstring)."""
    s = state.summary
    assert s is not None
    n = state.n
    if s.what == "pairs" and s.pairs is not None and s.pairs_Pd is not None:
        return _pairs_scene(state, s, settings, violating_pairs)
    if s.groups is None or s.group_pairs is None or n < 2:
        empty = np.zeros((0, 2), np.int64)
        return group_scene(state, settings, np.zeros(n, np.int64), groups=empty,
                           min_ij=empty, max_ij=empty, Pd_min=np.zeros((0, 2, 2)),
                           mean_Pd=np.zeros((0, 2, 2)), Pd_max=np.zeros((0, 2, 2)),
                           note="summary: the map's blocks only")
    assert s.min_pair is not None and s.max_pair is not None
    assert s.min_Pd is not None and s.mean_Pd is not None and s.max_Pd is not None
    ids = state.landmark_ids
    groups = s.groups

    def flagged(pairs: np.ndarray) -> np.ndarray:
        a, b = ids[pairs[:, 0]], ids[pairs[:, 1]]
        return np.array([(int(min(x, y)), int(max(x, y))) in violating_pairs
                         for x, y in zip(a, b, strict=True)], dtype=bool)

    bad = set()
    index = {int(v): k for k, v in enumerate(ids.tolist())}
    for a, b in violating_pairs:
        i, j = index.get(a), index.get(b)
        if i is not None and j is not None and groups[i] != groups[j]:
            bad.add((int(min(groups[i], groups[j])), int(max(groups[i], groups[j]))))
    group_flag = np.array([(int(a), int(b)) in bad for a, b in s.group_pairs], dtype=bool)
    where = (f"{len(s.group_pairs)} pairs of map tiles of {s.tile_m:g} m"
             if s.tile_m is not None else f"its {len(np.unique(groups))} clusters")
    note = f"summary stream: min/mean/max per pair of {where}"
    if settings.selected_feature is not None or settings.selected_cluster is not None:
        note += " (the selection's pairs are asked for: they come with the next answer)"
    elif settings.mode != "minmeanmax":
        note += " (all pairs need the full state: --source state)"
    return group_scene(state, settings, groups, groups=s.group_pairs, min_ij=s.min_pair,
                       max_ij=s.max_pair, Pd_min=s.min_Pd.astype(float),
                       mean_Pd=s.mean_Pd.astype(float), Pd_max=s.max_Pd.astype(float),
                       flags=(flagged(s.min_pair), group_flag, flagged(s.max_pair)),
                       note=note, tile_m=s.tile_m)


def _pairs_scene(state: SummarisedState, s: StateSummary, settings: ViewSettings,
                 violating_pairs: frozenset[tuple[int, int]]) -> Scene:
    """A ``what=pairs`` summary: the selected feature's or cluster's pairs at full detail,
    each glyph from its own P_d as the robot computed it (float32 on the wire)."""
    assert s.pairs is not None and s.pairs_Pd is not None
    ids, xy = state.landmark_ids, state.landmarks
    ii, jj = s.pairs[:, 0], s.pairs[:, 1]
    Pd = s.pairs_Pd.astype(float).reshape(-1, 2, 2)
    pair_ids = np.column_stack([ids[ii], ids[jj]]).astype(np.int64).reshape(-1, 2)
    flags = np.array([(int(min(a, b)), int(max(a, b))) in violating_pairs
                      for a, b in pair_ids.tolist()], dtype=bool)
    groups = s.groups
    clusters = (np.column_stack([groups[ii], groups[jj]]).reshape(-1, 2)
                if groups is not None else np.full((len(ii), 2), -1, np.int64))
    what = (f"feature {s.selected_feature}" if s.selected_feature is not None
            else f"cluster {s.selected_cluster}")
    total = s.pairs_total if s.pairs_total is not None else len(ii)
    note = (f"summary stream: all {total} pairs of {what}" if total == len(ii) else
            f"summary stream: the {len(ii)} largest of the {total} pairs of {what}")
    if (settings.selected_feature, settings.selected_cluster) != (s.selected_feature,
                                                                  s.selected_cluster):
        note += " (another view's selection: one selection is pulled at a time)"
    centroids: dict[int, np.ndarray] = {}
    if groups is not None:
        for c in np.unique(groups).tolist():
            centroids[int(c)] = xy[groups == c].mean(axis=0)
    return Scene(mode="all", lines_xy=np.stack([xy[ii], xy[jj]], axis=1).reshape(-1, 2, 2),
                 line_ids=pair_ids, line_violation=flags,
                 glyphs=ellipsoids_from_pd(Pd, 0.5 * (xy[ii] + xy[jj]),
                                           glyph=settings.glyph, sigma_k=settings.sigma_k,
                                           scale=settings.scale),
                 glyph_role=np.full(len(ii), ROLE_PAIR, np.int64), glyph_ids=pair_ids,
                 glyph_clusters=clusters, glyph_size=pair_size(Pd), glyph_violation=flags,
                 cluster_ids=groups, centroids=centroids, selected_missing=False,
                 overview=note)
