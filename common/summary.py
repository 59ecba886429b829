"""What a remote viewer draws of a state, made from the full state (pure).

A viewer on a slow link asks the robot's ``summary`` queryable (docs/remote_viewers.md) for
what it will draw instead of receiving the whole covariance (32 MB at n = 1000):

* ``blocks``: the robot pose and its 3×3 covariance, every feature's mean and 2×2 marginal
  covariance — what the cones and the robot are drawn from;
* ``clusters``: the blocks, and per pair of groups of features the smallest, the mean and
  the largest relative covariance P_d = P_ii + P_jj − P_ij − P_ji over the pairs between
  them (the viewer's clustered min/mean/max picture). The groups are the single-linkage
  clusters at ``threshold`` (or ``count``), with ids kept stable from state to state by a
  :class:`~slamlens.common.clusters.ClusterTracker` per clustering; with a glyph ``budget`` the
  viewer's rule applies (:mod:`slamlens.common.overview`): too many clusters for the budget, and
  the groups become square map tiles;
* ``pairs``: the blocks, and the P_d of every pair inside one cluster (``cluster=K``, a
  stable id of a previous ``clusters`` answer with the same clustering) or of one feature
  (``feature=ID``) — a selection at full detail.

:func:`parse_query` turns a selector's parameters into a :class:`SummaryQuery` or raises
:class:`SummaryQueryError` with a sentence; :class:`Summariser` makes the summaries and
keeps the last few (per state and query), so viewers that ask the same share the work.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from slamlens.common import overview
from slamlens.common.clusters import ClusterTracker, cluster_labels
from slamlens.common.errors import SlamlensError
from slamlens.common.geometry import pd_size_m
from slamlens.common.messages import SlamState, StateSummary

#: the parameters a summary query may carry, and what each means (for the error text)
PARAMETERS = {
    "what": "blocks | clusters | pairs",
    "threshold": "cluster cut, m (> 0)",
    "count": "clusters wanted (0 = cut at threshold)",
    "budget": "glyph budget (0 = off)",
    "cluster": "stable cluster id (pairs)",
    "feature": "feature id (pairs)",
    "after": "seq already drawn: wait for a newer state",
    "epoch": "epoch of that seq",
}
DEFAULT_THRESHOLD_M = 0.6  #: as the viewer's ``cluster_threshold_m``
MAX_TRACKERS = 8  #: clusterings whose stable ids are kept (several viewers, settings)


class SummaryQueryError(SlamlensError):
    """A summary query the robot cannot answer (its text is the error reply)."""


@dataclass(frozen=True)
class SummaryQuery:
    """One summary request (module docstring); hashable: the cache key with the state."""

    what: str = "clusters"
    threshold_m: float = DEFAULT_THRESHOLD_M
    count: int = 0
    budget: int = 0
    cluster: int | None = None
    feature: int | None = None
    after: int | None = None  #: not part of the answer: the long poll's "newer than"
    epoch: int | None = None

    @property
    def clustering(self) -> tuple[float, int]:
        return (self.threshold_m, self.count)

    def answer_key(self) -> SummaryQuery:
        """The query without what only decides *when* to answer (the cache key)."""
        return replace(self, after=None, epoch=None)

    def newer(self, epoch: int, seq: int) -> bool:
        """Whether a state (epoch, seq) is one this query waits for."""
        if self.after is None:
            return True
        return (self.epoch is not None and epoch != self.epoch) or seq > self.after

    def selector(self) -> str:
        """The parameters as a Zenoh selector's (``;``-separated), for a client."""
        parts = [f"what={self.what}"]
        if self.what != "blocks":
            parts += [f"threshold={self.threshold_m:g}", f"count={self.count}"]
        if self.budget:
            parts.append(f"budget={self.budget}")
        if self.cluster is not None:
            parts.append(f"cluster={self.cluster}")
        if self.feature is not None:
            parts.append(f"feature={self.feature}")
        if self.after is not None:
            parts.append(f"after={self.after}")
        if self.epoch is not None:
            parts.append(f"epoch={self.epoch}")
        return ";".join(parts)


def _number(key: str, text: str, kind: type, *, low: float | None = None) -> float | int:
    try:
        value = kind(text)
    except ValueError:
        raise SummaryQueryError(f"summary query: {key}={text!r} is not "
                                f"{'an integer' if kind is int else 'a number'}") from None
    if kind is float and not math.isfinite(value):
        raise SummaryQueryError(f"summary query: {key}={text!r} is not finite")
    if low is not None and value < low:
        raise SummaryQueryError(f"summary query: {key}={text!r} must be ≥ {low:g}")
    return value


def parse_query(parameters: str) -> SummaryQuery:
    """A :class:`SummaryQuery` from a selector's parameters (``what=clusters;threshold=0.6``;
    ``&`` is accepted for ``;``); :class:`SummaryQueryError` names what is wrong."""
    seen: dict[str, str] = {}
    for part in parameters.replace("&", ";").split(";"):
        if not part.strip():
            continue
        key, eq, value = part.partition("=")
        key = key.strip()
        if key not in PARAMETERS:
            known = ", ".join(f"{k} ({v})" for k, v in PARAMETERS.items())
            raise SummaryQueryError(f"summary query: unknown parameter {key!r}; known: {known}")
        if not eq or not value.strip():
            raise SummaryQueryError(f"summary query: {key} needs a value ({PARAMETERS[key]})")
        if key in seen:
            raise SummaryQueryError(f"summary query: {key} given twice")
        seen[key] = value.strip()
    q = SummaryQuery()
    what = seen.get("what")
    if what is None and ("cluster" in seen or "feature" in seen):
        what = "pairs"
    if what is not None:
        if what not in ("blocks", "clusters", "pairs"):
            raise SummaryQueryError(f"summary query: what={what!r}; choose blocks, clusters "
                                    "or pairs")
        q = replace(q, what=what)
    if "threshold" in seen:
        t = float(_number("threshold", seen["threshold"], float))
        if t <= 0:
            raise SummaryQueryError(f"summary query: threshold={seen['threshold']!r} must be "
                                    "> 0 (m)")
        q = replace(q, threshold_m=t)
    ints: dict[str, Any] = {
        k: int(_number(k, seen[k], int, low=None if k == "feature" else 0))
        for k in ("count", "budget", "cluster", "feature", "after", "epoch") if k in seen}
    q = replace(q, **ints)
    if q.what == "pairs" and (q.cluster is None) == (q.feature is None):
        raise SummaryQueryError("summary query: what=pairs needs exactly one of cluster=K "
                                "or feature=ID")
    if q.what != "pairs" and (q.cluster is not None or q.feature is not None):
        raise SummaryQueryError(f"summary query: cluster / feature go with what=pairs, not "
                                f"what={q.what}")
    if q.epoch is not None and q.after is None:
        raise SummaryQueryError("summary query: epoch goes with after=SEQ")
    return q


def landmark_blocks(P: np.ndarray, n: int) -> np.ndarray:
    """The 2×2 marginal covariance of every landmark, (n, 2, 2), from P (3+2n)²."""
    lm = 3 + 2 * np.arange(n)
    out = np.empty((n, 2, 2))
    out[:, 0, 0] = P[lm, lm]
    out[:, 0, 1] = P[lm, lm + 1]
    out[:, 1, 0] = P[lm + 1, lm]
    out[:, 1, 1] = P[lm + 1, lm + 1]
    return out


class Summariser:
    """Makes summaries of states and keeps the last ``cache`` of them.

    Stable cluster ids need the states in order: :meth:`summary` is meant for the newest
    state each time (one worker calls it); a new epoch forgets the clusterings.
    """

    def __init__(self, *, cache: int = 16, max_group_pairs: int = 20_000,
                 max_pairs: int = 50_000) -> None:
        self.max_group_pairs = max_group_pairs  #: a larger clusters answer is refused
        self.max_pairs = max_pairs  #: a larger pairs answer is refused
        self._cache: OrderedDict[tuple[int, int, SummaryQuery], bytes] = OrderedDict()
        self._size = cache
        self._trackers: OrderedDict[tuple[float, int], tuple[int, ClusterTracker,
                                                             np.ndarray]] = OrderedDict()
        self._epoch: int | None = None
        self._lock = threading.Lock()
        self.made = 0  #: summaries computed
        self.shared = 0  #: answers served from the cache

    def summary(self, state: SlamState, query: SummaryQuery, *,
                state_bytes: int = 0) -> bytes:
        """The encoded :class:`StateSummary` of ``state`` for ``query`` (cached)."""
        key = (state.epoch, state.seq, query.answer_key())
        with self._lock:
            if self._epoch != state.epoch:
                self._epoch = state.epoch
                self._trackers.clear()
                self._cache.clear()
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                self.shared += 1
                return hit
            t0 = time.perf_counter()
            message = self._make(state, query.answer_key(), state_bytes)
            message = replace(message, compute_s=time.perf_counter() - t0)
            payload = message.to_bytes()
            self._cache[key] = payload
            while len(self._cache) > self._size:
                self._cache.popitem(last=False)
            self.made += 1
            return payload

    def make(self, state: SlamState, query: SummaryQuery) -> StateSummary:
        """The summary itself (not cached; it does advance the stable cluster ids)."""
        with self._lock:
            return self._make(state, query.answer_key(), 0)

    # -- the parts ---------------------------------------------------------------------
    def _clusters(self, state: SlamState, clustering: tuple[float, int]) -> np.ndarray:
        """Stable cluster id per landmark (one tracker per clustering; the same state
        asked twice gets the same ids)."""
        held = self._trackers.get(clustering)
        if held is not None and held[0] == state.seq and len(held[2]) == state.n:
            self._trackers.move_to_end(clustering)
            return held[2]
        tracker = held[1] if held is not None else ClusterTracker()
        labels = cluster_labels(state.landmarks, threshold_m=clustering[0],
                                count=clustering[1])
        stable = tracker.update(state.landmark_ids, labels)
        self._trackers[clustering] = (state.seq, tracker, stable)
        self._trackers.move_to_end(clustering)
        while len(self._trackers) > MAX_TRACKERS:
            self._trackers.popitem(last=False)
        return stable

    def _make(self, state: SlamState, q: SummaryQuery, state_bytes: int) -> StateSummary:
        n, P = state.n, state.covariance
        base = StateSummary(
            robot=state.robot, seq=state.seq, stamp=state.stamp, step=state.step,
            pose=state.pose, pose_covariance=P[:3, :3], landmark_ids=state.landmark_ids,
            landmarks=state.landmarks, landmark_covariances=landmark_blocks(P, n),
            epoch=state.epoch, input_stamp=state.input_stamp, what="blocks",
            state_bytes=state_bytes)
        if q.what == "blocks":
            return base
        clusters = self._clusters(state, q.clustering)
        if q.what == "pairs":
            return self._pairs(state, q, base, clusters)
        groups, tile_m = clusters, None
        k = len(np.unique(clusters))
        if q.budget > 0 and n >= 2 and k > overview.max_groups(q.budget):
            groups, tile_m = overview.tile_groups(state.landmarks, q.budget)
        k = len(np.unique(groups))
        if k * (k - 1) // 2 > self.max_group_pairs:
            raise SummaryQueryError(
                f"summary query: {k} clusters make {k * (k - 1) // 2} cluster pairs, more "
                f"than {self.max_group_pairs}; ask with budget=G (then map tiles) or a "
                "larger threshold")
        if n < 2:  # no pair yet (the init state, a first feature): no group pairs
            gp = overview.GroupPairs(np.zeros((0, 2), np.int64), np.zeros(0, np.int64),
                                     np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64),
                                     np.zeros((0, 2, 2)))
        else:
            gp = overview.group_min_mean_max(P, groups)
        return replace(
            base, what="clusters", cluster_threshold_m=q.threshold_m, cluster_count=q.count,
            tile_m=tile_m,
            groups=groups, group_pairs=gp.groups, pair_count=gp.count, min_pair=gp.min_pair,
            max_pair=gp.max_pair, mean_Pd=gp.mean_Pd,
            min_Pd=overview.pair_relative_covariances(P, gp.min_pair[:, 0], gp.min_pair[:, 1]),
            max_Pd=overview.pair_relative_covariances(P, gp.max_pair[:, 0], gp.max_pair[:, 1]))

    def _pairs(self, state: SlamState, q: SummaryQuery, base: StateSummary,
               clusters: np.ndarray) -> StateSummary:
        n = state.n
        if q.feature is not None:
            hit = np.flatnonzero(state.landmark_ids == q.feature)
            if not hit.size:
                raise SummaryQueryError(f"summary query: feature {q.feature} is not in the "
                                        f"map of seq {state.seq}")
            i = int(hit[0])
            others = np.delete(np.arange(n), i)
            ii, jj = np.minimum(i, others), np.maximum(i, others)
        else:
            members = np.flatnonzero(clusters == q.cluster)
            if not members.size:
                raise SummaryQueryError(f"summary query: cluster {q.cluster} is not in the "
                                        f"map of seq {state.seq} (threshold "
                                        f"{q.threshold_m:g} m, count {q.count})")
            a, b = np.triu_indices(len(members), k=1)
            ii, jj = members[a], members[b]
        if q.budget <= 0 and len(ii) > self.max_pairs:  # refuse before the work
            raise SummaryQueryError(
                f"summary query: {len(ii)} pairs, more than {self.max_pairs}; ask with "
                f"budget=G (then the {overview.SELECTED_CAP}·G largest)")
        Pd = overview.pair_relative_covariances(state.covariance, ii, jj)
        total = len(ii)
        cap = overview.SELECTED_CAP * q.budget
        if q.budget > 0 and total > cap:  # as the viewer: the largest, in pair order
            keep = np.sort(np.argsort(-pd_size_m(Pd), kind="stable")[:cap])
            ii, jj, Pd = ii[keep], jj[keep], Pd[keep]
        if len(ii) > self.max_pairs:
            raise SummaryQueryError(
                f"summary query: {len(ii)} pairs, more than {self.max_pairs}; ask with "
                f"budget=G (then the {overview.SELECTED_CAP}·G largest)")
        return replace(base, what="pairs", cluster_threshold_m=q.threshold_m,
                       cluster_count=q.count, groups=clusters, selected_cluster=q.cluster,
                       selected_feature=q.feature,
                       pairs=np.column_stack([ii, jj]).reshape(-1, 2), pairs_Pd=Pd,
                       pairs_total=total)
