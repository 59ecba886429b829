"""Time series behind the viewer's plots (issue 5): P_d size per pair, min/mean/max per
cluster pair, and the monitor's statistics (NEES, NIS and their bounds).

Samples are decimated in wall-clock time (one state and one health sample per
``min_interval_s`` at most) so a fixed number of samples covers minutes, whatever the
estimator's event rate. Each state sample keeps the size of P_d for *every* pair, so the
plot of any pair can be drawn after the fact, not only from when somebody asked for it.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.geometry import all_relative_covariances, pd_size_m
from common.messages import Health, SlamState

#: A scalar size for each P_d of a stack (m, 2, 2) → (m,).
SizeFn = Callable[[np.ndarray], np.ndarray]
#: Cluster labels (n,) for landmark positions (n, 2); stable identities across calls.
ClusterFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def pair_index(i: int, j: int, n: int) -> int:
    """Position of pair (i, j), i < j, in ``np.triu_indices(n, k=1)`` order."""
    return i * (2 * n - i - 1) // 2 + (j - i - 1)


@dataclass(frozen=True)
class StateSample:
    stamp: float
    seq: int
    landmark_ids: np.ndarray  #: int64[n]
    sizes: np.ndarray  #: float32[n(n−1)/2], triu order
    clusters: dict[tuple[int, int], tuple[float, float, float]]  #: (A, B) → min, mean, max


@dataclass(frozen=True)
class HealthSample:
    stamp: float
    seq: int
    statistics: dict[str, float]


def _clean(values: Iterable[float | None]) -> list[float | None]:
    """JSON-safe list: NaN and infinities become null."""
    return [None if v is None or not math.isfinite(v) else float(v) for v in values]


#: above this many cluster pairs a sample keeps no cluster min/mean/max (a map of n = 1000
#: mostly singletons has ~500 000: a dict of them per sample, 600 samples, is gigabytes)
MAX_CLUSTER_PAIRS = 2000


class SeriesStore:
    """Bounded, decimated history of states and health verdicts (thread-safe)."""

    def __init__(self, *, length: int = 600, min_interval_s: float = 0.2,
                 size_of: SizeFn = pd_size_m, cluster: ClusterFn | None = None,
                 size_name: str = "size of P_d: √λmax, the 1-σ major semi-axis (m)") -> None:
        self._states: deque[StateSample] = deque(maxlen=length)
        self._health: deque[HealthSample] = deque(maxlen=length)
        self._min_interval = min_interval_s
        self._size_of = size_of
        self._cluster = cluster
        self.size_name = size_name
        self._last_state = -math.inf
        self._last_health = -math.inf
        self._epoch: int | None = None  #: epoch of the map sampled
        self._pending: dict[str, float] = {}  #: newest statistics since the last sample
        self._lock = threading.Lock()

    def clear(self) -> None:
        with self._lock:
            self._states.clear()
            self._health.clear()
            self._last_state = self._last_health = -math.inf
            self._epoch = None
            self._pending = {}

    # -- filling ------------------------------------------------------------------
    def add_state(self, state: SlamState, *, now: float) -> bool:
        """Sample ``state`` unless one was sampled less than ``min_interval_s`` ago."""
        if now - self._last_state < self._min_interval:
            return False
        n = state.n
        if n >= 2:
            _, _, Pd = all_relative_covariances(state.covariance, n)
            sizes = np.asarray(self._size_of(Pd), dtype=float)
        else:
            Pd = np.zeros((0, 2, 2))
            sizes = np.zeros(0)
        clusters = self._cluster_stats(state, Pd, sizes) if self._cluster is not None else {}
        sample = StateSample(float(state.stamp), int(state.seq), np.array(state.landmark_ids),
                             sizes.astype(np.float32), clusters)  # float32: half the memory
        with self._lock:
            new_map = self._epoch is not None and state.epoch != self._epoch
            if new_map or (state.epoch == 0 and self._states
                           and sample.seq < self._states[-1].seq):
                self._states.clear()  # a new map (epoch; or, epoch unknown, seq went back)
                self._health.clear()
            elif self._states and sample.seq <= self._states[-1].seq:
                return False  # the same map replayed from a checkpoint: already plotted
            self._epoch = int(state.epoch)
            self._states.append(sample)
            self._last_state = now
        return True

    def _cluster_stats(self, state: SlamState, Pd: np.ndarray,
                       sizes: np.ndarray) -> dict[tuple[int, int], tuple[float, float, float]]:
        n = state.n
        if n < 2 or self._cluster is None:
            return {}
        labels = np.asarray(self._cluster(np.asarray(state.landmarks), np.asarray(
            state.landmark_ids)))
        groups = np.unique(labels).size
        if groups * (groups - 1) // 2 > MAX_CLUSTER_PAIRS:
            return {}  # a map of many small clusters: no per-cluster-pair plot (too many)
        first, second = np.triu_indices(n, k=1)
        A, B = labels[first], labels[second]
        lo, hi = np.minimum(A, B), np.maximum(A, B)
        between = lo != hi
        if not between.any():
            return {}
        lo, hi = lo[between], hi[between]
        # one group per cluster pair, in (a, b) order, reduced at once: a map of n = 1000
        # singletons has ~500 000 cluster pairs (a loop with a mask each took minutes)
        order = np.lexsort((hi, lo))
        lo, hi = lo[order], hi[order]
        starts = np.flatnonzero(np.r_[True, (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])])
        grouped = sizes[between][order]
        counts = np.diff(np.r_[starts, lo.size])
        # mean: the size of the element-wise mean P_d (as the minmeanmax glyph shows it)
        means = self._size_of(np.add.reduceat(Pd[between][order], starts, axis=0)
                              / counts[:, None, None])
        return {(int(a), int(b)): (float(mn), float(me), float(mx)) for a, b, mn, me, mx in zip(
            lo[starts], hi[starts], np.minimum.reduceat(grouped, starts), np.asarray(means),
            np.maximum.reduceat(grouped, starts), strict=True)}

    def add_health(self, health: Health, *, now: float) -> bool:
        """Sample the monitor's statistics at most every ``min_interval_s``. A statistic
        that only some verdicts carry (NIS: update states only) keeps its newest value from
        the verdicts skipped since the last sample, so decimation never drops a series."""
        with self._lock:
            self._pending.update(health.statistics)
            if now - self._last_health < self._min_interval:
                return False
            self._health.append(HealthSample(float(health.stamp), int(health.seq),
                                             self._pending))
            self._pending = {}
            self._last_health = now
        return True

    # -- reading ------------------------------------------------------------------
    def latest_sizes(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(landmark_ids, sizes) of the newest state sample."""
        with self._lock:
            if not self._states:
                return None
            s = self._states[-1]
        return s.landmark_ids, s.sizes

    def default_pairs(self, *, selected: int | None = None, flagged: Sequence[tuple[int, int]] = (),
                      limit: int = 6) -> list[tuple[int, int]]:
        """Pairs worth plotting: flagged by the monitor, else the selected feature's,
        else the largest P_d right now."""
        if flagged:
            return [(min(a, b), max(a, b)) for a, b in flagged][:limit]
        latest = self.latest_sizes()
        if latest is None:
            return []
        ids, sizes = latest
        n = len(ids)
        first, second = np.triu_indices(n, k=1)
        if selected is not None:
            mask = (ids[first] == selected) | (ids[second] == selected)
            first, second, sizes = first[mask], second[mask], sizes[mask]
        order = np.argsort(-sizes, kind="stable")[:limit]
        return [(min(int(ids[first[k]]), int(ids[second[k]])),
                 max(int(ids[first[k]]), int(ids[second[k]]))) for k in order]

    def to_json(self, pairs: Sequence[tuple[int, int]]) -> dict[str, Any]:
        with self._lock:
            states = list(self._states)
            health = list(self._health)
        pair_values: list[list[float | None]] = [[] for _ in pairs]
        for s in states:
            index = {int(v): k for k, v in enumerate(s.landmark_ids)}
            n = len(s.landmark_ids)
            for values, (a, b) in zip(pair_values, pairs, strict=True):
                i, j = index.get(a), index.get(b)
                if i is None or j is None or i == j:
                    values.append(None)
                    continue
                i, j = min(i, j), max(i, j)
                values.append(float(s.sizes[pair_index(i, j, n)]))
        labels = sorted({k for s in states for k in s.clusters})
        clusters = []
        for a, b in labels:
            rows = [s.clusters.get((a, b)) for s in states]
            clusters.append({
                "clusters": [a, b], "label": f"{a}–{b}",
                **{name: _clean(None if r is None else r[k] for r in rows)
                   for k, name in enumerate(("min", "mean", "max"))}})
        stat_names = sorted({k for h in health for k in h.statistics})
        return {
            "size": self.size_name,
            "state": {"t": [s.stamp for s in states], "seq": [s.seq for s in states]},
            "pairs": [{"ids": [a, b], "label": f"{a}–{b}", "values": _clean(v)}
                      for (a, b), v in zip(pairs, pair_values, strict=True)],
            "clusters": clusters,
            "health": {"t": [h.stamp for h in health], "seq": [h.seq for h in health],
                       "stats": {k: _clean(h.statistics.get(k) for h in health)
                                 for k in stat_names}},
        }
