"""Hostile but well-formed inputs: a test per plausibility gate and per poisoning
path. Each hostile input is refused whole, counted by reason, and the final state after the
hostile inputs equals — bit for bit — that of an estimator that never saw them."""

from __future__ import annotations

import dataclasses
import functools
import math
import threading

import numpy as np
import pytest

from slamlens.common.errors import EstimationError, MessageError
from slamlens.common.messages import (
    Observations,
    Odometry,
    SlamState,
    Truth,
    finite_by_construction,
)
from slamlens.services.slam import ekf
from slamlens.services.slam.ekf import RefusedStepError
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.plausibility import ImplausibleInputError
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

#: every plausibility bound off: what is left is the filter's own guard
NO_GATES = dict(max_dt_s=0.0, max_speed=0.0, max_turn_rate=0.0, max_range=0.0,
                max_abs_bearing=0.0, max_stamp_jump_s=0.0, max_batch=0, max_landmarks=0)


@functools.cache
def _stream() -> tuple[Odometry | Observations, ...]:
    return tuple(e for e in Simulator(load_world("paper"), seed=3).events()
                 if not isinstance(e, Truth))


def clean_stream(n: int = 240) -> list[Odometry | Observations]:
    return list(_stream()[:n])


def apply(est: Estimator, message: Odometry | Observations) -> bool:
    """Apply one input; False if the estimator refused it (as the service counts it)."""
    try:
        if isinstance(message, Odometry):
            est.predict(v=message.v, w=message.w, dt=message.dt, stamp=message.stamp)
        else:
            est.observe(ids=message.ids, ranges=message.ranges, bearings=message.bearings,
                        stamp=message.stamp)
    except EstimationError:
        return False
    return True


def assert_same_state(a: Estimator, b: Estimator) -> None:
    assert np.array_equal(a.pose, b.pose)
    assert np.array_equal(a.landmark_ids, b.landmark_ids)
    assert np.array_equal(a.landmarks, b.landmarks)
    assert np.array_equal(a.covariance, b.covariance)


def odometry(stamp: float, *, v: float = 0.1, w: float = 0.05, dt: float = 0.05) -> Odometry:
    return Odometry(robot="robot1", stamp=stamp, dt=dt, v=v, w=w)


def batch(stamp: float, ids, ranges, bearings) -> Observations:
    return Observations(robot="robot1", stamp=stamp, ids=np.asarray(ids, np.int64),
                        ranges=np.asarray(ranges, float), bearings=np.asarray(bearings, float))


def run_with_hostile(settings: EstimatorSettings, hostile: dict[int, list]) -> tuple[
        Estimator, Estimator, list[bool]]:
    """(estimator that saw the hostile inputs at the given positions, one that did not,
    whether each hostile input was applied)."""
    stream = clean_stream()
    seen, clean = Estimator(settings), Estimator(settings)
    applied = []
    for i, message in enumerate(stream):
        for bad in hostile.get(i, []):
            applied.append(apply(seen, bad))
        assert apply(seen, message) == apply(clean, message)
    return seen, clean, applied


def stamp_at(i: int) -> float:
    return float(clean_stream()[i].stamp)


# ------------------------------------------------------------------ plausibility gates


@pytest.mark.parametrize(("reason", "make"), [
    ("dt", lambda t: odometry(t, dt=1e200)),
    ("dt", lambda t: odometry(t, dt=11.0)),
    ("speed", lambda t: odometry(t, v=-1e6)),
    ("turn_rate", lambda t: odometry(t, w=1e4)),
    ("range", lambda t: batch(t, [901], [1e300], [0.1])),
    ("range", lambda t: batch(t, [3, 902], [1.0, 250.0], [0.1, 0.2])),
    ("bearing", lambda t: batch(t, [903], [1.0], [1e6])),
    ("stamp_jump", lambda t: odometry(t + 1e6)),
    ("stamp_jump", lambda t: batch(t - 3600.0, [3], [1.0], [0.1])),
    ("batch_size", lambda t: batch(t, np.arange(1000, 2000), np.ones(1000),
                                   np.zeros(1000))),
])
def test_each_gate_refuses_the_input_whole_and_the_map_is_as_if_never_seen(reason, make) -> None:
    settings = EstimatorSettings()
    hostile = {40: [make(stamp_at(40))], 150: [make(stamp_at(150))]}
    seen, clean, applied = run_with_hostile(settings, hostile)
    assert applied == [False, False]
    assert seen.refusals == {reason: 2}
    assert seen.last_refusal is not None and seen.last_refusal.reason == reason
    assert_same_state(seen, clean)


def test_map_size_gate_bounds_the_map_a_client_can_force() -> None:
    settings = EstimatorSettings(max_landmarks=20, max_batch=0)
    flood = batch(stamp_at(100), np.arange(5000, 6000), np.ones(1000), np.zeros(1000))
    seen, clean, applied = run_with_hostile(settings, {100: [flood]})
    assert applied == [False] and seen.refusals == {"map_size": 1}
    assert seen.n == clean.n <= 20
    assert_same_state(seen, clean)


def test_map_size_bound_stops_anonymous_landmarks_and_keeps_updating_known_ones() -> None:
    est = Estimator(EstimatorSettings(max_landmarks=2))
    est.observe(ids=[-1, -1], ranges=[1.0, 2.0], bearings=[0.5, -0.5], stamp=0.0)
    assert est.n == 2
    rep = est.observe(ids=[-1, -1], ranges=[1.0, 3.0], bearings=[0.5, 2.5], stamp=0.1)
    assert est.n == 2 and est.refusals == {"map_size": 1}  # the far one would be new
    assert rep.rejected == 1 and len(rep.observed_ids) == 1  # the near one updated


def test_a_bound_of_zero_turns_its_gate_off() -> None:
    est = Estimator(EstimatorSettings(**NO_GATES))
    est.predict(v=50.0, w=20.0, dt=30.0, stamp=1e7)
    est.observe(ids=[1], ranges=[500.0], bearings=[10.0], stamp=1e7)
    assert est.n == 1 and not est.refusals


def test_a_clock_that_really_jumped_is_followed_after_stamp_resync_inputs() -> None:
    est = Estimator(EstimatorSettings(stamp_resync=5))
    est.predict(v=0.1, w=0.0, dt=0.1, stamp=100.0)
    for k in range(4):  # the robot rebooted: its clock restarts near 0
        with pytest.raises(ImplausibleInputError):
            est.predict(v=0.1, w=0.0, dt=0.1, stamp=0.1 * (k + 1))
    est.predict(v=0.1, w=0.0, dt=0.1, stamp=0.5)  # the 5th in a row: followed
    est.predict(v=0.1, w=0.0, dt=0.1, stamp=0.6)
    assert est.refusals == {"stamp_jump": 4} and est.gates.resyncs == 1
    assert est.pose[0] == pytest.approx(0.03)


def test_scattered_jumps_are_never_taken_for_a_new_clock() -> None:
    est = Estimator(EstimatorSettings(stamp_resync=3))
    t = 10.0
    for k in range(10):
        t += 0.1
        est.predict(v=0.1, w=0.0, dt=0.1, stamp=t)
        with pytest.raises(ImplausibleInputError):
            est.predict(v=0.1, w=0.0, dt=0.1, stamp=1e6 * (k + 1))  # each far from the last
    assert est.gates.resyncs == 0 and est.refusals == {"stamp_jump": 10}


# ------------------------------------------------------------------ poisoning paths


@pytest.mark.parametrize(("path", "make"), [
    # every gate off: what keeps the filter finite is its own guard
    ("predict overflows P", lambda t: odometry(t, dt=1e200)),
    ("predict overflows the pose", lambda t: odometry(t, v=1e300, dt=1.0)),
    ("a new landmark at 1e300 m", lambda t: batch(t, [901], [1e300], [0.1])),
    ("a new landmark at 1e200 m", lambda t: batch(t, [902], [1e200], [0.1])),
    ("an update from 1e300 m", lambda t: batch(t, [3], [1e300], [0.1])),
])
def test_the_guard_refuses_a_step_that_would_poison_the_filter(path, make) -> None:
    settings = EstimatorSettings(**NO_GATES)
    t40, t150 = stamp_at(40), stamp_at(150)
    seen, clean, applied = run_with_hostile(settings, {40: [make(t40)], 150: [make(t150)]})
    assert applied == [False, False], path
    assert sum(seen.refusals.values()) == 2 and set(seen.refusals) <= {"non-finite", "not-psd"}
    assert_same_state(seen, clean)
    state = seen.to_state(seq=1, stamp=1.0, step="update")
    assert np.isfinite(state.covariance).all() and np.array_equal(state.covariance,
                                                                  state.covariance.T)


def test_a_batch_keeps_its_good_observations_and_the_guard_skips_the_bad_one() -> None:
    good = Estimator(EstimatorSettings(**NO_GATES))
    seen = Estimator(EstimatorSettings(**NO_GATES))
    for est in (good, seen):
        est.observe(ids=[1, 2], ranges=[1.0, 2.0], bearings=[0.3, -0.4], stamp=0.0)
        est.predict(v=0.1, w=0.1, dt=0.1, stamp=0.1)
    good.observe(ids=[1], ranges=[1.0], bearings=[0.2], stamp=0.1)
    rep = seen.observe(ids=[7, 1], ranges=[1e300, 1.0], bearings=[0.1, 0.2], stamp=0.1)
    assert rep.refused == 1 and list(rep.observed_ids) == [1]
    assert_same_state(seen, good)


def test_a_batch_refused_whole_by_the_guard_raises_and_changes_nothing() -> None:
    est = Estimator(EstimatorSettings(**NO_GATES))
    est.observe(ids=[1], ranges=[1.0], bearings=[0.3], stamp=0.0)
    before = est.covariance, est.pose
    with pytest.raises(RefusedStepError):
        est.observe(ids=[5, 6], ranges=[1e300, 1e250], bearings=[0.1, 0.2], stamp=0.1)
    assert np.array_equal(est.covariance, before[0]) and np.array_equal(est.pose, before[1])
    assert est.refusals == {"non-finite": 2}


def poisoned(P: np.ndarray) -> SlamState:
    """A state whose covariance is not PSD (as a corrupt checkpoint could carry)."""
    n = (P.shape[0] - 3) // 2
    return SlamState(robot="robot1", seq=5, stamp=1.0, step="update", pose=[0.0, 0.0, 0.0],
                     landmark_ids=np.arange(1, n + 1), landmarks=np.array(
                         [[1.0 + k, 0.5] for k in range(n)]).reshape(n, 2), covariance=P)


def test_an_update_that_would_drive_a_variance_negative_is_refused() -> None:
    P = np.diag([1e-2, 1e-2, 1e-3, 1e-2, 1e-2, 1e-4, 1e-4])
    P[5, 3] = P[3, 5] = 0.005  # |ρ| = 5 between landmarks 1 and 2: not PSD; S is still PD
    est = Estimator(EstimatorSettings())
    est.restore(poisoned(P))
    before = est.covariance
    with pytest.raises(RefusedStepError) as info:
        est.observe(ids=[1], ranges=[1.2], bearings=[0.4], stamp=1.0)
    assert info.value.reason == "not-psd"
    assert np.array_equal(est.covariance, before) and est.refusals == {"not-psd": 1}


def test_a_prediction_that_would_make_p_vv_indefinite_is_refused() -> None:
    P = np.diag([1e-2, 1e-2, 1e-3])
    P[0, 2] = P[2, 0] = 0.5  # not PSD
    est = Estimator(EstimatorSettings())
    est.restore(poisoned(P))
    with pytest.raises(RefusedStepError) as info:
        est.predict(v=0.1, w=0.0, dt=0.1, stamp=1.1)
    assert info.value.reason == "not-psd"
    assert np.array_equal(est.pose, np.zeros(3))


def test_planted_faults_still_break_psd_on_purpose() -> None:
    """The guard checks finiteness only when a fault is planted: the cross-covariance fault
    makes P indefinite, as the monitor's demonstrations need."""
    settings = EstimatorSettings(fault="cross-covariance", faulty_features=(3, 12))
    est = Estimator(settings)
    for message in clean_stream(400):
        apply(est, message)
    assert np.linalg.eigvalsh(est.covariance).min() < -1e-9 * np.max(np.diag(est.covariance))
    assert not est.refusals


def test_the_guard_does_not_change_a_correct_run() -> None:
    """The guarded kernels compute exactly what the unguarded ones do (a batch's downdates
    held back and applied at its end, or before a landmark is added, as the estimator does)."""
    guarded = Estimator(EstimatorSettings())
    x, L, ws = np.zeros(3 + 2 * 16), np.zeros((35, 35)), ekf.Workspace.for_capacity(35)
    plain = {"x": x, "L": L, "n": 0, "ids": {}}
    for message in clean_stream(400):
        apply(guarded, message)
        if isinstance(message, Odometry):
            ekf.predict(x, L, plain["n"], v=message.v, w=message.w, dt=message.dt,
                        var_v=0.05 ** 2, var_w=0.05 ** 2)
            continue
        for lid, z_r, z_b in zip(message.ids.tolist(), message.ranges.tolist(),
                                 message.bearings.tolist(), strict=True):
            j = plain["ids"].get(lid)
            if j is None:
                ekf.flush(L, 3 + 2 * plain["n"], ws)
                ekf.initialise(x, L, plain["n"], z_range=z_r, z_bearing=z_b,
                               var_range=0.05 ** 2, var_bearing=0.02 ** 2, ws=ws)
                plain["ids"][lid] = plain["n"]
                plain["n"] += 1
            else:
                ekf.update(x, L, plain["n"], j, z_range=z_r, z_bearing=z_b,
                           var_range=0.05 ** 2, var_bearing=0.02 ** 2, ws=ws, defer=True)
        ekf.flush(L, 3 + 2 * plain["n"], ws)
    N = 3 + 2 * plain["n"]
    assert np.array_equal(guarded.covariance, ekf.symmetric(L, N))
    assert np.array_equal(guarded.pose, x[:3])


def test_settings_validation_still_applies_with_every_gate_off() -> None:
    settings = EstimatorSettings(**NO_GATES)
    assert dataclasses.asdict(settings)["max_landmarks"] == 0
    est = Estimator(settings)
    with pytest.raises(EstimationError):
        est.predict(v=math.nan, w=0.0, dt=0.1, stamp=0.0)  # NaN is refused regardless


@pytest.mark.parametrize("seed", [4, 8, 13])
def test_every_state_the_guarded_filter_builds_is_finite_under_extreme_inputs(seed) -> None:
    """The estimator's messages take its covariance as finite without summing it
    (``finite_by_construction``: the guard's proof). Checked here independently, entry by
    entry, after every step of a clean run with every gate off and extreme inputs mixed in
    at random: magnitudes up to the guard's limits and past them."""
    rng = np.random.default_rng(seed)
    est = Estimator(EstimatorSettings(**NO_GATES))
    stream = clean_stream()
    states = 0
    for i, message in enumerate(stream):
        apply(est, message)
        if i % 3 == 0:
            t = float(message.stamp)
            scale = 10.0 ** rng.uniform(0, 300)
            bad = (odometry(t, v=float(rng.choice([-1, 1]) * scale), dt=float(rng.uniform(0, 5)))
                   if rng.random() < 0.5 else
                   batch(t, [int(rng.integers(1, 40))], [scale], [float(rng.uniform(-4, 4))]))
            apply(est, bad)
        state = est.to_state(seq=i + 1, stamp=float(message.stamp), step="update")
        assert np.isfinite(state.covariance).all(), i
        assert np.isfinite(state.pose).all() and np.isfinite(state.landmarks).all(), i
        states += 1
    assert states == len(stream) and sum(est.refusals.values()) > 0  # extreme steps were refused


def test_a_proven_array_skips_only_its_own_finiteness_check() -> None:
    bad = np.eye(3)
    bad[1, 1] = np.nan
    bad.flags.writeable = False
    other = bad.copy()
    other.flags.writeable = False

    def state(cov: np.ndarray) -> SlamState:
        return SlamState(robot="r1", seq=1, stamp=0.0, step="predict", pose=np.zeros(3),
                         landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)),
                         covariance=cov)

    with finite_by_construction(bad):
        proven = state(bad)  # taken as proven (the producer's word), not read
        with pytest.raises(MessageError, match="finite"):
            state(other)  # another array is checked as ever
        seen: list[BaseException] = []
        worker = threading.Thread(target=lambda: _refused(state, bad, seen))
        worker.start()
        worker.join()
        assert seen and "finite" in str(seen[0])  # other threads do not share the proof
    with pytest.raises(MessageError, match="finite"):
        state(bad)  # outside the block, checked
    with pytest.raises(MessageError, match="finite"):
        SlamState.from_bytes(proven.to_bytes())  # consumers check in full


def _refused(build, cov, seen: list) -> None:
    try:
        build(cov)
    except MessageError as exc:
        seen.append(exc)
