"""The viewer's side of the summary stream (services/visualiser/summary_view.py)."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.messages import SlamState, StateSummary
from slamlens.common.summary import Summariser, parse_query
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.scene import ROLE_MAX, ROLE_MEAN, ROLE_MIN
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.summary_view import (
    decode_summary_state,
    summarised_state,
    summary_of,
    summary_scene,
)
from tests.unit.test_summary import consistent_state, oracle_pd


def test_the_rebuilt_state_holds_the_blocks_and_no_cross_terms() -> None:
    state = consistent_state(20)
    s = StateSummary.from_bytes(Summariser().summary(state, parse_query("what=clusters")))
    rebuilt = summarised_state(s)
    assert summary_of(rebuilt) is s and summary_of(state) is None
    P, Q = state.covariance, rebuilt.covariance
    np.testing.assert_allclose(Q[:3, :3], P[:3, :3], rtol=1e-6)
    for i in range(20):
        a = slice(3 + 2 * i, 5 + 2 * i)
        np.testing.assert_allclose(Q[a, a], P[a, a], rtol=1e-6)
    block = np.zeros_like(Q, dtype=bool)
    block[:3, :3] = True
    for i in range(20):
        block[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] = True
    assert not Q[~block].any()
    assert (rebuilt.seq, rebuilt.epoch, rebuilt.n) == (state.seq, state.epoch, 20)


def test_the_scene_is_the_robot_s_min_mean_max_not_pairs_of_the_rebuilt_matrix() -> None:
    state = consistent_state(30)
    payload = Summariser().summary(state, parse_query("what=clusters"))
    rebuilt = decode_summary_state(payload)
    s = rebuilt.summary
    assert s is not None
    scene = summary_scene(rebuilt, ViewSettings())  # "all" asked: min/mean/max drawn
    c = len(s.group_pairs)
    assert scene.mode == "minmeanmax" and len(scene.glyph_role) == 3 * c
    assert list(scene.glyph_role) == [ROLE_MIN] * c + [ROLE_MEAN] * c + [ROLE_MAX] * c
    assert "full state" in scene.overview  # says what the summary cannot show
    ids = state.landmark_ids
    for k, (i, j) in enumerate(s.max_pair.tolist()):
        assert tuple(scene.glyph_ids[2 * c + k]) == (ids[i], ids[j])
        size = np.sqrt(np.linalg.eigvalsh(oracle_pd(state.covariance, i, j))[-1])
        assert scene.glyph_size[2 * c + k] == pytest.approx(size, rel=1e-5)


@pytest.mark.parametrize("n", [0, 1])
def test_a_map_without_pairs_draws(n: int) -> None:
    state = consistent_state(3)
    small = SlamState(robot="r1", seq=0, stamp=0.0, step="init", pose=np.zeros(3),
                      landmark_ids=state.landmark_ids[:n], landmarks=state.landmarks[:n],
                      covariance=state.covariance[:3 + 2 * n, :3 + 2 * n])
    rebuilt = decode_summary_state(Summariser().summary(small, parse_query("what=clusters")))
    img = Renderer().render(None, state=rebuilt, settings=ViewSettings(),
                            camera=CameraModel.top_down(bounds_xy=(-2, -2, 2, 2)))
    assert img.ndim == 3
