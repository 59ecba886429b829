"""Single-linkage clusters and their stable identities."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from slamlens.common.clusters import ClusterTracker, cluster_colour, cluster_labels

CENTRES = np.array([[1.6, -0.55], [1.55, 1.7], [-0.6, 1.3]])  # the paper world's clusters


def three_clusters(seed: int = 0, per: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.concatenate([c + rng.uniform(-0.2, 0.2, (per, 2)) for c in CENTRES])


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all((a[:, None] == a[None]) == (b[:, None] == b[None])))


def test_three_well_separated_clusters_are_found_by_distance_and_by_count() -> None:
    pts = three_clusters()
    truth = np.repeat([0, 1, 2], 5)
    by_distance = cluster_labels(pts, threshold_m=0.6)
    by_count = cluster_labels(pts, count=3)
    assert same_partition(by_distance, truth)
    assert same_partition(by_count, truth)
    assert by_distance.tolist() == truth.tolist()  # numbered by first appearance


def test_single_linkage_equals_components_of_the_threshold_graph() -> None:
    rng = np.random.default_rng(11)
    for _ in range(20):
        pts = rng.uniform(0, 3, (int(rng.integers(2, 40)), 2))
        threshold = float(rng.uniform(0.1, 0.8))
        _, oracle = connected_components(cdist(pts, pts) <= threshold, directed=False)
        assert same_partition(cluster_labels(pts, threshold_m=threshold), oracle)


def test_count_cut_gives_that_many_clusters() -> None:
    pts = three_clusters(per=4)
    for count in (1, 2, 3, 5, 12):
        assert len(np.unique(cluster_labels(pts, count=count))) == count


def test_tiny_maps() -> None:
    assert cluster_labels(np.zeros((0, 2))).shape == (0,)
    assert cluster_labels(np.array([[1.0, 2.0]])).tolist() == [0]


def test_identities_survive_small_perturbations_and_renumbering() -> None:
    ids = np.arange(101, 116)
    tracker = ClusterTracker()
    first = tracker.update(ids, cluster_labels(three_clusters(0)))
    rng = np.random.default_rng(1)
    for step in range(10):
        pts = three_clusters(0) + rng.normal(0, 0.02, (15, 2))
        order = rng.permutation(15)  # another state order: fcluster numbers differently
        labels = cluster_labels(pts[order])
        stable = tracker.update(ids[order], labels)
        np.testing.assert_array_equal(stable, first[order], err_msg=f"step {step}")


def test_adding_landmarks_keeps_ids_and_new_clusters_get_new_ids() -> None:
    ids = np.arange(1, 16)
    pts = three_clusters(2)
    tracker = ClusterTracker()
    first = tracker.update(ids, cluster_labels(pts))
    # a sixteenth landmark joins the second cluster
    pts16 = np.vstack([pts, CENTRES[1] + [0.05, 0.0]])
    ids16 = np.append(ids, 99)
    second = tracker.update(ids16, cluster_labels(pts16))
    np.testing.assert_array_equal(second[:15], first)
    assert second[15] == first[5]
    # a far landmark makes a cluster of its own, with an id never used before
    pts17 = np.vstack([pts16, [5.0, 5.0]])
    third = tracker.update(np.append(ids16, 7), cluster_labels(pts17))
    np.testing.assert_array_equal(third[:16], second)
    assert third[16] not in set(first.tolist())


def test_a_split_keeps_the_id_on_the_larger_part() -> None:
    ids = np.arange(6)
    tracker = ClusterTracker()
    joined = np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.0], [0.9, 0.0], [1.2, 0.0], [1.5, 0.0]])
    before = tracker.update(ids, cluster_labels(joined, threshold_m=0.4))
    assert len(set(before.tolist())) == 1
    split = joined.copy()
    split[4:] += [1.0, 0.0]  # the last two move away
    after = tracker.update(ids, cluster_labels(split, threshold_m=0.4))
    assert after[:4].tolist() == [before[0]] * 4
    assert after[4] == after[5] != before[0]


def test_cluster_colours_are_stable_and_distinct() -> None:
    colours = [cluster_colour(i) for i in range(10)]
    assert colours == [cluster_colour(i) for i in range(10)]
    assert len(set(colours)) == 10
    for c in colours:
        assert len(c) == 3 and all(0 <= v <= 255 for v in c)


class _OracleTracker:
    """The textbook matching: one Hungarian assignment over all new × old clusters on
    their overlap counts (Jaccard tie-break), set operations per cluster pair."""

    def __init__(self) -> None:
        self.members: dict[int, frozenset[int]] = {}
        self.next_id = 0

    def update(self, ids: np.ndarray, labels: np.ndarray) -> np.ndarray:
        from scipy.optimize import linear_sum_assignment

        new_labels = np.unique(labels)
        new = [frozenset(ids[labels == lab].tolist()) for lab in new_labels]
        old = list(self.members)
        assigned: dict[int, int] = {}
        self.tied = False  # two candidates scored alike: either match is right
        self.split_or_merge = False  # a cluster overlapping several of the other frame
        if old and new:
            ov = np.array([[len(m & self.members[o]) for o in old] for m in new], float)
            un = np.array([[len(m | self.members[o]) for o in old] for m in new], float)
            score = ov + 1e-3 * ov / np.maximum(un, 1.0)
            for matrix in (score, score.T):
                for line in matrix:
                    top = np.sort(line[line > 0])[::-1]
                    self.tied |= len(top) > 1 and top[0] - top[1] < 1e-12
                    self.split_or_merge |= len(top) > 1
            rows, cols = linear_sum_assignment(score, maximize=True)
            for r, c in zip(rows, cols, strict=True):
                if ov[r, c] > 0:
                    assigned[int(r)] = old[int(c)]
        members = {}
        for k, m in enumerate(new):
            if k not in assigned:
                assigned[k] = self.next_id
                self.next_id += 1
            members[assigned[k]] = m
        self.members = members
        lut = np.array([assigned[k] for k in range(len(new_labels))])
        return lut[np.searchsorted(new_labels, labels)]


def test_the_fast_tracker_matches_one_assignment_over_all_clusters() -> None:
    """Random maps that grow, drift, split and merge: the same stable ids as the oracle."""
    rng = np.random.default_rng(5)
    compared = involved = 0
    for trial in range(80):
        fast, oracle = ClusterTracker(), _OracleTracker()
        xy = rng.uniform(0, 6, (30, 2))
        ids = rng.permutation(1000)[:30]
        for step in range(12):
            if step % 3 == 2:  # the map grows
                xy = np.vstack([xy, rng.uniform(0, 6, (10, 2))])
                ids = np.append(ids, 2000 + 10 * step + trial * 1000 + np.arange(10))
            xy = xy + rng.normal(0, 0.08, xy.shape)  # drift: clusters split and merge
            order = rng.permutation(len(ids))
            labels = cluster_labels(xy[order], threshold_m=0.7)
            ours, theirs = fast.update(ids[order], labels), oracle.update(ids[order], labels)
            if oracle.tied:  # an even split: both answers are right, the runs part ways
                break
            np.testing.assert_array_equal(ours, theirs)
            compared += 1
            involved += oracle.split_or_merge
    assert compared >= 150 and involved >= 20


def test_identities_stay_stable_as_a_1000_feature_map_grows() -> None:
    """A map of 40 well-separated clusters filled in 25 steps up to 1000 features: every
    cluster keeps the id it got when it was first seen."""
    rng = np.random.default_rng(2)
    centres = np.stack(np.meshgrid(np.arange(8), np.arange(5)), -1).reshape(-1, 2) * 4.0
    xy = np.repeat(centres, 25, axis=0) + rng.normal(0, 0.25, (1000, 2))
    ids = np.arange(1000)
    seen = rng.permutation(1000)
    tracker = ClusterTracker()
    first_id: dict[int, int] = {}
    for k in range(40, 1001, 40):
        idx = np.sort(seen[:k])
        stable = tracker.update(ids[idx], cluster_labels(xy[idx], threshold_m=1.5))
        for centre, cid in zip((idx // 25).tolist(), stable.tolist(), strict=True):
            assert first_id.setdefault(centre, cid) == cid
    assert len(set(first_id.values())) == 40


@pytest.mark.parametrize("seed", range(4))
def test_threshold_labels_equal_the_dendrogram_cut_label_for_label(seed: int) -> None:
    """The threshold cut (KD-tree + connected components) gives the labels that cutting
    scipy's single-linkage dendrogram gives (both renumbered by first appearance), on
    clustered and on grid-like maps up to n = 1000."""
    from scipy.cluster.hierarchy import fcluster, linkage

    rng = np.random.default_rng(seed)
    n = (40, 300, 1000, 1000)[seed]
    pts = (rng.uniform(0, 10, (n, 2)) if seed % 2 == 0 else
           np.stack(np.meshgrid(np.arange(25), np.arange(40)), -1).reshape(-1, 2)[:n]
           + rng.normal(0, 0.2, (n, 2)))
    raw = fcluster(linkage(pts, method="single"), t=0.6, criterion="distance")
    _, first, inverse = np.unique(raw, return_index=True, return_inverse=True)
    want = np.argsort(np.argsort(first))[inverse]
    np.testing.assert_array_equal(cluster_labels(pts, threshold_m=0.6), want)
