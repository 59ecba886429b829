"""World files: the paper scenario's geometry (docs/simulator.md) and the loader's validation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.cluster.hierarchy import fcluster, linkage

from slamlens.common.errors import ConfigError
from slamlens.services.slam.world import load_world, packaged_worlds

WORLDS = Path(__file__).parents[2] / "services" / "slam" / "worlds"

MINIMAL = """
name = "tiny"
landmarks = [[1.0, 0.5], [2.0, -0.5]]
waypoints = [[1.0, 0.0], [0.0, 0.0]]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "world.toml"
    path.write_text(text)
    return path


def test_paper_world_matches_the_papers_scenario() -> None:
    world = load_world("paper")
    assert world.name == "paper"
    assert world.n_landmarks == 15
    assert list(world.landmark_ids) == list(range(1, 16))
    # all landmarks inside a 3 m x 3 m area that contains the loop (paper §4)
    lo, hi = world.landmarks_xy.min(axis=0), world.landmarks_xy.max(axis=0)
    assert np.all(hi - lo <= 3.0)
    assert np.all(world.landmarks_xy >= -1.0) and np.all(world.landmarks_xy <= 2.0)
    assert np.allclose(world.area_max_xy - world.area_min_xy, [3.0, 3.0])
    # a 1 m x 1 m square loop starting and ending at the map origin
    corners = np.vstack([[0.0, 0.0], world.waypoints_xy])
    sides = np.hypot(*np.diff(corners, axis=0).T)
    assert np.allclose(sides, 1.0)
    assert np.allclose(world.waypoints_xy[-1], [0.0, 0.0])
    assert np.allclose(world.start_pose, [0.0, 0.0, 0.0])
    # forward sensor: 180° and a limited range; the agreed noise defaults
    assert math.isclose(world.sensor.fov_rad, math.pi, rel_tol=1e-9)
    assert 1.5 <= world.sensor.max_range_m <= 2.0
    assert (world.noise.sigma_v, world.noise.sigma_w, world.noise.sigma_range,
            world.noise.sigma_bearing) == (0.05, 0.05, 0.05, 0.02)
    assert world.loops == 3


@pytest.mark.parametrize("threshold_m", [0.5, 0.65, 0.8])
def test_paper_landmarks_form_three_clusters_of_five(threshold_m: float) -> None:
    world = load_world("paper")
    labels = fcluster(linkage(world.landmarks_xy, method="single"), t=threshold_m,
                      criterion="distance")
    assert sorted(np.bincount(labels)[1:]) == [5, 5, 5]
    # clusters are contiguous id blocks 1-5, 6-10, 11-15
    for block in range(3):
        assert len(set(labels[5 * block:5 * block + 5])) == 1


def test_load_by_path_equals_load_by_name() -> None:
    assert load_world(WORLDS / "paper.toml") == load_world("paper")
    assert load_world(str(WORLDS / "grid.toml")) == load_world("grid")
    assert load_world("paper") != load_world("grid")
    assert set(packaged_worlds()) >= {"paper", "grid"}


def test_world_arrays_are_read_only() -> None:
    world = load_world("paper")
    with pytest.raises(ValueError):
        world.landmarks_xy[0, 0] = 9.0
    with pytest.raises(ValueError):
        world.landmark_ids[0] = 9


def test_minimal_file_gets_documented_defaults(tmp_path: Path) -> None:
    world = load_world(write(tmp_path, MINIMAL))
    assert list(world.landmark_ids) == [1, 2]  # ids default to 1..n
    assert np.allclose(world.landmarks_xy, [[1.0, 0.5], [2.0, -0.5]])
    assert world.sensor.period_s == 0.1 and world.motion.dt_s == 0.1
    assert world.noise.sigma_bearing == 0.02
    assert world.area_min_xy is None
    assert world.loops == 3


@pytest.mark.parametrize(("snippet", "named"), [
    ('colour = "red"\n', "colour"),
    ("[sensor]\nmax_range = 2.0\n", "max_range"),
    ("[motion]\nspeed_mps = -1.0\n", "motion.speed_mps"),
    ("[sensor]\nfov_rad = 7.0\n", "sensor.fov_rad"),
    ("[noise]\nsigma_range = -0.1\n", "noise.sigma_range"),
    ("[noise]\nsigma_v = \"loud\"\n", "sigma_v"),
    ("[run]\nloops = 0\n", "run.loops"),
    ("[start]\npose = [0.0, 0.0]\n", "start.pose"),
    ("[area]\nmin_xy = [0.0, 0.0]\nmax_xy = [1.5, 1.0]\n", "landmarks"),
])
def test_bad_keys_and_values_are_rejected_naming_the_key(tmp_path: Path, snippet: str,
                                                         named: str) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        load_world(write(tmp_path, MINIMAL + snippet))


@pytest.mark.parametrize(("landmarks", "named"), [
    ("[[1.0, 2.0, 3.0, 4.0]]", "landmarks"),
    ("[[1, 1.0, 2.0], [1, 2.0, 3.0]]", "distinct"),
    ("[[-3, 1.0, 2.0]]", "non-negative"),
    ("[[1.5, 1.0, 2.0]]", "integers"),
    ("[]", "landmarks"),
    ('[["a", 1.0]]', "landmarks"),
])
def test_bad_landmark_tables_are_rejected(tmp_path: Path, landmarks: str, named: str) -> None:
    text = f'name = "bad"\nlandmarks = {landmarks}\nwaypoints = [[1.0, 0.0]]\n'
    with pytest.raises(ConfigError, match=named):
        load_world(write(tmp_path, text))


def test_unknown_world_and_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="paper"):  # lists what exists
        load_world("no_such_world")
    with pytest.raises(ConfigError, match="cannot read"):
        load_world(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_world(write(tmp_path, "name = \n"))


# -- generated maps ([landmark_grid]; the "large" world) ---------------------

GRID = """
name = "gen"
waypoints = [[1.0, 0.0], [0.0, 0.0]]
[landmark_grid]
rows = 3
columns = 4
spacing_m = 0.5
origin_xy = [1.0, -1.0]
jitter_m = 0.1
seed = 7
"""


def test_large_world_has_1000_distinct_landmarks_inside_its_area() -> None:
    world = load_world("large")
    assert "large" in packaged_worlds()
    assert world.n_landmarks == 1000
    assert list(world.landmark_ids) == list(range(1, 1001))
    xy = world.landmarks_xy
    assert len({(float(x), float(y)) for x, y in xy}) == 1000
    assert np.all(xy >= world.area_min_xy) and np.all(xy <= world.area_max_xy)
    # each landmark stays within the jitter of its own 1 m grid point (25 rows x 40 columns)
    row, column = np.divmod(np.arange(1000), 40)
    grid = np.column_stack([column, row]) - 1.0
    assert np.all(np.abs(xy - grid) <= 0.2)
    gaps = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() >= 1.0 - 2 * 0.2  # distinct, and never closer than spacing − 2·jitter
    assert world.landmarks_xy.flags.writeable is False


def test_generated_map_is_deterministic_per_seed(tmp_path: Path) -> None:
    first, again = load_world(write(tmp_path, GRID)), load_world(write(tmp_path, GRID))
    assert first == again
    other = load_world(write(tmp_path, GRID.replace("seed = 7", "seed = 8")))
    assert not np.array_equal(first.landmarks_xy, other.landmarks_xy)
    assert np.array_equal(first.landmark_ids, other.landmark_ids)
    # ids row by row from the lower left, first_id 1 by default
    assert list(first.landmark_ids) == list(range(1, 13))
    row, column = np.divmod(np.arange(12), 4)
    assert np.all(np.abs(first.landmarks_xy - (np.column_stack([column, row]) * 0.5
                                               + [1.0, -1.0])) <= 0.1)
    no_jitter = load_world(write(tmp_path, GRID.replace("jitter_m = 0.1", "jitter_m = 0.0")))
    assert np.array_equal(no_jitter.landmarks_xy, np.column_stack([column, row]) * 0.5
                          + [1.0, -1.0])
    shifted = load_world(write(tmp_path, GRID + "first_id = 100\n"))
    assert list(shifted.landmark_ids) == list(range(100, 112))


@pytest.mark.parametrize(("change", "named"), [
    (("rows = 3", "rows = 0"), "landmark_grid.rows"),
    (("columns = 4", ""), "landmark_grid.columns"),
    (("columns = 4", "columns = 4.5"), "columns"),
    (("spacing_m = 0.5", "spacing_m = -1.0"), "landmark_grid.spacing_m"),
    (("jitter_m = 0.1", "jitter_m = 0.25"), "landmark_grid.jitter_m"),
    (("jitter_m = 0.1", "jitter_m = -0.1"), "landmark_grid.jitter_m"),
    (("origin_xy = [1.0, -1.0]", "origin_xy = [1.0]"), "landmark_grid.origin_xy"),
    (("seed = 7", "seed = -1"), "landmark_grid.seed"),
    (("seed = 7", "colour = 3"), "colour"),
    (("rows = 3", "rows = 400"), "at most"),
])
def test_bad_landmark_grids_are_rejected_naming_the_key(tmp_path: Path, change: tuple[str, str],
                                                        named: str) -> None:
    text = GRID.replace(*change)
    if "400" in change[1]:
        text = text.replace("columns = 4", "columns = 400")
    with pytest.raises(ConfigError, match=named):
        load_world(write(tmp_path, text))


def test_landmark_grid_and_a_landmark_list_are_exclusive(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="either 'landmarks' or \\[landmark_grid\\]"):
        load_world(write(tmp_path, 'landmarks = [[1.0, 2.0]]\n' + GRID))
    with pytest.raises(ConfigError, match="must be a table"):
        load_world(write(tmp_path, GRID.split("[landmark_grid]")[0].replace(
            'name = "gen"', 'name = "gen"\nlandmark_grid = 3')))
    with pytest.raises(ConfigError, match="outside the area"):
        load_world(write(tmp_path, GRID + "[area]\nmin_xy = [0.0, 0.0]\nmax_xy = [3.0, 3.0]\n"))
