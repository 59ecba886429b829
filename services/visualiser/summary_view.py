"""A picture from a robot's summary instead of its full state (``--source summary``, pure).

A viewer behind a slow link pulls a :class:`~common.messages.StateSummary` (issue 13,
docs/remote_viewers.md): the map's blocks and the clustered min / mean / max of the
relative covariances, never the whole matrix. :func:`summarised_state` makes of it a
:class:`SummarisedState` — a ``SlamState`` whose covariance holds only what arrived (the
robot's 3×3 block and each feature's 2×2 block; every cross term zero), carrying the
summary — so the rest of the viewer (path, cones, legend, map bounds, health) works
unchanged; :func:`summary_scene` is its picture: the robot's min / mean / max glyphs
between the group centroids, whatever mode the view asks for (a summary holds nothing
else). Relative covariances are never computed from the block-diagonal matrix: its cross
terms are absent, not zero (``Renderer.draw`` takes the scene from here, and the plots of
individual pairs are not fed by summarised states).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.messages import SlamState, StateSummary
from services.visualiser.scene import Scene, group_scene
from services.visualiser.settings import ViewSettings


@dataclass(frozen=True, eq=False)
class SummarisedState(SlamState):
    """A state rebuilt from a summary: blocks only (module docstring)."""

    summary: StateSummary | None = field(default=None, metadata={"kind": "summary"})


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
    if settings.mode != "minmeanmax" or settings.selected_feature is not None \
            or settings.selected_cluster is not None:
        note += " (all pairs and selections need the full state: --source state)"
    return group_scene(state, settings, groups, groups=s.group_pairs, min_ij=s.min_pair,
                       max_ij=s.max_pair, Pd_min=s.min_Pd.astype(float),
                       mean_Pd=s.mean_Pd.astype(float), Pd_max=s.max_Pd.astype(float),
                       flags=(flagged(s.min_pair), group_flag, flagged(s.max_pair)),
                       note=note, tile_m=s.tile_m)
