"""The simulated robot: a seeded, deterministic stream of odometry, observations and truth.

The true robot is a unicycle following the world's waypoint loop with a simple heading
controller. Its true pose integrates the *commanded* (v, ω) with the first-order (docs/estimator.md)
model, and the odometry it reports is the commanded (v, ω) plus Gaussian noise of the
world's σv, σω. So an estimator using the standard model (docs/estimator.md) with the same σ
has an exactly right motion and noise model: its NEES is χ²-consistent (the consistency
tests rely on it).
The true trajectory does not depend on the seed; only the measurement noises do.

Per step k (from t = (k−1)·dt to t = k·dt) the stream is: ``Odometry(stamp=t)``, then
``Truth(stamp=t)`` (pose after the step, every landmark), then, when a sensor period has
elapsed, ``Observations(stamp=t)`` of every landmark within range and field of view of the
true pose. One ``Truth`` at t = 0 comes first. Everything is in the map frame = the robot's
start pose (docs/protocol.md).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from slamlens.common.arrays import frozen_array
from slamlens.common.errors import ConfigError
from slamlens.common.geometry import compose2, inverse2, transform2, wrap_angle
from slamlens.common.messages import Observations, Odometry, Truth
from slamlens.services.slam.world import World

_EMPTY_I8 = frozen_array(np.zeros(0), "<i8")
_EMPTY_F8 = frozen_array(np.zeros(0), "<f8")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The true, noise-free run in the map frame."""

    stamps: np.ndarray  #: float64[T+1], s; stamps[k] = start_time + k·dt
    poses: np.ndarray  #: float64[T+1, 3], true pose (x m, y m, θ rad) at stamps[k]
    controls: np.ndarray  #: float64[T, 2], commanded (v m/s, ω rad/s) from stamps[k] to [k+1]
    sensor_steps: np.ndarray  #: int64[...], indices k at which an observation batch is taken
    landmarks_xy: np.ndarray  #: float64[n, 2], true landmarks in the map frame


def step_pose(pose: np.ndarray, v: float, w: float, dt: float) -> np.ndarray:
    """The first-order velocity model of docs/estimator.md (θ wrapped)."""
    x, y, theta = pose
    return np.array([x + v * dt * math.cos(theta), y + v * dt * math.sin(theta),
                     float(wrap_angle(theta + w * dt))])


def heading_control(pose: np.ndarray, target_xy: np.ndarray, *, speed_mps: float,
                    max_turn_rate: float, heading_gain: float, dt: float) -> tuple[float, float]:
    """Commanded (v, ω) towards ``target_xy``: turn proportionally, slow down when off course."""
    dx, dy = target_xy[0] - pose[0], target_xy[1] - pose[1]
    error = float(wrap_angle(math.atan2(dy, dx) - pose[2]))
    w = max(-max_turn_rate, min(max_turn_rate, heading_gain * error))
    # cos(error) ≥ 0 makes it turn on the spot at a corner; distance/dt stops it overshooting
    v = min(speed_mps * max(0.0, math.cos(error)), math.hypot(dx, dy) / dt)
    return v, w


def world_to_map(world: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(landmarks_xy, waypoints_xy, start_pose) expressed in the map frame (= start pose)."""
    x0, y0, th0 = world.start_pose
    c, s = math.cos(th0), math.sin(th0)
    R_map_from_world = np.array([[c, s], [-s, c]])

    def to_map(points: np.ndarray) -> np.ndarray:
        return (points - np.array([x0, y0])) @ R_map_from_world.T

    return to_map(world.landmarks_xy), to_map(world.waypoints_xy), np.zeros(3)


def plan_trajectory(world: World, *, loops: int | None = None,
                    start_time_s: float = 0.0) -> Trajectory:
    """Drive ``loops`` times round the waypoints (default: the world's) without noise."""
    loops = world.loops if loops is None else loops
    if loops < 1:
        raise ConfigError(f"loops must be ≥ 1, got {loops}")
    motion, sensor = world.motion, world.sensor
    landmarks, waypoints, pose = world_to_map(world)
    dt = motion.dt_s
    m = waypoints.shape[0]
    perimeter = float(np.sum(np.hypot(*np.diff(np.vstack([pose[:2], waypoints, waypoints[:1]]),
                                                   axis=0).T)))
    expected_s = loops * (perimeter / motion.speed_mps + m * 2 * math.pi / motion.max_turn_rate)
    max_steps = int(10 * expected_s / dt) + 1000  # a controller that cannot arrive must stop

    poses = [pose]
    controls: list[tuple[float, float]] = []
    reached = 0
    total = loops * m
    while True:
        while reached < total and math.dist(pose[:2], waypoints[reached % m]) \
                < motion.waypoint_tolerance_m:
            reached += 1
        if reached == total:
            break
        if len(controls) >= max_steps:
            raise ConfigError(f"world {world.name!r}: the robot cannot reach waypoint "
                              f"{reached % m} {list(waypoints[reached % m])} (map frame); "
                              "check motion.max_turn_rate, heading_gain and waypoint_tolerance_m")
        v, w = heading_control(pose, waypoints[reached % m], speed_mps=motion.speed_mps,
                               max_turn_rate=motion.max_turn_rate,
                               heading_gain=motion.heading_gain, dt=dt)
        pose = step_pose(pose, v, w, dt)
        poses.append(pose)
        controls.append((v, w))

    T = len(controls)
    stamps = start_time_s + dt * np.arange(T + 1)  # k·dt, not a running sum: no drift
    elapsed = dt * np.arange(1, T + 1)
    # a batch at the first step end at or after each multiple of the sensor period
    period_index = np.floor(elapsed / sensor.period_s + 1e-9)
    previous = np.concatenate([[0.0], period_index[:-1]])
    sensor_steps = np.nonzero(period_index > previous)[0] + 1
    return Trajectory(stamps=frozen_array(stamps, "<f8"), poses=frozen_array(poses, "<f8"),
                      controls=frozen_array(np.reshape(controls, (T, 2)), "<f8"),
                      sensor_steps=frozen_array(sensor_steps, "<i8"),
                      landmarks_xy=frozen_array(landmarks, "<f8"))


def visible(pose: np.ndarray, landmarks_xy: np.ndarray, *, max_range_m: float,
            fov_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mask, ranges m, bearings rad) of the landmarks seen from ``pose`` (true values)."""
    dx = landmarks_xy[:, 0] - pose[0]
    dy = landmarks_xy[:, 1] - pose[1]
    ranges = np.hypot(dx, dy)
    bearings = np.asarray(wrap_angle(np.arctan2(dy, dx) - pose[2]))
    mask = (ranges <= max_range_m) & (np.abs(bearings) <= fov_rad / 2)
    return mask, ranges, bearings


def first_seen_times(world: World, *, loops: int | None = None) -> dict[int, float]:
    """Time (s from the start) at which each landmark id is first observed; unseen ids absent."""
    traj = plan_trajectory(world, loops=loops)
    seen: dict[int, float] = {}
    for k in traj.sensor_steps:
        mask, _, _ = visible(traj.poses[k], traj.landmarks_xy,
                             max_range_m=world.sensor.max_range_m, fov_rad=world.sensor.fov_rad)
        for landmark_id in world.landmark_ids[mask]:
            seen.setdefault(int(landmark_id), float(traj.stamps[k]))
    return seen


def staggered(world: World, k: int) -> tuple[World, np.ndarray]:
    """Robot ``k`` (from 0) of several driving the same loop in one arena.

    Robot 0 is the world as it is. Robot k ≥ 1 starts on waypoint k − 1, facing waypoint
    k, and visits the loop in the same order from there, so at the same speed the robots
    stay a side of the loop apart. Returns its world and the pose of its start in robot 0's
    map frame (the arena frame its truth is said in: docs/protocol.md gives each robot its own map
    frame, its start pose).
    """
    m = world.waypoints_xy.shape[0]
    if k == 0:
        return world, np.zeros(3)
    if k >= m:
        raise ConfigError(f"world {world.name!r} has {m} waypoints: at most {m} robots "
                          "(one per start on the loop)")
    start_xy, ahead = world.waypoints_xy[k - 1], world.waypoints_xy[k]
    heading = math.atan2(ahead[1] - start_xy[1], ahead[0] - start_xy[0])
    start = np.array([start_xy[0], start_xy[1], heading])
    if np.hypot(*(start_xy - world.start_pose[:2])) < 2 * world.motion.waypoint_tolerance_m:
        raise ConfigError(f"world {world.name!r}: robot {k + 1} would start where robot 1 "
                          f"does (waypoint {k - 1} is the start pose); use fewer robots")
    waypoints = np.roll(world.waypoints_xy, -k, axis=0)
    waypoints.setflags(write=False)
    start.setflags(write=False)
    mine = dataclasses.replace(world, start_pose=start, waypoints_xy=waypoints)
    return mine, compose2(inverse2(world.start_pose), start)


class Simulator:
    """A simulated robot driver: ``events()`` yields the docs/protocol.md messages in stream order.

    ``truth_origin`` is the pose of the robot's map frame in the frame its ``Truth`` is said
    in (several robots in one arena, :func:`staggered`); ``marker_id`` goes in every Truth.
    """

    def __init__(self, world: World, *, robot: str = "robot1", seed: int = 0,
                 anonymous: bool = False, loops: int | None = None,
                 start_time_s: float = 0.0, truth_origin: np.ndarray | None = None,
                 marker_id: int | None = None) -> None:
        self.world = world
        self.robot = robot
        self.seed = seed
        self.anonymous = anonymous
        self.marker_id = marker_id
        self.trajectory = plan_trajectory(world, loops=loops, start_time_s=start_time_s)
        self._origin = None if truth_origin is None or not np.any(truth_origin) \
            else np.asarray(truth_origin, dtype=float)
        self._truth_landmarks = self.trajectory.landmarks_xy if self._origin is None \
            else frozen_array(transform2(self._origin, self.trajectory.landmarks_xy), "<f8")

    @property
    def duration_s(self) -> float:
        """Simulated time from the first to the last event, s."""
        return float(self.trajectory.stamps[-1] - self.trajectory.stamps[0])

    @property
    def n_steps(self) -> int:
        return int(self.trajectory.controls.shape[0])

    def events(self) -> Iterator[Odometry | Observations | Truth]:
        """Truth at t=0, then per step: Odometry, Truth, and Observations when due."""
        traj, noise, sensor = self.trajectory, self.world.noise, self.world.sensor
        # independent streams, so odometry noise is the same whatever the sensor draws
        odo_seq, obs_seq = np.random.SeedSequence(self.seed).spawn(2)
        odo_rng, obs_rng = np.random.default_rng(odo_seq), np.random.default_rng(obs_seq)
        measured = traj.controls + odo_rng.standard_normal(traj.controls.shape) * np.array(
            [noise.sigma_v, noise.sigma_w])
        dt = self.world.motion.dt_s
        ids = self.world.landmark_ids
        landmarks = traj.landmarks_xy
        sensor_due = np.zeros(self.n_steps + 1, dtype=bool)
        sensor_due[traj.sensor_steps] = True

        yield self._truth(0)
        for k in range(1, self.n_steps + 1):
            stamp = float(traj.stamps[k])
            v, w = measured[k - 1]
            yield Odometry(robot=self.robot, stamp=stamp, dt=dt, v=float(v), w=float(w))
            yield self._truth(k)
            if not sensor_due[k]:
                continue
            mask, ranges, bearings = visible(traj.poses[k], landmarks,
                                             max_range_m=sensor.max_range_m,
                                             fov_rad=sensor.fov_rad)
            count = int(mask.sum())
            if count == 0:
                yield Observations(robot=self.robot, stamp=stamp, ids=_EMPTY_I8,
                                   ranges=_EMPTY_F8, bearings=_EMPTY_F8)
                continue
            draw = obs_rng.standard_normal((count, 2))
            # a range cannot be negative; clipping only matters for a landmark under the robot
            z_range = np.maximum(ranges[mask] + noise.sigma_range * draw[:, 0], 0.0)
            z_bearing = np.asarray(wrap_angle(bearings[mask] + noise.sigma_bearing * draw[:, 1]))
            z_ids = np.full(count, -1) if self.anonymous else ids[mask]
            yield Observations(robot=self.robot, stamp=stamp, ids=z_ids, ranges=z_range,
                               bearings=z_bearing)

    def _truth(self, k: int) -> Truth:
        pose = self.trajectory.poses[k]
        if self._origin is not None:
            pose = compose2(self._origin, pose)
        return Truth(robot=self.robot, stamp=float(self.trajectory.stamps[k]), pose=pose,
                     landmark_ids=self.world.landmark_ids, landmarks=self._truth_landmarks,
                     marker_id=self.marker_id)
