"""Time series behind the viewer's plots: P_d size per pair, min/mean/max per
cluster pair, and the monitor's statistics (NEES, NIS and their bounds).

Samples are decimated in wall-clock time (one state and one health sample per
``min_interval_s`` at most) so a fixed number of samples covers minutes, whatever the
estimator's event rate. Each state sample of a map of up to ``DENSE_PAIRS`` pairs keeps the
size of P_d for *every* pair, so the plot of any pair can be drawn after the fact, not only
from when somebody asked for it.

Large maps (more than ``DENSE_PAIRS`` pairs, n > 200): every pair's size is still
computed per sample (:func:`all_pair_sizes`, whole-matrix float32 passes, no per-pair
gathers), but only the newest sample keeps all of them (what ``default_pairs`` ranks); the
history keeps, per sample, the ``KEEP_LARGEST`` largest pairs and the pairs plotted
recently (``to_json`` asked for them: up to ``WATCHED`` pairs), so a pair's plot begins when
it was first among the largest or first plotted (before: null). At n = 1000 every sample
of every pair would be 2 MB, 1.2 GB for the 600 samples. The cluster min / mean / max of a
large map come from the whole-matrix kernel (``slamlens.common.overview.group_min_mean_max``), and
a sample is taken at most every ``COST_FACTOR`` × its own computing time (the plots take at
most 1/20 of the viewer's time, whatever n).
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from slamlens.common import overview
from slamlens.common.geometry import all_relative_covariances, pd_size_m
from slamlens.common.messages import Health, SlamState

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
    sizes: np.ndarray  #: float32[n(n−1)/2], triu order (or of ``kept`` only)
    clusters: dict[tuple[int, int], tuple[float, float, float]]  #: (A, B) → min, mean, max
    #: large maps: the triu positions (sorted) of the pairs ``sizes`` holds; None: all
    kept: np.ndarray | None = None

    def size(self, k: int) -> float | None:
        """The size of the pair at triu position ``k``, or None (not kept)."""
        if self.kept is None:
            return float(self.sizes[k])
        at = int(np.searchsorted(self.kept, k))
        if at < len(self.kept) and int(self.kept[at]) == k:
            return float(self.sizes[at])
        return None


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
#: above this many pairs a sample keeps only some pairs (module docstring)
DENSE_PAIRS = overview.FAST_PAIRS
KEEP_LARGEST = 1000  #: a large map's sample keeps this many of its largest pairs …
WATCHED = 64  #: … and the pairs of the last this many plotted
COST_FACTOR = 20.0  #: a large map is sampled at most every 20 × the sample's computing time


def all_pair_sizes(P: np.ndarray, n: int, *, chunk: int = 256) -> np.ndarray:
    """√λmax of P_d for every pair i < j (triu order), float32: the same values as
    ``pd_size_m(all_relative_covariances(P, n)[2])`` to float32 rounding, from strided
    views of P (X = P[x_i, x_j], Y, and the cross terms) in row blocks — no per-pair
    gathers of P (about 3× faster at n = 1000)."""
    N = 3 + 2 * n
    X, Y, Z = P[3:N:2, 3:N:2], P[4:N:2, 4:N:2], P[3:N:2, 4:N:2]
    f4 = np.float32
    dx, dy, dz = (np.diagonal(M).astype(f4) for M in (X, Y, Z))
    lam = np.empty((n, n), f4)
    for i0 in range(0, n, chunk):
        i1 = min(n, i0 + chunk)
        a = X[i0:i1].astype(f4)
        a *= -2.0
        a += dx[i0:i1, None]
        a += dx[None, :]
        c = Y[i0:i1].astype(f4)
        c *= -2.0
        c += dy[i0:i1, None]
        c += dy[None, :]
        b = Z[i0:i1].astype(f4)
        b += Z[:, i0:i1].T  # P_xy(i, j) + P_yx(i, j) = P_xy(i, j) + P_xy(j, i)
        np.subtract(dz[i0:i1, None] + dz[None, :], b, out=b)
        h = a - c
        h *= 0.5
        h *= h
        b *= b
        h += b
        np.sqrt(h, out=h)
        a += c
        a *= 0.5
        a += h
        lam[i0:i1] = a
    first, second = np.triu_indices(n, k=1)
    out = lam.reshape(-1).take(first * n + second)
    np.maximum(out, 0.0, out=out)
    return np.sqrt(out, out=out)


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
        self._interval = min_interval_s  #: the interval now (large maps: by their cost)
        self._latest: tuple[np.ndarray, np.ndarray] | None = None  #: newest ids, all sizes
        #: pairs plotted recently (ids, smaller first): a large map's samples keep them
        self._watched: OrderedDict[tuple[int, int], None] = OrderedDict()
        self._epoch: int | None = None  #: epoch of the map sampled
        self._pending: dict[str, float] = {}  #: newest statistics since the last sample
        self._lock = threading.Lock()

    def clear(self) -> None:
        with self._lock:
            self._states.clear()
            self._health.clear()
            self._last_state = self._last_health = -math.inf
            self._interval = self._min_interval
            self._latest = None
            self._epoch = None
            self._pending = {}

    # -- filling ------------------------------------------------------------------
    @property
    def interval_s(self) -> float:
        """The sampling interval now (a large map's: by its cost), s."""
        with self._lock:
            return self._interval

    def due(self, now: float) -> bool:
        """Whether a state at ``now`` would be sampled (the interval has passed)."""
        return now - self._last_state >= self._interval

    def add_state(self, state: SlamState, *, now: float) -> bool:
        """Sample ``state`` unless one was sampled less than ``min_interval_s`` ago (for a
        large map: less than ``COST_FACTOR`` × the last sample's computing time)."""
        if not self.due(now):
            return False
        t0 = time.perf_counter()
        n = state.n
        pairs = n * (n - 1) // 2
        large = pairs > DENSE_PAIRS and self._size_of is pd_size_m
        kept: np.ndarray | None = None
        if large:
            full = all_pair_sizes(np.asarray(state.covariance), n)
            clusters = self._cluster_stats_large(state) if self._cluster is not None else {}
            kept = self._kept(full, np.asarray(state.landmark_ids))
            sizes = full[kept]
        elif n >= 2:
            _, _, Pd = all_relative_covariances(state.covariance, n)
            sizes = np.asarray(self._size_of(Pd), dtype=float)
            clusters = self._cluster_stats(state, Pd, sizes) if self._cluster is not None \
                else {}
            full = sizes
        else:
            sizes = full = np.zeros(0)
            clusters = {}
        sample = StateSample(float(state.stamp), int(state.seq), np.array(state.landmark_ids),
                             sizes.astype(np.float32), clusters,  # float32: half the memory
                             kept)
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
            self._latest = (sample.landmark_ids, np.asarray(full, np.float32))
            self._last_state = now
            spent = time.perf_counter() - t0
            self._interval = max(self._min_interval, COST_FACTOR * spent) if large \
                else self._min_interval
        return True

    def _kept(self, full: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Triu positions (sorted) a large map's sample keeps: its ``KEEP_LARGEST``
        largest pairs and the watched pairs present in the map."""
        n = len(ids)
        k = min(KEEP_LARGEST, len(full))
        largest = np.argpartition(-full, k - 1)[:k] if k else np.zeros(0, np.int64)
        with self._lock:
            watched = list(self._watched)
        index = {int(v): i for i, v in enumerate(ids.tolist())}
        extra = []
        for a, b in watched:
            i, j = index.get(a), index.get(b)
            if i is not None and j is not None and i != j:
                extra.append(pair_index(min(i, j), max(i, j), n))
        return np.unique(np.r_[largest, np.array(extra, np.int64)].astype(np.int64))

    def _cluster_stats_large(self, state: SlamState
                             ) -> dict[tuple[int, int], tuple[float, float, float]]:
        """Cluster min / mean / max of a large map from the whole-matrix kernel."""
        assert self._cluster is not None
        labels = np.asarray(self._cluster(np.asarray(state.landmarks),
                                          np.asarray(state.landmark_ids)))
        groups = np.unique(labels).size
        if groups < 2 or groups * (groups - 1) // 2 > MAX_CLUSTER_PAIRS:
            return {}
        P = np.asarray(state.covariance)
        gp = overview.group_min_mean_max(P, labels)
        low = pd_size_m(overview.pair_relative_covariances(P, gp.min_pair[:, 0],
                                                           gp.min_pair[:, 1]))
        high = pd_size_m(overview.pair_relative_covariances(P, gp.max_pair[:, 0],
                                                            gp.max_pair[:, 1]))
        means = pd_size_m(gp.mean_Pd)
        return {(int(a), int(b)): (float(mn), float(me), float(mx)) for (a, b), mn, me, mx
                in zip(gp.groups.tolist(), low, means, high, strict=True)}

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
        """(landmark_ids, sizes of every pair) of the newest state sample."""
        with self._lock:
            if not self._states or self._latest is None:
                return None
            return self._latest

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
            for a, b in pairs:  # a large map's next samples keep these pairs
                key = (min(a, b), max(a, b))
                self._watched[key] = None
                self._watched.move_to_end(key)
            while len(self._watched) > WATCHED:
                self._watched.popitem(last=False)
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
                values.append(s.size(pair_index(i, j, n)))
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


class PlotSampler:
    """Samples large maps' states for the plots on a thread of its own (``viewer-plots``),
    newest first: the render thread hands a state over (O(1)) and never waits for a sample;
    a state handed over while one is being sampled replaces any not yet taken.
    ``on_error(state, exc)`` is told of a sample that failed (the plots are optional)."""

    def __init__(self, on_error: Callable[[SlamState, Exception], None]) -> None:
        self._on_error = on_error
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._next: tuple[SeriesStore, SlamState, float] | None = None
        self._thread: threading.Thread | None = None
        self.sampled = 0  #: states sampled
        self.sampled_event = threading.Event()  #: set after each sample taken
        self.replaced = 0  #: states handed over and replaced by a newer one before sampling

    def offer(self, store: SeriesStore, state: SlamState, now: float) -> None:
        with self._lock:
            if self._next is not None:
                self.replaced += 1
            self._next = (store, state, now)
        self._wake.set()

    def idle(self) -> bool:
        """Nothing handed over waits to be sampled."""
        with self._lock:
            return self._next is None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="viewer-plots", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                job, self._next = self._next, None
            if job is None:
                continue
            store, state, now = job
            try:
                if store.add_state(state, now=now):
                    self.sampled += 1
                    self.sampled_event.set()
            except Exception as exc:  # the plots are optional; the viewer goes on
                self._on_error(state, exc)
