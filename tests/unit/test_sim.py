"""The simulator: stream order, determinism, exact motion model, noise statistics, sensor."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from slamlens.common.geometry import compose2, inverse2
from slamlens.common.messages import Observations, Odometry, Truth
from slamlens.services.slam.sim import (
    Simulator,
    first_seen_times,
    plan_trajectory,
    staggered,
    visible,
)
from slamlens.services.slam.world import NoiseModel, World, load_world

PAPER = load_world("paper")


def spec_step(pose: np.ndarray, v: float, w: float, dt: float) -> np.ndarray:
    """docs/estimator.md prediction, written out again here as the oracle."""
    x, y, th = pose
    th2 = th + w * dt
    return np.array([x + v * dt * np.cos(th), y + v * dt * np.sin(th),
                     (th2 + np.pi) % (2 * np.pi) - np.pi])


def split(events: list) -> tuple[list[Odometry], list[Truth], list[Observations]]:
    return ([e for e in events if isinstance(e, Odometry)],
            [e for e in events if isinstance(e, Truth)],
            [e for e in events if isinstance(e, Observations)])


@pytest.fixture(scope="module")
def paper_events() -> list:
    return list(Simulator(PAPER, seed=7).events())


def test_stream_order_truth_first_then_odometry_truth_observations(paper_events: list) -> None:
    first = paper_events[0]
    assert isinstance(first, Truth) and first.stamp == 0.0
    assert np.array_equal(first.pose, [0.0, 0.0, 0.0])  # map frame = start pose
    letter = {Odometry: "o", Truth: "t", Observations: "z"}
    kinds = "".join(letter[type(e)] for e in paper_events[1:])
    # per step: odometry, truth, and a batch every sensor period (= dt for paper)
    assert kinds == "otz" * (len(kinds) // 3)
    stamps_ok = True
    i = 1
    while i < len(paper_events):
        odo, truth = paper_events[i], paper_events[i + 1]
        assert isinstance(odo, Odometry) and isinstance(truth, Truth)
        assert odo.stamp == truth.stamp
        assert math.isclose(odo.dt, PAPER.motion.dt_s)
        i += 2
        if i < len(paper_events) and isinstance(paper_events[i], Observations):
            stamps_ok &= paper_events[i].stamp == truth.stamp
            i += 1
    assert stamps_ok
    stamps = [e.stamp for e in paper_events]
    assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))
    odo, truths, obs = split(paper_events)
    assert len(truths) == len(odo) + 1
    assert len(obs) == len(odo)  # period_s == dt_s: one batch per step


def test_sensor_period_longer_than_step() -> None:
    world = dataclasses.replace(PAPER, sensor=dataclasses.replace(PAPER.sensor, period_s=0.3))
    events = list(Simulator(world, loops=1).events())
    odo, _, obs = split(events)
    gaps = np.diff([o.stamp for o in obs])
    assert np.allclose(gaps, 0.3)
    assert abs(len(obs) - len(odo) / 3) <= 1


def test_same_seed_same_stream_other_seed_other_noise_same_truth() -> None:
    a = [e.to_bytes() for e in Simulator(PAPER, seed=3, loops=1).events()]
    b = [e.to_bytes() for e in Simulator(PAPER, seed=3, loops=1).events()]
    assert a == b
    ea = list(Simulator(PAPER, seed=3, loops=1).events())
    ec = list(Simulator(PAPER, seed=4, loops=1).events())
    oa, ta, za = split(ea)
    oc, tc, zc = split(ec)
    assert all(x == y for x, y in zip(ta, tc, strict=True))  # truth does not depend on the seed
    assert not np.allclose([o.v for o in oa], [o.v for o in oc])
    assert not np.allclose(np.concatenate([z.ranges for z in za]),
                           np.concatenate([z.ranges for z in zc]))


def test_true_pose_integrates_the_commanded_controls_with_the_spec_model() -> None:
    sim = Simulator(PAPER, seed=1)
    _, truths, _ = split(list(sim.events()))
    controls = sim.trajectory.controls
    dt = PAPER.motion.dt_s
    for k in range(1, len(truths)):
        expected = spec_step(truths[k - 1].pose, *controls[k - 1], dt)
        assert np.allclose(truths[k].pose, expected, atol=1e-12)


def test_odometry_noise_has_the_worlds_sigma() -> None:
    noise = NoiseModel(sigma_v=0.03, sigma_w=0.08, sigma_range=0.05, sigma_bearing=0.02)
    world = dataclasses.replace(PAPER, noise=noise)  # distinct σ: a swap would show
    sim = Simulator(world, seed=11, loops=10)
    odo, truths, _ = split(list(sim.events()))
    dt = PAPER.motion.dt_s
    poses = np.array([t.pose for t in truths])
    # recover the commanded controls from consecutive true poses (first-order model)
    step = np.diff(poses[:, :2], axis=0)
    heading = poses[:-1, 2]
    v_true = (step[:, 0] * np.cos(heading) + step[:, 1] * np.sin(heading)) / dt
    w_true = ((np.diff(poses[:, 2]) + np.pi) % (2 * np.pi) - np.pi) / dt
    ev = np.array([o.v for o in odo]) - v_true
    ew = np.array([o.w for o in odo]) - w_true
    n = ev.size
    assert n > 1500
    for err, sigma in ((ev, noise.sigma_v), (ew, noise.sigma_w)):
        assert abs(err.mean()) < 4 * sigma / math.sqrt(n)
        assert abs(err.std(ddof=1) / sigma - 1) < 0.1  # ~6 standard errors of a std for n>1500
        assert abs(np.corrcoef(err[:-1], err[1:])[0, 1]) < 0.1  # white


def true_range_bearing(pose: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dx, dy = xy[:, 0] - pose[0], xy[:, 1] - pose[1]
    bearing = (np.arctan2(dy, dx) - pose[2] + np.pi) % (2 * np.pi) - np.pi
    return np.hypot(dx, dy), bearing


def test_observations_are_exactly_the_landmarks_in_range_and_view(paper_events: list) -> None:
    truth = None
    residual_r, residual_b = [], []
    for event in paper_events:
        if isinstance(event, Truth):
            truth = event
            continue
        if not isinstance(event, Observations):
            continue
        assert truth is not None and truth.stamp == event.stamp
        r, b = true_range_bearing(truth.pose, truth.landmarks)
        in_view = (r <= PAPER.sensor.max_range_m) & (np.abs(b) <= PAPER.sensor.fov_rad / 2)
        assert sorted(event.ids) == sorted(truth.landmark_ids[in_view])
        index = {int(i): k for k, i in enumerate(truth.landmark_ids)}
        rows = [index[int(i)] for i in event.ids]
        residual_r.extend(event.ranges - r[rows])
        residual_b.extend((event.bearings - b[rows] + np.pi) % (2 * np.pi) - np.pi)
        assert np.all(event.bearings >= -np.pi) and np.all(event.bearings < np.pi)
    residual_r, residual_b = np.array(residual_r), np.array(residual_b)
    assert residual_r.size > 1500
    for err, sigma in ((residual_r, PAPER.noise.sigma_range),
                       (residual_b, PAPER.noise.sigma_bearing)):
        assert abs(err.mean()) < 4 * sigma / math.sqrt(err.size)
        assert abs(err.std(ddof=1) / sigma - 1) < 0.1


def test_anonymous_mode_hides_ids_but_not_the_measurements() -> None:
    named = split(list(Simulator(PAPER, seed=5, loops=1).events()))[2]
    anon = split(list(Simulator(PAPER, seed=5, loops=1, anonymous=True).events()))[2]
    assert len(named) == len(anon)
    for a, b in zip(named, anon, strict=True):
        assert np.all(b.ids == -1) and b.ids.shape == a.ids.shape
        assert np.array_equal(a.ranges, b.ranges) and np.array_equal(a.bearings, b.bearings)


def test_landmarks_are_first_seen_at_different_times(paper_events: list) -> None:
    seen: dict[int, float] = {}
    for event in paper_events:
        if isinstance(event, Observations):
            for i in event.ids:
                seen.setdefault(int(i), event.stamp)
    assert set(seen) == set(range(1, 16))  # every landmark is seen in the default run
    assert seen == pytest.approx(first_seen_times(PAPER))
    # when the robot reaches the first corner (1, 0)
    _, truths, _ = split(paper_events)
    corner_t = next(t.stamp for t in truths if np.hypot(t.pose[0] - 1, t.pose[1]) < 0.06)
    cluster_first = [min(seen[i] for i in range(5 * c + 1, 5 * c + 6)) for c in range(3)]
    assert cluster_first[0] < corner_t < cluster_first[1] < cluster_first[2]
    assert len(set(seen.values())) >= 10  # first sightings are spread, not all at t = 0
    assert max(seen.values()) - min(seen.values()) > 5.0


def test_robot_drives_the_square_loop(paper_events: list) -> None:
    _, truths, _ = split(paper_events)
    poses = np.array([t.pose for t in truths])
    assert np.all(poses[:, :2] > -0.2) and np.all(poses[:, :2] < 1.2)
    for corner in ([1, 0], [1, 1], [0, 1]):
        d = np.hypot(*(poses[:, :2] - corner).T)
        assert np.sum(np.diff((d < 0.05).astype(int)) == 1) == PAPER.loops  # visited per loop
    assert np.hypot(*poses[-1, :2]) < PAPER.motion.waypoint_tolerance_m
    speeds = np.hypot(*np.diff(poses[:, :2], axis=0).T) / PAPER.motion.dt_s
    assert speeds.max() <= PAPER.motion.speed_mps + 1e-12


def test_loops_and_duration() -> None:
    one, three = Simulator(PAPER, loops=1), Simulator(PAPER)
    assert three.duration_s == pytest.approx(3 * one.duration_s, rel=0.05)
    events = list(three.events())
    assert events[-1].stamp == pytest.approx(three.duration_s)
    shifted = list(Simulator(PAPER, loops=1, start_time_s=100.0).events())
    assert shifted[0].stamp == 100.0
    assert shifted[-1].stamp == pytest.approx(100.0 + one.duration_s)


def test_truth_is_in_the_map_frame_when_the_world_start_is_elsewhere() -> None:
    # move and turn the whole world: the map-frame stream must not change
    th, t = 0.7, np.array([3.0, -2.0])
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])

    def move(xy: np.ndarray) -> np.ndarray:
        out = xy @ R.T + t
        out.setflags(write=False)
        return out

    moved: World = dataclasses.replace(
        PAPER, landmarks_xy=move(PAPER.landmarks_xy), waypoints_xy=move(PAPER.waypoints_xy),
        start_pose=np.array([t[0], t[1], th]))
    _, ta, za = split(list(Simulator(PAPER, seed=2, loops=1).events()))
    _, tb, zb = split(list(Simulator(moved, seed=2, loops=1).events()))
    assert len(ta) == len(tb) and len(za) == len(zb)
    for a, b in zip(ta, tb, strict=True):
        assert np.allclose(a.pose, b.pose, atol=1e-9)
        assert np.allclose(a.landmarks, b.landmarks, atol=1e-12)
    assert all(np.array_equal(a.ids, b.ids) for a, b in zip(za, zb, strict=True))


def test_plan_shapes_and_read_only() -> None:
    traj = plan_trajectory(PAPER)
    assert traj.poses.shape == (traj.controls.shape[0] + 1, 3)
    assert traj.stamps[0] == 0.0
    assert not traj.poses.flags.writeable


# -- several robots in one arena -----------------------------------------
def _fleet(n: int, **kw) -> list[Simulator]:
    sims = []
    for k in range(n):
        world, origin = staggered(PAPER, k)
        sims.append(Simulator(world, robot=f"r{k + 1}", seed=k, loops=1, truth_origin=origin,
                              marker_id=10 + k, **kw))
    return sims


def test_several_robots_start_on_the_loop_one_corner_apart() -> None:
    sims = _fleet(4)
    starts = [next(iter(s.events())) for s in sims]
    assert all(isinstance(t, Truth) for t in starts)
    # in the arena frame (robot 1's map frame): the start, then corners 1..3 of the square,
    # each facing the next corner
    expected = [(0.0, 0.0, 0.0), (1.0, 0.0, math.pi / 2), (1.0, 1.0, -math.pi),
                (0.0, 1.0, -math.pi / 2)]
    for truth, pose in zip(starts, expected, strict=True):
        assert np.allclose(truth.pose, pose, atol=1e-12)
    assert [t.marker_id for t in starts] == [10, 11, 12, 13]
    for truth in starts[1:]:  # one arena: the same landmarks wherever a robot starts
        assert np.allclose(truth.landmarks, starts[0].landmarks, atol=1e-12)
        assert np.array_equal(truth.landmark_ids, starts[0].landmark_ids)


def test_each_robot_drives_the_loop_in_its_own_map_frame_and_they_stay_apart() -> None:
    sims = _fleet(3)
    runs = [split(list(s.events())) for s in sims]
    n = min(len(truths) for _, truths, _ in runs)
    for k, (odometry, truths, _) in enumerate(runs):
        assert all(o.robot == f"r{k + 1}" for o in odometry + truths)
        assert len(odometry) == len(sims[0].trajectory.controls)  # the same loop, shifted
        # its own map frame is its start (docs/protocol.md): the truth re-expressed there (what the
        # monitor does with origin_stamp) is its trajectory, which starts at 0
        at_start = inverse2(truths[0].pose)
        for truth, pose in zip(truths, sims[k].trajectory.poses, strict=True):
            assert np.allclose(compose2(at_start, truth.pose), pose, atol=1e-9)
    for i in range(n):  # congruent motion, a side of the square apart: never collide
        a, b, c = (runs[k][1][i].pose[:2] for k in range(3))
        assert min(np.hypot(*(a - b)), np.hypot(*(b - c)), np.hypot(*(a - c))) > 0.5


def test_more_robots_than_corners_is_refused() -> None:
    from slamlens.common.errors import ConfigError

    with pytest.raises(ConfigError, match="at most 4 robots"):
        staggered(PAPER, 4)


def test_one_robot_is_the_plain_simulator() -> None:
    world, origin = staggered(PAPER, 0)
    assert world is PAPER and not np.any(origin)
    plain = list(Simulator(PAPER, seed=3, loops=1).events())
    same = list(Simulator(world, seed=3, loops=1, truth_origin=origin).events())
    assert plain == same
    assert all(t.marker_id is None for t in plain if isinstance(t, Truth))


def test_large_world_path_observes_all_1000_landmarks_in_one_loop() -> None:
    """The scenario: the lawnmower loop sees every landmark of the 1000 within one
    loop, a few at a time (the update cost stays that of ~4 observations per batch)."""
    world = load_world("large")
    traj = plan_trajectory(world, loops=1)
    duration = float(traj.stamps[-1])
    assert 300.0 < duration < 600.0  # ~411 m at 1 m/s plus turns on the spot
    seen = first_seen_times(world, loops=1)
    assert sorted(seen) == list(range(1, 1001))
    # the map grows over the whole loop: a quarter of it by the first quarter of the time
    times = np.array(sorted(seen.values()))
    assert times[249] < 0.35 * duration and times[749] < 0.85 * duration
    counts = [int(visible(traj.poses[k], traj.landmarks_xy,
                          max_range_m=world.sensor.max_range_m,
                          fov_rad=world.sensor.fov_rad)[0].sum()) for k in traj.sensor_steps]
    assert 2.5 < float(np.mean(counts)) < 6.0 and max(counts) <= 10
    # the same seed gives the same stream (the map itself does not depend on the sim seed)
    first = [m.to_bytes() for m, _ in zip(Simulator(world, seed=3).events(), range(300),
                                          strict=False)]
    again = [m.to_bytes() for m, _ in zip(Simulator(world, seed=3).events(), range(300),
                                          strict=False)]
    assert first == again
