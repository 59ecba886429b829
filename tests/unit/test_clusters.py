"""Single-linkage clusters and their stable identities."""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from common.clusters import ClusterTracker, cluster_colour, cluster_labels

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
