"""Large maps within a glyph budget (common/overview.py, scene.plan_overview):
the overview's min / mean / max against a brute-force oracle, the budget rule, map tiles,
and full detail for a selected feature or cluster."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common import overview
from slamlens.common.geometry import all_relative_covariances, pd_size_m
from slamlens.common.messages import SlamState
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.scene import ROLE_PAIR, build_scene, min_mean_max, plan_overview
from slamlens.services.visualiser.settings import ViewSettings


def ekf_like_state(xy: np.ndarray, *, seed: int = 0) -> SlamState:
    """A covariance like an EKF's after a few loops: a common part plus a random
    anisotropic block per feature and small random correlations (PSD by construction)."""
    rng = np.random.default_rng(seed)
    n = len(xy)
    N = 3 + 2 * n
    A = rng.normal(0, 0.01, (N, N // 3 + 2))
    P = A @ A.T + np.diag(rng.uniform(1e-5, 4e-4, N))
    P[3:, 3:] += np.kron(np.ones((n, n)), 0.02 ** 2 * np.eye(2))
    return SlamState(robot="big", seq=3, stamp=0.3, step="update", pose=[0.0, 0.0, 0.0],
                     landmark_ids=np.arange(100, 100 + n), landmarks=xy, covariance=P)


def grid(n: int, spacing: float = 1.0, seed: int = 0) -> np.ndarray:
    side = int(np.ceil(np.sqrt(n)))
    cells = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n]
    return cells * spacing + np.random.default_rng(seed).normal(0, 0.05, (n, 2))


@pytest.mark.parametrize("seed", range(6))
def test_group_min_mean_max_equals_the_brute_force_over_all_pairs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 90))
    state = ekf_like_state(rng.uniform(0, 5, (n, 2)), seed=seed)
    groups = rng.integers(0, int(rng.integers(2, 9)), n) * 5 + 11  # arbitrary ids
    ii, jj, Pd = all_relative_covariances(state.covariance, n)
    ref = min_mean_max(ii, jj, Pd, groups)
    fast = overview.group_min_mean_max(state.covariance, groups)
    np.testing.assert_array_equal(fast.groups, ref.clusters)
    np.testing.assert_array_equal(fast.count, ref.count)
    sizes = pd_size_m(Pd)
    ref_min, ref_max = sizes[ref.min_pair], sizes[ref.max_pair]
    got_min = pd_size_m(overview.pair_relative_covariances(state.covariance, *fast.min_pair.T))
    got_max = pd_size_m(overview.pair_relative_covariances(state.covariance, *fast.max_pair.T))
    # the same pairs, or (float32 ranking) one of the same size to 1e-5
    np.testing.assert_allclose(got_min, ref_min, rtol=1e-5)
    np.testing.assert_allclose(got_max, ref_max, rtol=1e-5)
    np.testing.assert_allclose(fast.mean_Pd, ref.mean_Pd, rtol=1e-4,
                               atol=1e-6 * np.abs(ref.mean_Pd).max())
    assert np.all(fast.min_pair[:, 0] < fast.min_pair[:, 1])


def test_pairs_of_a_few_indices_equal_those_of_all_pairs_bit_for_bit() -> None:
    state = ekf_like_state(np.random.default_rng(1).uniform(0, 3, (30, 2)))
    ii, jj, Pd = all_relative_covariances(state.covariance, 30)
    pick = np.array([0, 17, 200, 434])
    np.testing.assert_array_equal(
        overview.pair_relative_covariances(state.covariance, ii[pick], jj[pick]), Pd[pick])


def test_the_budget_rule() -> None:
    assert overview.max_groups(2000) == overview.MAX_GROUPS == 12
    assert overview.max_groups(30) == 5 and overview.overview_glyphs(5) == 30
    assert overview.max_groups(29) == 4
    assert overview.pair_count(10) == 45
    assert overview.pair_count(6, np.array([0, 0, 0, 1, 1, 1]), inter=True) == 9
    clustered = ekf_like_state(np.concatenate([c + np.random.default_rng(2).normal(
        0, 0.1, (20, 2)) for c in ([0, 0], [5, 0], [0, 5])]))
    renderer = Renderer()
    settings = ViewSettings(glyph_budget=500)  # 1770 pairs at n = 60
    ids = renderer.cluster_ids(clustered, settings)
    plan = plan_overview(clustered, settings, ids)
    assert plan is not None and "1 770 pairs > budget 500" in plan.note
    assert "3 clusters" in plan.note and plan.tile_m is None
    scene = build_scene(clustered, settings, cluster_ids=ids, plan=plan)
    assert scene.mode == "minmeanmax" and len(scene.glyph_role) == 9  # 3 cluster pairs
    assert scene.overview == plan.note
    # within the budget, or a selection, or no budget: pair by pair as before
    for within in (ViewSettings(glyph_budget=2000), ViewSettings(glyph_budget=0),
                   settings.replace(selected_feature=105),
                   settings.replace(selected_cluster=int(ids[0]))):
        assert plan_overview(clustered, within, ids) is None
    # minmeanmax itself over its budget (many clusters) goes to tiles
    many = ekf_like_state(grid(100, spacing=1.0))
    many_ids = renderer.cluster_ids(many, ViewSettings(mode="minmeanmax"))
    assert len(np.unique(many_ids)) == 100
    plan = plan_overview(many, ViewSettings(mode="minmeanmax"), many_ids)
    assert plan is not None and plan.tile_m is not None
    assert len(np.unique(plan.groups)) <= overview.MAX_GROUPS


def test_map_tiles_keep_their_ids_as_the_map_grows() -> None:
    xy = grid(1000, spacing=1.0)
    small, side_small = overview.tile_groups(xy[:400], 2000)
    large, side_large = overview.tile_groups(xy, 2000)
    assert len(np.unique(large)) <= overview.MAX_GROUPS
    if side_small == side_large:
        np.testing.assert_array_equal(small, large[:400])
    same_side, _ = overview.tile_groups(xy, 2000)
    np.testing.assert_array_equal(same_side, large)  # deterministic


def test_a_selected_feature_or_cluster_shows_all_its_pairs_at_full_detail() -> None:
    state = ekf_like_state(grid(400, spacing=0.3))  # one big cluster at the 0.6 m cut
    renderer = Renderer()
    camera = CameraModel.top_down(bounds_xy=(-1, -1, 7, 7))
    budget = ViewSettings(glyph_budget=100)
    ids = renderer.cluster_ids(state, budget)
    feature = build_scene(state, budget.replace(selected_feature=150), cluster_ids=ids)
    assert len(feature.glyph_role) == 399 and np.all(feature.glyph_role == ROLE_PAIR)
    assert np.all((feature.glyph_ids == 150).any(axis=1))
    one = int(ids[0])
    members = int(np.sum(ids == one))
    cluster = build_scene(state, budget.replace(selected_cluster=one, glyph_budget=0),
                          cluster_ids=ids)
    assert len(cluster.glyph_role) == members * (members - 1) // 2
    capped = build_scene(state, budget.replace(selected_cluster=one), cluster_ids=ids)
    assert len(capped.glyph_role) == overview.SELECTED_CAP * 100 < members * (members - 1) // 2
    assert "largest" in capped.overview
    # the capped pairs are the largest ones
    assert capped.glyph_size.min() >= np.sort(cluster.glyph_size)[-400:].min() - 1e-12
    # the picture says so in its legend (not drawn pair by pair)
    picture = renderer.render(None, state=state, camera=camera, settings=budget)
    assert renderer.overview_note(budget).startswith("79 800 pairs > budget 100")
    assert picture.shape == (720, 1280, 3)
