"""The remote viewers' summary (common/summary.py) against a dense numpy oracle, and its
query parameters (docs/remote_viewers.md)."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.clusters import cluster_labels
from slamlens.common.messages import SlamState, StateSummary
from slamlens.common.summary import Summariser, SummaryQuery, SummaryQueryError, parse_query


def consistent_state(n: int, *, seed: int = 0, seq: int = 1, spread: float = 0.2,
                     epoch: int = 7) -> SlamState:
    """n features in three spatial clusters and a random PSD covariance (A Aᵀ + εI)."""
    rng = np.random.default_rng(seed)
    centres = np.array([[-1.0, 1.0], [1.2, 1.0], [0.1, -1.2]])
    xy = np.concatenate([c + rng.normal(0, spread, (n // 3 + 1, 2)) for c in centres])[:n]
    N = 3 + 2 * n
    A = rng.normal(size=(N, N)) * 0.03
    P = A @ A.T + 1e-4 * np.eye(N)
    return SlamState(robot="r1", seq=seq, stamp=0.5 * seq, step="update",
                     pose=np.array([0.3, -0.2, 0.4]), landmark_ids=np.arange(10, 10 + n),
                     landmarks=xy, covariance=P, epoch=epoch)


def oracle_pd(P: np.ndarray, i: int, j: int) -> np.ndarray:
    """P_d of landmarks i, j the textbook way: P_ii + P_jj − P_ij − P_ji (docs/monitor.md)."""
    a, b = slice(3 + 2 * i, 5 + 2 * i), slice(3 + 2 * j, 5 + 2 * j)
    return P[a, a] + P[b, b] - P[a, b] - P[b, a]


def size(Pd: np.ndarray) -> float:
    return float(np.sqrt(np.linalg.eigvalsh(Pd)[-1]))


def oracle_groups(state: SlamState, groups: np.ndarray) -> dict[tuple[int, int], dict]:
    """Per group pair: min / max size and the mean P_d over every inter-group pair."""
    out: dict[tuple[int, int], dict] = {}
    P = state.covariance
    for i in range(state.n):
        for j in range(i + 1, state.n):
            if groups[i] == groups[j]:
                continue
            key = (int(min(groups[i], groups[j])), int(max(groups[i], groups[j])))
            Pd = oracle_pd(P, i, j)
            s = size(Pd)
            g = out.setdefault(key, {"min": np.inf, "max": -np.inf, "sum": np.zeros((2, 2)),
                                     "count": 0})
            g["min"], g["max"] = min(g["min"], s), max(g["max"], s)
            g["sum"] += Pd
            g["count"] += 1
    return out


def test_blocks_are_the_state_s_pose_covariance_and_marginals_in_float32() -> None:
    state = consistent_state(40)
    s = StateSummary.from_bytes(Summariser().summary(state, parse_query("what=blocks")))
    P = state.covariance
    assert (s.robot, s.seq, s.epoch, s.what, s.n) == ("r1", 1, 7, "blocks", 40)
    assert s.landmark_covariances.dtype == np.float32 and s.landmarks.dtype == np.float32
    np.testing.assert_array_equal(s.landmark_ids, state.landmark_ids)
    np.testing.assert_allclose(s.pose, state.pose)
    np.testing.assert_allclose(s.pose_covariance, P[:3, :3], rtol=1e-6)
    np.testing.assert_allclose(s.landmarks, state.landmarks, rtol=1e-6)
    for i in range(40):
        block = P[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i]
        np.testing.assert_allclose(s.landmark_covariances[i], block, rtol=1e-6)
    assert s.group_pairs is None and s.pairs is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clusters_equal_the_dense_oracle_within_float32(seed: int) -> None:
    state = consistent_state(60, seed=seed)
    s = StateSummary.from_bytes(Summariser().summary(state, parse_query(
        "what=clusters;threshold=0.6")))
    # the groups are the single-linkage clusters (ids renumbered, the partition the same)
    labels = cluster_labels(state.landmarks, threshold_m=0.6)
    assert s.groups is not None and s.group_pairs is not None
    same = labels[:, None] == labels[None, :]
    np.testing.assert_array_equal(s.groups[:, None] == s.groups[None, :], same)
    expected = oracle_groups(state, s.groups)
    assert sorted(map(tuple, s.group_pairs.tolist())) == sorted(expected)
    assert s.min_Pd is not None and s.max_Pd is not None and s.mean_Pd is not None
    assert s.min_Pd.dtype == np.float32
    scale = float(np.abs(state.covariance).max())
    for k, (a, b) in enumerate(s.group_pairs.tolist()):
        e = expected[(a, b)]
        assert s.pair_count[k] == e["count"]
        np.testing.assert_allclose(s.mean_Pd[k], e["sum"] / e["count"], atol=1e-5 * scale)
        # the min / max pairs are the oracle's (by size, to float32 ranking) and their P_d
        # is theirs
        for which, pair, Pd in (("min", s.min_pair[k], s.min_Pd[k]),
                                ("max", s.max_pair[k], s.max_Pd[k])):
            i, j = int(pair[0]), int(pair[1])
            assert i < j and {int(s.groups[i]), int(s.groups[j])} == {a, b}
            np.testing.assert_allclose(Pd, oracle_pd(state.covariance, i, j),
                                       atol=1e-5 * scale)
            assert size(oracle_pd(state.covariance, i, j)) == pytest.approx(e[which],
                                                                              rel=1e-4)


def test_a_budget_turns_many_clusters_into_map_tiles() -> None:
    state = consistent_state(60, spread=3.0)  # scattered: many single-linkage clusters
    q = parse_query("what=clusters;threshold=0.05;budget=30")
    s = StateSummary.from_bytes(Summariser().summary(state, q))
    assert s.tile_m is not None and s.tile_m > 0
    k = len(np.unique(s.groups))
    assert 3 * k * (k - 1) // 2 <= 30
    tiles = np.floor(state.landmarks / s.tile_m)
    same_tile = (tiles[:, None, :] == tiles[None, :, :]).all(-1)
    np.testing.assert_array_equal(s.groups[:, None] == s.groups[None, :], same_tile)
    expected = oracle_groups(state, s.groups)
    scale = float(np.abs(state.covariance).max())
    for k, (a, b) in enumerate(s.group_pairs.tolist()):
        np.testing.assert_allclose(s.mean_Pd[k], expected[(a, b)]["sum"]
                                   / expected[(a, b)]["count"], atol=1e-5 * scale)


def test_too_many_cluster_pairs_without_a_budget_is_refused_with_the_way_out() -> None:
    state = consistent_state(60, spread=3.0)
    with pytest.raises(SummaryQueryError, match="budget="):
        Summariser(max_group_pairs=10).summary(state, parse_query("threshold=0.01"))


def test_pairs_of_one_cluster_and_of_one_feature_equal_the_oracle() -> None:
    state = consistent_state(45)
    summariser = Summariser()
    first = StateSummary.from_bytes(summariser.summary(state, parse_query("what=clusters")))
    cluster = int(first.groups[0])
    s = StateSummary.from_bytes(summariser.summary(state, parse_query(f"cluster={cluster}")))
    assert s.what == "pairs" and s.selected_cluster == cluster
    members = np.flatnonzero(first.groups == cluster)
    assert s.pairs_total == len(members) * (len(members) - 1) // 2 == len(s.pairs)
    scale = float(np.abs(state.covariance).max())
    for (i, j), Pd in zip(s.pairs.tolist(), s.pairs_Pd, strict=True):
        assert i < j and i in members and j in members
        np.testing.assert_allclose(Pd, oracle_pd(state.covariance, i, j), atol=1e-5 * scale)
    f = StateSummary.from_bytes(summariser.summary(state, parse_query("feature=12")))
    assert len(f.pairs) == 44 and all(2 in p for p in f.pairs.tolist())  # id 12 = index 2
    # capped by a budget: its largest pairs, in pair order
    capped = StateSummary.from_bytes(summariser.summary(
        state, parse_query(f"cluster={cluster};budget=10")))
    sizes = [size(oracle_pd(state.covariance, i, j)) for i, j in s.pairs.tolist()]
    kept = {tuple(p) for p in capped.pairs.tolist()}
    assert len(kept) == 40 and capped.pairs_total == s.pairs_total
    threshold = sorted(sizes, reverse=True)[39]
    assert all(sz >= threshold * (1 - 1e-5) for p, sz in zip(s.pairs.tolist(), sizes,
                                                              strict=True) if tuple(p) in kept)


def test_cluster_ids_stay_stable_as_the_map_grows() -> None:
    summariser = Summariser()
    big = consistent_state(30, seq=2)
    small = SlamState(robot="r1", seq=1, stamp=0.5, step="update", pose=big.pose,
                      landmark_ids=big.landmark_ids[:20], landmarks=big.landmarks[:20],
                      covariance=big.covariance[:43, :43], epoch=7)
    q = parse_query("what=clusters")
    a = StateSummary.from_bytes(summariser.summary(small, q))
    b = StateSummary.from_bytes(summariser.summary(big, q))
    np.testing.assert_array_equal(b.groups[:20], a.groups)


def test_the_cache_shares_one_computation_between_equal_queries() -> None:
    summariser = Summariser()
    state = consistent_state(30)
    one = summariser.summary(state, parse_query("what=clusters;after=0"))
    two = summariser.summary(state, parse_query("what=clusters;after=0;epoch=3"))
    assert one == two and (summariser.made, summariser.shared) == (1, 1)


@pytest.mark.parametrize("parameters, says", [
    ("what=everything", "what='everything'"),
    ("colour=red", "unknown parameter 'colour'"),
    ("threshold=abc", "threshold='abc' is not a number"),
    ("threshold=-1", "must be > 0"),
    ("threshold=nan", "not finite"),
    ("budget=-5", "budget='-5' must be ≥ 0"),
    ("count=1.5", "count='1.5' is not an integer"),
    ("what=pairs", "exactly one of cluster=K or feature=ID"),
    ("cluster=1;feature=2", "exactly one of"),
    ("what=blocks;cluster=1", "go with what=pairs"),
    ("epoch=3", "epoch goes with after=SEQ"),
    ("what=clusters;what=blocks", "what given twice"),
    ("threshold", "threshold needs a value"),
])
def test_bad_parameters_raise_one_clear_sentence(parameters: str, says: str) -> None:
    with pytest.raises(SummaryQueryError, match="summary query") as info:
        parse_query(parameters)
    assert says in str(info.value)


def test_parameters_round_trip_through_the_selector() -> None:
    q = SummaryQuery(what="clusters", threshold_m=0.4, count=3, budget=2000, after=9, epoch=5)
    assert parse_query(q.selector()) == q
    assert parse_query("what=clusters&threshold=0.4&count=3&budget=2000&after=9&epoch=5") == q
    assert parse_query("") == SummaryQuery()
    assert q.newer(5, 10) and not q.newer(5, 9) and q.newer(6, 1)


def test_too_many_pairs_are_refused_before_the_work() -> None:
    state = consistent_state(45)
    summariser = Summariser(max_pairs=20)
    first = StateSummary.from_bytes(summariser.summary(state, parse_query("what=clusters")))
    with pytest.raises(SummaryQueryError, match="more than 20; ask with budget"):
        summariser.summary(state, parse_query(f"cluster={int(first.groups[0])}"))
    capped = StateSummary.from_bytes(summariser.summary(
        state, parse_query(f"cluster={int(first.groups[0])};budget=4")))
    assert len(capped.pairs) == 16


def test_a_missing_feature_or_cluster_is_a_query_error() -> None:
    state = consistent_state(12)
    with pytest.raises(SummaryQueryError, match="feature 999 is not in the map"):
        Summariser().summary(state, parse_query("feature=999"))
    with pytest.raises(SummaryQueryError, match="cluster 77 is not in the map"):
        Summariser().summary(state, parse_query("cluster=77"))


@pytest.mark.parametrize("n", [0, 1, 2])
def test_maps_without_pairs_or_with_one_summarise(n: int) -> None:
    state = consistent_state(3)
    small = SlamState(robot="r1", seq=0, stamp=0.0, step="init", pose=np.zeros(3),
                      landmark_ids=state.landmark_ids[:n], landmarks=state.landmarks[:n],
                      covariance=state.covariance[:3 + 2 * n, :3 + 2 * n])
    for text in ("what=clusters", "what=clusters;budget=3", "what=blocks"):
        s = StateSummary.from_bytes(Summariser().summary(small, parse_query(text)))
        assert s.n == n
        if s.what == "clusters":
            assert len(s.group_pairs) == (1 if n == 2 and s.groups[0] != s.groups[1] else 0)
