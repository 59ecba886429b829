"""Simulated worlds: landmarks, a waypoint loop, sensor, motion and noise, read from TOML.

A world file is small and documented (``worlds/paper.toml`` is the reference, docs/simulator.md)::

    name = "paper"
    landmarks = [[x, y], ...]          # or [[id, x, y], ...]; ids default to 1..n
    [landmark_grid] rows, columns, spacing_m, origin_xy, jitter_m, seed, first_id
                                       # instead of ``landmarks``: a seeded, generated grid
    waypoints = [[x, y], ...]          # a closed loop, visited in order, then again
    [start]  pose = [0.0, 0.0, 0.0]    # x m, y m, θ rad; the map frame is this pose
    [area]   min_xy = [-1, -1]  max_xy = [2, 2]   # optional: every landmark must lie inside
    [sensor] max_range_m, fov_rad, period_s
    [motion] speed_mps, dt_s, waypoint_tolerance_m, max_turn_rate, heading_gain
    [noise]  sigma_v, sigma_w, sigma_range, sigma_bearing      # standard deviations, SI
    [run]    loops

Coordinates in the file are in the world frame. :func:`load_world` accepts the name of a
packaged world ("paper", "grid", "large") or a path; unknown keys and bad values raise
:class:`~slamlens.common.errors.ConfigError` naming the key.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from slamlens.common.arrays import frozen_array, values_equal
from slamlens.common.config import settings_from_mapping
from slamlens.common.errors import ConfigError


@dataclass(frozen=True, kw_only=True)
class SensorModel:
    """Forward range-bearing sensor: what is seen and how often."""

    max_range_m: float = 1.6  #: landmarks farther than this (true range) are not seen, m
    fov_rad: float = math.pi  #: full field of view; seen when |true bearing| ≤ fov/2, rad
    period_s: float = 0.1  #: time between observation batches, s


@dataclass(frozen=True, kw_only=True)
class MotionModel:
    """Unicycle driven by a waypoint-following controller."""

    speed_mps: float = 0.25  #: cruise speed, m/s
    dt_s: float = 0.1  #: simulation (and odometry) step, s
    waypoint_tolerance_m: float = 0.05  #: a waypoint counts as reached within this, m
    max_turn_rate: float = 1.0  #: |ω| limit of the controller, rad/s
    heading_gain: float = 2.0  #: ω = gain · heading error (then clipped), 1/s


@dataclass(frozen=True, kw_only=True)
class NoiseModel:
    """Standard deviations of the zero-mean Gaussian noises, SI units."""

    sigma_v: float = 0.05  #: odometry forward speed, m/s
    sigma_w: float = 0.05  #: odometry turn rate, rad/s
    sigma_range: float = 0.05  #: range, m
    sigma_bearing: float = 0.02  #: bearing, rad


@dataclass(frozen=True, kw_only=True)
class _Run:
    loops: int = 3


@dataclass(frozen=True, kw_only=True)
class _Start:
    pose: tuple[float, ...] = (0.0, 0.0, 0.0)


@dataclass(frozen=True, kw_only=True)
class _Area:
    min_xy: tuple[float, ...] = ()
    max_xy: tuple[float, ...] = ()


#: a generated map larger than this is refused (a typo in rows/columns, not a map)
MAX_GENERATED_LANDMARKS = 100_000


@dataclass(frozen=True, kw_only=True)
class LandmarkGrid:
    """A generated map: ``rows`` × ``columns`` landmarks ``spacing_m`` apart, each moved by
    a seeded uniform offset in [−jitter_m, jitter_m] on both axes (``seed``). Ids run from
    ``first_id`` row by row from the lower left (``origin_xy`` is that row's first grid
    point, before the jitter)."""

    rows: int = 0  #: grid rows (along y), ≥ 1
    columns: int = 0  #: grid columns (along x), ≥ 1
    spacing_m: float = 1.0  #: distance between neighbouring grid points, m
    origin_xy: tuple[float, ...] = (0.0, 0.0)  #: grid point of row 0, column 0, world frame, m
    jitter_m: float = 0.0  #: each coordinate moved by U(−jitter, jitter), m; < spacing/2
    seed: int = 0  #: seed of the jitter (numpy SeedSequence)
    first_id: int = 1  #: id of the landmark at row 0, column 0

    def generate(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids int64[n], landmarks_xy float64[n, 2]), read-only; deterministic per seed."""
        row, column = np.divmod(np.arange(self.rows * self.columns), self.columns)
        grid = np.column_stack([column, row]) * self.spacing_m + np.asarray(self.origin_xy)
        rng = np.random.default_rng(np.random.SeedSequence(self.seed))
        # jitter < spacing/2 keeps every landmark inside its own cell: distinct, and at least
        # spacing − 2·jitter from any other (data association stays unambiguous)
        offsets = rng.uniform(-self.jitter_m, self.jitter_m, size=grid.shape)
        ids = self.first_id + np.arange(grid.shape[0])
        return frozen_array(ids, "<i8"), frozen_array(grid + offsets, "<f8")


@dataclass(frozen=True, eq=False, kw_only=True)
class World:
    """A loaded world. Arrays are read-only; equality compares their contents."""

    name: str
    description: str = ""
    landmark_ids: np.ndarray  #: int64[n], distinct, ≥ 0
    landmarks_xy: np.ndarray  #: float64[n, 2], world frame, m
    waypoints_xy: np.ndarray  #: float64[m, 2], world frame, m; one loop visits all in order
    start_pose: np.ndarray  #: float64[3] (x m, y m, θ rad), world frame; defines the map frame
    area_min_xy: np.ndarray | None = None  #: float64[2] lower corner of the arena, or None
    area_max_xy: np.ndarray | None = None  #: float64[2] upper corner of the arena, or None
    sensor: SensorModel = field(default_factory=SensorModel)
    motion: MotionModel = field(default_factory=MotionModel)
    noise: NoiseModel = field(default_factory=NoiseModel)
    loops: int = 3  #: default duration, in loops of the waypoint circuit
    source: str = ""  #: where it was loaded from (for messages)

    @property
    def n_landmarks(self) -> int:
        return int(self.landmark_ids.shape[0])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, World):
            return NotImplemented
        return all(values_equal(getattr(self, name), getattr(other, name))
                   for name in self.__dataclass_fields__ if name != "source")

    __hash__ = None  # type: ignore[assignment]


_TOP_KEYS = {"name", "description", "landmarks", "landmark_grid", "waypoints",
             "start", "area", "sensor", "motion", "noise", "run"}
_POSITIVE = {
    "sensor": ("max_range_m", "fov_rad", "period_s"),
    "motion": ("speed_mps", "dt_s", "waypoint_tolerance_m", "max_turn_rate", "heading_gain"),
}


def packaged_worlds() -> list[str]:
    """Names of the worlds shipped in ``services/slam/worlds/``."""
    folder = resources.files("slamlens.services.slam") / "worlds"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_world(name_or_path: str | Path) -> World:
    """Load a packaged world by name ("paper") or a world file by path."""
    text_path = str(name_or_path)
    is_path = isinstance(name_or_path, Path) or text_path.endswith(".toml") or "/" in text_path
    if is_path:
        path = Path(name_or_path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise ConfigError(f"world file {path}: cannot read ({exc.strerror})") from None
        source = str(path)
    else:
        resource = resources.files("slamlens.services.slam") / "worlds" / f"{text_path}.toml"
        if not resource.is_file():
            raise ConfigError(f"unknown world {text_path!r}; packaged worlds: "
                              f"{', '.join(packaged_worlds())} (or give a path to a .toml)")
        text = resource.read_text()
        source = f"world {text_path!r}"
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    return world_from_mapping(raw, source=source)


def world_from_mapping(raw: dict[str, Any], *, source: str = "world") -> World:
    """Validate a parsed world file (see the module docstring for the keys)."""
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(unknown)}; "
                          f"known: {', '.join(sorted(_TOP_KEYS))}")
    name = raw.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{source}: key 'name' must be a non-empty string, got {name!r}")
    description = raw.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"{source}: key 'description' must be a string")

    sections: dict[str, Any] = {}
    for key, cls in (("sensor", SensorModel), ("motion", MotionModel), ("noise", NoiseModel),
                     ("run", _Run), ("start", _Start), ("area", _Area)):
        table = raw.get(key, {})
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: key {key!r} must be a table [{key}]")
        try:
            sections[key] = settings_from_mapping(cls, table)
        except ConfigError as exc:
            raise ConfigError(f"{source} [{key}]: {exc}") from None

    for key in ("sensor", "motion"):
        for fname in _POSITIVE[key]:
            value = getattr(sections[key], fname)
            if not value > 0:
                raise ConfigError(f"{source}: key '{key}.{fname}' must be > 0, got {value!r}")
    if sections["sensor"].fov_rad > 2 * math.pi:
        raise ConfigError(f"{source}: key 'sensor.fov_rad' must be ≤ 2π, "
                          f"got {sections['sensor'].fov_rad!r}")
    for fname in ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing"):
        value = getattr(sections["noise"], fname)
        if not value >= 0:
            raise ConfigError(f"{source}: key 'noise.{fname}' must be ≥ 0, got {value!r}")
    if sections["run"].loops < 1:
        raise ConfigError(f"{source}: key 'run.loops' must be ≥ 1, got {sections['run'].loops}")

    start = sections["start"].pose
    if len(start) != 3:
        raise ConfigError(f"{source}: key 'start.pose' must be [x, y, theta], got {list(start)}")

    if "landmark_grid" in raw:
        if "landmarks" in raw:
            raise ConfigError(f"{source}: give either 'landmarks' or [landmark_grid], not both")
        ids, landmarks = _generate_landmarks(raw["landmark_grid"], source)
    else:
        ids, landmarks = _parse_landmarks(raw.get("landmarks"), source)
    waypoints = _parse_points(raw.get("waypoints"), "waypoints", source, columns=2)
    if waypoints.shape[0] < 1:
        raise ConfigError(f"{source}: key 'waypoints' must list at least one [x, y]")

    area = sections["area"]
    area_min = area_max = None
    if area.min_xy or area.max_xy:
        if len(area.min_xy) != 2 or len(area.max_xy) != 2:
            raise ConfigError(f"{source}: keys 'area.min_xy' and 'area.max_xy' must both be [x, y]")
        area_min, area_max = frozen_array(area.min_xy, "<f8"), frozen_array(area.max_xy, "<f8")
        if not np.all(area_min < area_max):
            raise ConfigError(f"{source}: key 'area.min_xy' must be below 'area.max_xy'")
        outside = np.any((landmarks < area_min) | (landmarks > area_max), axis=1)
        if np.any(outside):
            bad = [int(i) for i in ids[outside]]
            raise ConfigError(f"{source}: key 'landmarks': ids {bad} lie outside the area "
                              f"{list(area.min_xy)}..{list(area.max_xy)}")

    return World(name=name, description=description, landmark_ids=ids, landmarks_xy=landmarks,
                 waypoints_xy=waypoints, start_pose=frozen_array(start, "<f8"),
                 area_min_xy=area_min, area_max_xy=area_max, sensor=sections["sensor"],
                 motion=sections["motion"], noise=sections["noise"],
                 loops=sections["run"].loops, source=source)


def _parse_points(value: Any, key: str, source: str, *, columns: int) -> np.ndarray:
    if not isinstance(value, list):
        raise ConfigError(f"{source}: key {key!r} must be a list of rows, "
                          f"got {type(value).__name__}")
    rows = []
    for i, row in enumerate(value):
        if (not isinstance(row, list) or len(row) != columns
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)):
            raise ConfigError(f"{source}: key {key!r} row {i}: expected {columns} numbers, "
                              f"got {row!r}")
        rows.append([float(v) for v in row])
    array = np.array(rows, dtype=float).reshape(-1, columns)
    if not np.all(np.isfinite(array)):
        raise ConfigError(f"{source}: key {key!r}: values must be finite")
    array.setflags(write=False)
    return array


def _generate_landmarks(table: Any, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Validate a [landmark_grid] table and generate its landmarks."""
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: key 'landmark_grid' must be a table [landmark_grid]")
    for key in ("rows", "columns"):
        if key not in table:
            raise ConfigError(f"{source}: key 'landmark_grid.{key}' is required")
    try:
        grid = settings_from_mapping(LandmarkGrid, table)
    except ConfigError as exc:
        raise ConfigError(f"{source} [landmark_grid]: {exc}") from None
    for key in ("rows", "columns"):
        if getattr(grid, key) < 1:
            raise ConfigError(f"{source}: key 'landmark_grid.{key}' must be ≥ 1, "
                              f"got {getattr(grid, key)}")
    if grid.rows * grid.columns > MAX_GENERATED_LANDMARKS:
        raise ConfigError(f"{source}: [landmark_grid] makes {grid.rows * grid.columns} "
                          f"landmarks; at most {MAX_GENERATED_LANDMARKS}")
    if not (math.isfinite(grid.spacing_m) and grid.spacing_m > 0):
        raise ConfigError(f"{source}: key 'landmark_grid.spacing_m' must be > 0, "
                          f"got {grid.spacing_m!r}")
    if not (math.isfinite(grid.jitter_m) and 0 <= grid.jitter_m < grid.spacing_m / 2):
        raise ConfigError(f"{source}: key 'landmark_grid.jitter_m' must be in "
                          f"[0, spacing_m / 2 = {grid.spacing_m / 2:g}), got {grid.jitter_m!r}")
    if len(grid.origin_xy) != 2 or not all(math.isfinite(v) for v in grid.origin_xy):
        raise ConfigError(f"{source}: key 'landmark_grid.origin_xy' must be [x, y], "
                          f"got {list(grid.origin_xy)}")
    if grid.seed < 0:
        raise ConfigError(f"{source}: key 'landmark_grid.seed' must be ≥ 0, got {grid.seed}")
    if grid.first_id < 0:
        raise ConfigError(f"{source}: key 'landmark_grid.first_id' must be ≥ 0, "
                          f"got {grid.first_id}")
    return grid.generate()


def _parse_landmarks(value: Any, source: str) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{source}: key 'landmarks' must be a non-empty list of [x, y] "
                          "or [id, x, y]")
    width = len(value[0]) if isinstance(value[0], list) else 0
    if width not in (2, 3):
        raise ConfigError(f"{source}: key 'landmarks' row 0: expected [x, y] or [id, x, y], "
                          f"got {value[0]!r}")
    table = _parse_points(value, "landmarks", source, columns=width)
    if width == 2:
        return frozen_array(np.arange(1, table.shape[0] + 1), "<i8"), table
    ids = table[:, 0]
    if not np.all(ids == np.round(ids)) or np.any(ids < 0):
        raise ConfigError(f"{source}: key 'landmarks': ids must be non-negative integers")
    if len(np.unique(ids)) != len(ids):
        raise ConfigError(f"{source}: key 'landmarks': ids must be distinct")
    return frozen_array(ids, "<i8"), frozen_array(table[:, 1:], "<f8")
