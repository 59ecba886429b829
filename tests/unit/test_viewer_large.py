"""The viewer at n = 1000: what the picture shows (the overview note, a selected
cluster's and a selected feature's pairs at full detail), the scene computed once per
state however many pictures are drawn of it, and the plots' bounded samples of large maps
(every pair's size from the whole-matrix kernel; the largest and the watched pairs kept)."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from slamlens.common import overview
from slamlens.common.geometry import all_relative_covariances, pd_size_m
from slamlens.common.messages import SlamState
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.legend import OVERVIEW_COLOUR
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.scene import ROLE_PAIR
from slamlens.services.visualiser.series import (
    DENSE_PAIRS,
    KEEP_LARGEST,
    PlotSampler,
    SeriesStore,
    all_pair_sizes,
    pair_index,
)
from slamlens.services.visualiser.settings import ViewSettings
from tests.unit.test_overview import ekf_like_state, grid

RED = (0, 0, 255)


def clustered_map(clusters: int = 10, per: int = 100, seed: int = 1) -> np.ndarray:
    """``clusters`` × ``per`` features: tight square patches (0.15 m apart) 6 m apart."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(per)))
    patch = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:per]
    centres = np.stack(np.meshgrid(np.arange(5), np.arange(2)), -1).reshape(-1, 2)[:clusters]
    xy = np.concatenate([c * 6.0 + patch * 0.15 for c in centres])
    return xy + rng.normal(0, 0.005, xy.shape)


@pytest.fixture(scope="module")
def grid_state() -> SlamState:
    """n = 1000 on a 1 m grid: ~1000 singleton clusters at the 0.6 m cut."""
    return ekf_like_state(grid(1000, spacing=1.0), seed=2)


@pytest.fixture(scope="module")
def clustered_state() -> SlamState:
    return ekf_like_state(clustered_map(), seed=3)


def colour_pixels(image: np.ndarray, bgr: tuple[int, int, int], tol: int = 40) -> np.ndarray:
    diff = np.abs(image.astype(int) - np.array(bgr)).max(axis=2)
    return diff <= tol


def test_all_pairs_at_n_1000_become_the_overview_with_its_note(grid_state) -> None:
    renderer = Renderer()
    settings = ViewSettings()  # "all", budget 2000
    camera = CameraModel.top_down(bounds_xy=(-1, -1, 33, 33))
    picture = renderer.render(None, state=grid_state, camera=camera, settings=settings)
    note = renderer.overview_note(settings)
    assert note.startswith("499 500 pairs > budget 2 000: min/mean/max per pair of ")
    assert "map tiles of" in note and note.endswith("select a feature or a cluster for all "
                                                   "its pairs")
    scene = renderer.scene(grid_state, settings)
    tiles = len(np.unique(scene.cluster_ids))
    assert 2 <= tiles <= overview.MAX_GROUPS
    assert len(scene.glyph_role) == 3 * tiles * (tiles - 1) // 2  # min, mean, max per pair
    assert scene.mode == "minmeanmax" and scene.tile_m is not None
    # the note is written in the legend, in its colour, and glyphs are drawn in red
    assert colour_pixels(picture[:260], OVERVIEW_COLOUR, tol=30).sum() > 100
    assert colour_pixels(picture, RED, tol=60).sum() > 50


def test_a_selected_cluster_at_n_1000_shows_all_its_pairs(clustered_state) -> None:
    renderer = Renderer()
    camera = CameraModel.top_down(bounds_xy=(-1, -1, 27, 9))
    base = ViewSettings()
    ids = renderer.cluster_ids(clustered_state, base)
    assert len(np.unique(ids)) == 10
    chosen = int(ids[350])  # the fourth patch
    settings = base.replace(selected_cluster=chosen)
    picture = renderer.render(None, state=clustered_state, camera=camera, settings=settings)
    scene = renderer.scene(clustered_state, settings)
    members = np.flatnonzero(ids == chosen)
    assert len(members) == 100
    assert len(scene.glyph_role) == 100 * 99 // 2 and np.all(scene.glyph_role == ROLE_PAIR)
    member_ids = set(clustered_state.landmark_ids[members].tolist())
    assert set(scene.glyph_ids.reshape(-1).tolist()) == member_ids
    assert renderer.overview_note(settings) == ""  # full detail, nothing left out
    # red glyphs (shaded: reddish) over the selected patch, none over the other patches
    # (6 m apart) nor anywhere else outside the legend box
    xy = clustered_state.landmarks
    b, g, r = (picture[..., k].astype(int) for k in range(3))
    red = (r > g + 40) & (r > b + 40)
    red[:160, :480] = False  # the legend's swatches
    lo, hi = xy[members].min(axis=0) - 2.0, xy[members].max(axis=0) + 2.0
    corners, _ = camera.project(np.array([[lo[0], lo[1], 0], [hi[0], hi[1], 0]]))
    (u0, v1), (u1, v0) = corners.astype(int)
    inside = int(red[v0:v1, u0:u1].sum())
    assert inside > 3000
    assert int(red.sum()) == inside


def test_a_selected_feature_at_n_1000_shows_its_999_pairs(grid_state) -> None:
    renderer = Renderer()
    settings = ViewSettings(selected_feature=int(grid_state.landmark_ids[500]))
    camera = CameraModel.top_down(bounds_xy=(-1, -1, 33, 33))
    renderer.render(None, state=grid_state, camera=camera, settings=settings)
    scene = renderer.scene(grid_state, settings)
    assert len(scene.glyph_role) == 999 and np.all(scene.glyph_role == ROLE_PAIR)
    assert np.all((scene.glyph_ids == settings.selected_feature).any(axis=1))
    # the glyphs are the pairs' own P_d, float64, as all pairs would give them
    i = 500
    others = np.delete(np.arange(1000), i)
    _, _, Pd = all_relative_covariances(grid_state.covariance, 1000)
    first, second = np.minimum(i, others), np.maximum(i, others)
    rows = first * (2 * 1000 - first - 1) // 2 + (second - first - 1)
    np.testing.assert_allclose(np.sort(scene.glyph_size), np.sort(pd_size_m(Pd[rows])),
                               rtol=1e-12)


def test_the_scene_is_computed_once_per_state_not_per_camera_frame(clustered_state) -> None:
    renderer = Renderer()
    camera = CameraModel.top_down(bounds_xy=(-1, -1, 27, 9))
    settings = ViewSettings(mode="minmeanmax")
    frames = [np.full((720, 1280, 3), v, np.uint8) for v in (60, 90, 120)]
    pictures = [renderer.render(f, state=clustered_state, camera=camera, settings=settings)
                for f in frames]
    assert renderer.scenes_built == 1  # three camera frames, one state: one scene
    # each picture is what a fresh renderer draws over that frame
    for frame, picture in zip(frames, pictures, strict=True):
        fresh = Renderer().render(frame, state=clustered_state, camera=camera,
                                  settings=settings)
        np.testing.assert_array_equal(picture, fresh)
    # another view's settings: its own scene; a new state: the scenes again
    renderer.render(frames[0], state=clustered_state, camera=camera,
                    settings=settings.replace(mode="all"))
    assert renderer.scenes_built == 2
    newer = ekf_like_state(clustered_map(), seed=4)
    renderer.render(frames[0], state=newer, camera=camera, settings=settings)
    assert renderer.scenes_built == 3
    # cluster ids stay those of the same clusters across states
    np.testing.assert_array_equal(renderer.cluster_ids(newer, settings),
                                  renderer.cluster_ids(clustered_state, settings))


def test_a_prepared_state_is_drawn_without_a_scene_and_the_previous_keeps_its_own(
        clustered_state) -> None:
    """The viewer prepares the next state's scene (``viewer-prepare``) while the render
    thread still draws the previous one over new camera frames: both stay cached."""
    renderer = Renderer()
    camera = CameraModel.top_down(bounds_xy=(-1, -1, 27, 9))
    settings = ViewSettings()
    frame = np.full((720, 1280, 3), 70, np.uint8)
    renderer.render(frame, state=clustered_state, camera=camera, settings=settings)
    newer = dataclasses.replace(clustered_state, seq=clustered_state.seq + 1)
    prepared = threading.Thread(target=renderer.prepare, args=(newer, settings))
    prepared.start()
    prepared.join()
    assert renderer.scenes_built == 2
    renderer.render(frame, state=clustered_state, camera=camera, settings=settings)
    picture = renderer.render(frame, state=newer, camera=camera, settings=settings)
    assert renderer.scenes_built == 2  # neither computed again
    np.testing.assert_array_equal(picture, Renderer().render(
        frame, state=newer, camera=camera, settings=settings))


# -- plots of large maps ---------------------------------------------------------------
def wide_state(n: int, *, seq: int = 1, seed: int = 0) -> SlamState:
    """n features spread over 20 m × 20 m (mostly singleton clusters)."""
    state = ekf_like_state(np.random.default_rng(seed).uniform(0, 20, (n, 2)), seed=seed)
    return dataclasses.replace(state, seq=seq, stamp=0.1 * seq)


def test_all_pair_sizes_equal_the_per_pair_oracle() -> None:
    state = ekf_like_state(grid(230, spacing=0.5), seed=5)
    want = pd_size_m(all_relative_covariances(state.covariance, state.n)[2])
    got = all_pair_sizes(np.asarray(state.covariance), state.n, chunk=64)
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-4)


def test_a_large_maps_samples_keep_the_largest_and_the_watched_pairs() -> None:
    n = 210  # 21 945 pairs: above DENSE_PAIRS
    assert n * (n - 1) // 2 > DENSE_PAIRS
    store = SeriesStore(min_interval_s=0.0)
    first = wide_state(n, seq=1, seed=6)
    assert store.add_state(first, now=0.0)
    ids, sizes = store.latest_sizes()  # type: ignore[misc]
    assert len(sizes) == n * (n - 1) // 2  # the newest sample ranks every pair
    want = pd_size_m(all_relative_covariances(first.covariance, n)[2])
    np.testing.assert_allclose(sizes, want, rtol=1e-4)
    # the biggest pair's plot has its value; a small pair's has none (not kept) ...
    biggest = store.default_pairs(limit=1)[0]
    k_small = int(np.argmin(want))
    small_i, small_j = np.triu_indices(n, k=1)
    small = (int(ids[small_i[k_small]]), int(ids[small_j[k_small]]))
    data = store.to_json([biggest, small])
    assert data["pairs"][0]["values"][0] == pytest.approx(float(want.max()), rel=1e-4)
    assert data["pairs"][1]["values"] == [None]
    # ... until it is plotted: from the next sample on it is kept too
    second = wide_state(n, seq=2, seed=6)
    assert store.add_state(second, now=store.interval_s)
    values = store.to_json([small])["pairs"][0]["values"]
    assert values[0] is None and values[1] == pytest.approx(
        float(want[pair_index(small_i[k_small], small_j[k_small], n)]), rel=1e-4)
    sample = store._states[-1]
    assert sample.kept is not None and KEEP_LARGEST <= len(sample.kept) <= KEEP_LARGEST + 2
    # large maps are paced by their own cost
    assert store.interval_s > 0.0


def test_the_plot_sampler_samples_the_newest_state_off_the_calling_thread() -> None:
    n = 210
    store = SeriesStore(min_interval_s=0.0)
    errors: list[Exception] = []
    sampler = PlotSampler(lambda _s, exc: errors.append(exc))
    threads: list[str] = []
    real_add = store.add_state

    def add(state: SlamState, *, now: float) -> bool:
        threads.append(threading.current_thread().name)
        return real_add(state, now=now)

    store.add_state = add  # type: ignore[method-assign]
    sampler.start()
    try:
        sampler.offer(store, wide_state(n, seq=1, seed=7), 0.0)
        assert sampler.sampled_event.wait(30.0)
        assert sampler.sampled == 1 and threads == ["viewer-plots"] and not errors
        assert store.to_json([])["state"]["seq"] == [1]
    finally:
        sampler.stop()
