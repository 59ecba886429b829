"""scene.py on a hand-made covariance: which pairs, which min/mean/max, where glyphs go."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.errors import RenderError
from slamlens.common.geometry import relative_covariance
from slamlens.common.messages import SlamState
from slamlens.services.visualiser.glyphs import eig_sym2
from slamlens.services.visualiser.scene import (
    ROLE_MAX,
    ROLE_MEAN,
    ROLE_MIN,
    build_scene,
    min_mean_max,
    pair_size,
    select_pairs,
)
from slamlens.services.visualiser.settings import ViewSettings

IDS = np.array([10, 20, 30, 40])
XY = np.array([[0.0, 0.0], [0.2, 0.0], [2.0, 0.0], [2.2, 0.0]])  # clusters {10,20}, {30,40}
CLUSTERS = np.array([0, 0, 1, 1])


def hand_state() -> SlamState:
    """P_ii = d_i·I and chosen cross blocks, so every P_d is known by hand.

    Inter-cluster P_d: (10,30) = 0.02·I (smallest), (20,30) = 0.04·I,
    (10,40) = 0.05·I − [[0, .008], [.008, 0]], (20,40) = 0.06·I (largest).
    """
    n = 4
    P = np.zeros((3 + 2 * n, 3 + 2 * n))
    P[:3, :3] = np.diag([0.01, 0.01, 0.001])
    d = [0.01, 0.02, 0.03, 0.04]
    for i in range(n):
        P[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] = d[i] * np.eye(2)
    cross = {(0, 2): 0.01 * np.eye(2), (1, 2): 0.005 * np.eye(2),
             (0, 3): np.array([[0.0, 0.004], [0.004, 0.0]]), (0, 1): 0.012 * np.eye(2),
             (2, 3): 0.03 * np.eye(2)}
    for (i, j), block in cross.items():
        P[3 + 2 * i:5 + 2 * i, 3 + 2 * j:5 + 2 * j] = block
        P[3 + 2 * j:5 + 2 * j, 3 + 2 * i:5 + 2 * i] = block.T
    return SlamState(robot="r", seq=3, stamp=1.0, step="update", pose=[0.0, 0.0, 0.0],
                     landmark_ids=IDS, landmarks=XY, covariance=P)


def test_hand_made_relative_covariances_are_what_the_docstring_says() -> None:
    P = hand_state().covariance
    np.testing.assert_allclose(relative_covariance(P, 0, 2), 0.02 * np.eye(2))
    np.testing.assert_allclose(relative_covariance(P, 1, 3), 0.06 * np.eye(2))
    np.testing.assert_allclose(relative_covariance(P, 0, 3),
                               [[0.05, -0.008], [-0.008, 0.05]])


def test_select_pairs_per_mode_and_selection() -> None:
    ii, jj = select_pairs(4, mode="all")
    assert list(zip(ii.tolist(), jj.tolist(), strict=True)) == [
        (0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    ii, jj = select_pairs(4, mode="inter", cluster_ids=CLUSTERS)
    assert list(zip(ii.tolist(), jj.tolist(), strict=True)) == [(0, 2), (0, 3), (1, 2), (1, 3)]
    ii, jj = select_pairs(4, mode="all", selected_index=1)
    assert list(zip(ii.tolist(), jj.tolist(), strict=True)) == [(0, 1), (1, 2), (1, 3)]
    ii, jj = select_pairs(4, mode="inter", cluster_ids=CLUSTERS, selected_index=1)
    assert list(zip(ii.tolist(), jj.tolist(), strict=True)) == [(1, 2), (1, 3)]
    with pytest.raises(RenderError, match="needs cluster ids"):
        select_pairs(4, mode="inter")


def test_min_mean_max_picks_the_right_pairs() -> None:
    P = hand_state().covariance
    ii, jj = select_pairs(4, mode="inter", cluster_ids=CLUSTERS)
    Pd = np.array([relative_covariance(P, i, j) for i, j in zip(ii, jj, strict=True)])
    stats = min_mean_max(ii, jj, Pd, CLUSTERS)
    assert stats.clusters.tolist() == [[0, 1]] and stats.count.tolist() == [4]
    assert (ii[stats.min_pair[0]], jj[stats.min_pair[0]]) == (0, 2)
    assert (ii[stats.max_pair[0]], jj[stats.max_pair[0]]) == (1, 3)
    expected_mean = (0.02 * np.eye(2) + np.array([[0.05, -0.008], [-0.008, 0.05]])
                     + 0.04 * np.eye(2) + 0.06 * np.eye(2)) / 4
    np.testing.assert_allclose(stats.mean_Pd[0], expected_mean)


def test_min_mean_max_orders_by_size_on_random_groups() -> None:
    rng = np.random.default_rng(9)
    n = 12
    clusters = rng.integers(0, 4, n)
    ii, jj = np.triu_indices(n, 1)
    A = rng.normal(size=(len(ii), 2, 2))
    Pd = A @ A.transpose(0, 2, 1)
    stats = min_mean_max(ii, jj, Pd, clusters)
    size = pair_size(Pd)
    for row, (a, b) in enumerate(stats.clusters.tolist()):
        members = np.flatnonzero(np.minimum(clusters[ii], clusters[jj]) == a)
        members = members[np.maximum(clusters[ii[members]], clusters[jj[members]]) == b]
        assert a < b and len(members) == stats.count[row]
        assert size[stats.min_pair[row]] == size[members].min()
        assert size[stats.max_pair[row]] == size[members].max()
        np.testing.assert_allclose(stats.mean_Pd[row], Pd[members].mean(axis=0))


def test_size_is_the_major_sigma_and_never_grows_when_a_covariance_shrinks() -> None:
    rng = np.random.default_rng(2)
    A, B = rng.normal(size=(2, 100, 2, 2))
    small = A @ A.transpose(0, 2, 1)
    big = small + B @ B.transpose(0, 2, 1)  # big ≽ small in the Loewner order
    np.testing.assert_allclose(pair_size(small), np.sqrt(np.linalg.eigvalsh(small)[:, 1]))
    assert np.all(pair_size(small) <= pair_size(big) + 1e-12)


def test_all_mode_puts_one_glyph_per_pair_at_its_midpoint() -> None:
    state = hand_state()
    scene = build_scene(state, ViewSettings(sigma_k=3.0))
    assert scene.mode == "all" and len(scene.glyphs) == 6 and len(scene.lines_xy) == 6
    for k, (a, b) in enumerate(scene.glyph_ids.tolist()):
        i, j = int(np.flatnonzero(IDS == a)[0]), int(np.flatnonzero(IDS == b)[0])
        np.testing.assert_allclose(scene.glyphs.centres[k], [*(XY[i] + XY[j]) / 2, 0.0])
        np.testing.assert_allclose(scene.lines_xy[k], [XY[i], XY[j]])
        Pd = relative_covariance(state.covariance, i, j)
        lam = np.linalg.eigvalsh(Pd)
        assert scene.glyphs.a[k] == pytest.approx(3.0 * np.sqrt(lam[1]))
        assert scene.glyphs.b[k] == pytest.approx(3.0 * np.sqrt(lam[0]))
        assert scene.glyph_size[k] == pytest.approx(np.sqrt(lam[1]))


def test_inter_mode_hides_intra_cluster_pairs() -> None:
    scene = build_scene(hand_state(), ViewSettings(mode="inter"), cluster_ids=CLUSTERS)
    assert sorted(map(tuple, scene.glyph_ids.tolist())) == [(10, 30), (10, 40), (20, 30),
                                                             (20, 40)]
    assert np.all(scene.glyph_clusters[:, 0] != scene.glyph_clusters[:, 1])


def test_minmeanmax_places_min_below_before_and_max_above_after_the_mean() -> None:
    settings = ViewSettings(mode="minmeanmax", minmeanmax_spread=0.15)
    scene = build_scene(hand_state(), settings, cluster_ids=CLUSTERS)
    assert scene.glyph_role.tolist() == [ROLE_MIN, ROLE_MEAN, ROLE_MAX]
    assert scene.glyph_ids.tolist() == [[10, 30], [-1, -1], [20, 40]]
    np.testing.assert_allclose(scene.lines_xy[0], [[0.1, 0.0], [2.1, 0.0]])  # centroids
    x = scene.glyphs.centres[:, 0]
    np.testing.assert_allclose(x, [0.1 + 2.0 * 0.35, 1.1, 0.1 + 2.0 * 0.65])
    z, h = scene.glyphs.centres[:, 2], scene.glyphs.h
    assert z[1] == 0.0
    assert z[0] == pytest.approx(-(h[1] + h[0]))  # hangs just below the mean
    assert z[2] == pytest.approx(h[1] + h[2])  # rests just on top of it
    # sizes √λmax: min 0.02·I, mean 0.0425·I − [[0, .002], [.002, 0]] (λmax 0.0445), max 0.06·I
    assert scene.glyph_size.tolist() == pytest.approx(np.sqrt([0.02, 0.0445, 0.06]).tolist())
    lam1, lam2, _ = eig_sym2(np.array([0.0425 * np.eye(2) - np.array([[0, .002], [.002, 0]])]))
    assert scene.glyphs.a[1] == pytest.approx(2.0 * np.sqrt(lam1[0]))


def test_violations_are_flagged_on_the_glyphs_showing_them() -> None:
    state = hand_state()
    bad = frozenset({(10, 40)})
    scene = build_scene(state, ViewSettings(), violating_pairs=bad)
    flagged = scene.glyph_ids[scene.glyph_violation].tolist()
    assert flagged == [[10, 40]] and scene.line_violation.sum() == 1
    mmm = build_scene(state, ViewSettings(mode="minmeanmax"), cluster_ids=CLUSTERS,
                      violating_pairs=bad)
    # (10, 40) is neither the min nor the max pair, but it is in the mean and on the line
    assert mmm.glyph_violation.tolist() == [False, True, False]
    assert mmm.line_violation.tolist() == [True]
    worst = build_scene(state, ViewSettings(mode="minmeanmax"), cluster_ids=CLUSTERS,
                        violating_pairs=frozenset({(20, 40)}))
    assert worst.glyph_violation.tolist() == [False, True, True]


def test_selection_shows_only_the_features_pairs_in_every_mode() -> None:
    state = hand_state()
    for mode in ("all", "minmeanmax"):
        scene = build_scene(state, ViewSettings(mode=mode, selected_feature=30),
                            cluster_ids=CLUSTERS)
        assert scene.mode == "all"
        assert sorted(map(tuple, scene.glyph_ids.tolist())) == [(10, 30), (20, 30), (30, 40)]
    inter = build_scene(state, ViewSettings(mode="inter", selected_feature=30),
                        cluster_ids=CLUSTERS)
    assert sorted(map(tuple, inter.glyph_ids.tolist())) == [(10, 30), (20, 30)]
    missing = build_scene(state, ViewSettings(selected_feature=99))
    assert missing.selected_missing and len(missing.glyphs) == 0


def test_maps_with_fewer_than_two_features_have_no_pairs() -> None:
    one = SlamState(robot="r", seq=0, stamp=0.0, step="update", pose=[0, 0, 0],
                    landmark_ids=[5], landmarks=[[1.0, 1.0]], covariance=np.eye(5) * 0.01)
    for mode in ("all", "inter", "minmeanmax"):
        scene = build_scene(one, ViewSettings(mode=mode), cluster_ids=np.zeros(1, np.int64))
        assert len(scene.glyphs) == 0 and len(scene.lines_xy) == 0
