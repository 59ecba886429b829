"""The viewer's plots' series (services/visualiser/series.py): the pair index, P_d sizes
against an eigh oracle per pair, cluster statistics against brute force, the budget,
decimation in time, new runs and missing pairs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slamlens.common.messages import Health
from slamlens.services.visualiser.series import SeriesStore, pair_index
from tests.unit.viewer_states import random_state


# -- series -------------------------------------------------------------------------------
def test_pair_index_matches_numpy_triu_order() -> None:
    n = 9
    first, second = np.triu_indices(n, k=1)
    for k, (i, j) in enumerate(zip(first, second, strict=True)):
        assert pair_index(int(i), int(j), n) == k


def test_series_sizes_match_an_eigh_oracle_per_pair() -> None:
    state = random_state(6, seed=3)
    store = SeriesStore(min_interval_s=0.0)
    store.add_state(state, now=0.0)
    pairs = [(100, 105), (104, 101), (102, 103)]
    data = store.to_json(pairs)
    P = np.array(state.covariance)
    for (a, b), entry in zip(pairs, data["pairs"], strict=True):
        i, j = a - 100, b - 100
        si, sj = slice(3 + 2 * i, 5 + 2 * i), slice(3 + 2 * j, 5 + 2 * j)
        Pd = P[si, si] + P[sj, sj] - P[si, sj] - P[sj, si]
        expected = np.sqrt(np.linalg.eigvalsh(Pd)[-1])
        assert entry["values"] == [pytest.approx(expected, rel=1e-6)]
    assert data["state"]["seq"] == [1]


def test_series_cluster_min_mean_max_against_brute_force() -> None:
    xy = [[0, 0], [0.2, 0], [0.1, 0.2], [3, 3], [3.2, 3], [5, 0]]  # three clusters
    state = random_state(6, seed=5, landmarks=xy)
    labels = np.array([7, 7, 7, 8, 8, 9])
    store = SeriesStore(min_interval_s=0.0, cluster=lambda _xy, _ids: labels)
    store.add_state(state, now=0.0)
    clusters = {tuple(c["clusters"]): c for c in store.to_json([])["clusters"]}
    assert set(clusters) == {(7, 8), (7, 9), (8, 9)}
    P = np.array(state.covariance)

    def pd(i: int, j: int) -> np.ndarray:
        si, sj = slice(3 + 2 * i, 5 + 2 * i), slice(3 + 2 * j, 5 + 2 * j)
        return P[si, si] + P[sj, sj] - P[si, sj] - P[sj, si]

    members = [(i, j) for i in range(3) for j in (3, 4)]  # clusters 7 and 8
    sizes = [np.sqrt(np.linalg.eigvalsh(pd(i, j))[-1]) for i, j in members]
    mean_pd = np.mean([pd(i, j) for i, j in members], axis=0)
    c = clusters[(7, 8)]
    assert c["min"] == [pytest.approx(min(sizes), rel=1e-6)]
    assert c["max"] == [pytest.approx(max(sizes), rel=1e-6)]
    assert c["mean"] == [pytest.approx(np.sqrt(np.linalg.eigvalsh(mean_pd)[-1]), rel=1e-6)]


def test_series_cluster_stats_of_many_clusters_match_a_per_pair_loop() -> None:
    """Many clusters (singletons among them, labels in no order): every cluster pair's
    min / mean / max as a loop over the pairs computes it (a 1000-singleton map
    has ~500 000 cluster pairs, reduced at once)."""
    n = 40
    rng = np.random.default_rng(11)
    state = random_state(n, seed=12, landmarks=rng.uniform(0, 5, (n, 2)).tolist())
    labels = rng.permutation(np.r_[np.arange(25), rng.integers(0, 25, n - 25)]) * 3 + 2
    store = SeriesStore(min_interval_s=0.0, cluster=lambda _xy, _ids: labels)
    store.add_state(state, now=0.0)
    got = {tuple(c["clusters"]): (c["min"][0], c["mean"][0], c["max"][0])
           for c in store.to_json([])["clusters"]}
    P = np.array(state.covariance)

    def pd(i: int, j: int) -> np.ndarray:
        si, sj = slice(3 + 2 * i, 5 + 2 * i), slice(3 + 2 * j, 5 + 2 * j)
        return P[si, si] + P[sj, sj] - P[si, sj] - P[sj, si]

    want: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for i in range(n):
        for j in range(i + 1, n):
            if labels[i] != labels[j]:
                key = (int(min(labels[i], labels[j])), int(max(labels[i], labels[j])))
                want.setdefault(key, []).append((i, j))
    assert set(got) == set(want) and len(want) > 250
    for key, members in want.items():
        sizes = [np.sqrt(np.linalg.eigvalsh(pd(i, j))[-1]) for i, j in members]
        mean = np.sqrt(np.linalg.eigvalsh(np.mean([pd(i, j) for i, j in members], axis=0))[-1])
        assert got[key] == (pytest.approx(min(sizes), rel=1e-6), pytest.approx(mean, rel=1e-6),
                            pytest.approx(max(sizes), rel=1e-6))


def test_series_keeps_no_cluster_stats_beyond_the_cluster_pair_budget() -> None:
    from slamlens.services.visualiser.series import MAX_CLUSTER_PAIRS

    n = 70  # 70 singletons: 2415 cluster pairs, above the budget of 2000
    assert n * (n - 1) // 2 > MAX_CLUSTER_PAIRS > 60 * 59 // 2
    state = random_state(n, seed=3, landmarks=np.random.default_rng(4).uniform(
        0, 5, (n, 2)).tolist())
    many = SeriesStore(min_interval_s=0.0, cluster=lambda _xy, _ids: np.arange(n))
    many.add_state(state, now=0.0)
    assert many.to_json([])["clusters"] == []
    fewer = SeriesStore(min_interval_s=0.0, cluster=lambda _xy, _ids: np.arange(n) % 60)
    fewer.add_state(state, now=0.0)
    assert len(fewer.to_json([])["clusters"]) == 60 * 59 // 2


def test_series_decimates_in_time_and_restarts_with_a_new_run() -> None:
    store = SeriesStore(min_interval_s=0.2)
    assert store.add_state(random_state(3, seq=1), now=10.0)
    assert not store.add_state(random_state(3, seq=2), now=10.1)
    assert store.add_state(random_state(3, seq=3), now=10.25)
    assert store.to_json([])["state"]["seq"] == [1, 3]
    assert store.add_state(random_state(3, seq=1), now=11.0)  # seq went back: a new run
    assert store.to_json([])["state"]["seq"] == [1]
    health = Health(robot="r", seq=1, stamp=0.1, ok=True, suspects=np.zeros(0, np.int64),
                    statistics={"nis": 1.5})
    assert store.add_health(health, now=11.0)
    assert store.to_json([])["health"]["stats"] == {"nis": [1.5]}
    # a statistic only some verdicts carry (NIS: updates) survives the decimation
    predict = dataclasses.replace(health, statistics={"nees_pose": 3.0})
    update = dataclasses.replace(health, statistics={"nees_pose": 2.0, "nis": 0.7})
    assert not store.add_health(update, now=11.1)
    assert store.add_health(predict, now=11.25)
    assert store.to_json([])["health"]["stats"] == {"nis": [1.5, 0.7],
                                                    "nees_pose": [None, 3.0]}
    # epochs: the same epoch with a lower seq is the same map (a resumed estimator)
    epoch = SeriesStore(min_interval_s=0.0)
    for seq in (4, 5, 3):
        epoch.add_state(dataclasses.replace(random_state(3, seq=seq), epoch=9), now=seq)
    assert epoch.to_json([])["state"]["seq"] == [4, 5]
    epoch.add_state(dataclasses.replace(random_state(3, seq=8), epoch=10), now=9)
    assert epoch.to_json([])["state"]["seq"] == [8]  # another epoch: a new map


def test_series_marks_missing_pairs_as_null_and_picks_default_pairs() -> None:
    store = SeriesStore(min_interval_s=0.0)
    store.add_state(random_state(2, seq=1), now=0.0)
    store.add_state(random_state(4, seq=2), now=1.0)  # features 102, 103 appear
    data = store.to_json([(100, 103), (100, 101)])
    assert data["pairs"][0]["values"][0] is None and data["pairs"][0]["values"][1] is not None
    assert store.default_pairs(flagged=[(103, 101)]) == [(101, 103)]
    chosen = store.default_pairs(selected=102, limit=10)
    assert len(chosen) == 3 and all(102 in p for p in chosen)
    ids, sizes = store.latest_sizes()  # type: ignore[misc]
    biggest = store.default_pairs(limit=1)[0]
    k = pair_index(biggest[0] - 100, biggest[1] - 100, 4)
    assert sizes[k] == sizes.max()
