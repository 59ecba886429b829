"""Simulated worlds: landmarks, a waypoint loop, sensor, motion and noise, read from TOML.

A world file is small and documented (``worlds/paper.toml`` is the reference, SPEC §8)::

    name = "paper"
    landmarks = [[x, y], ...]          # or [[id, x, y], ...]; ids default to 1..n
    waypoints = [[x, y], ...]          # a closed loop, visited in order, then again
    [start]  pose = [0.0, 0.0, 0.0]    # x m, y m, θ rad; the map frame is this pose (SPEC §3)
    [area]   min_xy = [-1, -1]  max_xy = [2, 2]   # optional: every landmark must lie inside
    [sensor] max_range_m, fov_rad, period_s
    [motion] speed_mps, dt_s, waypoint_tolerance_m, max_turn_rate, heading_gain
    [noise]  sigma_v, sigma_w, sigma_range, sigma_bearing      # standard deviations, SI
    [run]    loops

Coordinates in the file are in the world frame. :func:`load_world` accepts the name of a
packaged world ("paper", "grid") or a path; unknown keys and bad values raise
:class:`~common.errors.ConfigError` naming the key.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from common.arrays import frozen_array, values_equal
from common.config import settings_from_mapping
from common.errors import ConfigError


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


_TOP_KEYS = {"name", "description", "landmarks", "waypoints",
             "start", "area", "sensor", "motion", "noise", "run"}
_POSITIVE = {
    "sensor": ("max_range_m", "fov_rad", "period_s"),
    "motion": ("speed_mps", "dt_s", "waypoint_tolerance_m", "max_turn_rate", "heading_gain"),
}


def packaged_worlds() -> list[str]:
    """Names of the worlds shipped in ``services/slam/worlds/``."""
    folder = resources.files("services.slam") / "worlds"
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
        resource = resources.files("services.slam") / "worlds" / f"{text_path}.toml"
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
