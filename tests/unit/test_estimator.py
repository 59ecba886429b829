"""The Estimator class: ids, association, refusal of bad input, capacity, messages, PSD."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.common.config import load_settings
from slamlens.common.errors import ConfigError, EstimationError
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.services.slam import association, ekf, models
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings

SIG_R, SIG_B = 0.05, 0.02


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def measure(pose: np.ndarray, lm: np.ndarray) -> tuple[float, float]:
    dx, dy = lm[0] - pose[0], lm[1] - pose[1]
    return math.hypot(dx, dy), wrap(math.atan2(dy, dx) - pose[2])


def dense_S(est: Estimator, j: int) -> tuple[np.ndarray, np.ndarray]:
    """(h, S) for landmark j from the full covariance and a dense H (oracle)."""
    x = np.concatenate([est.pose, est.landmarks.reshape(-1)])
    P = est.covariance
    a = 3 + 2 * j
    dx, dy = x[a] - x[0], x[a + 1] - x[1]
    q = dx * dx + dy * dy
    H = np.zeros((2, x.size))
    H[:, 0:3] = [[-dx / math.sqrt(q), -dy / math.sqrt(q), 0], [dy / q, -dx / q, -1]]
    H[:, a:a + 2] = [[dx / math.sqrt(q), dy / math.sqrt(q)], [-dy / q, dx / q]]
    h = np.array([math.sqrt(q), math.atan2(dy, dx) - x[2]])
    return h, H @ P @ H.T + np.diag([SIG_R**2, SIG_B**2])


def snapshot(est: Estimator) -> tuple[np.ndarray, ...]:
    return est.pose, est.landmark_ids, est.landmarks, est.covariance


def assert_same(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> None:
    for u, v in zip(a, b, strict=True):
        assert np.array_equal(u, v)


TRUE_MAP = {3: np.array([2.0, 0.5]), 8: np.array([1.0, -1.5]), 11: np.array([-1.0, 2.0]),
            20: np.array([3.0, 3.0])}


def mapped_estimator(rng: np.random.Generator, rounds: int = 30) -> Estimator:
    """A static robot at the origin that has observed TRUE_MAP ``rounds`` times."""
    est = Estimator(EstimatorSettings())
    pose = np.zeros(3)
    for _ in range(rounds):
        ids, rs, bs = [], [], []
        for lid, lm in TRUE_MAP.items():
            r, b = measure(pose, lm)
            ids.append(lid)
            rs.append(r + rng.normal(0, SIG_R))
            bs.append(wrap(b + rng.normal(0, SIG_B)))
        est.observe(ids=np.array(ids), ranges=rs, bearings=bs, stamp=0.0)
    return est


# ----------------------------------------------------------------------------- ids


def test_unknown_id_initialises_then_known_id_updates() -> None:
    est = Estimator(EstimatorSettings())
    rep = est.observe(ids=np.array([5, 7]), ranges=[2.0, 1.0], bearings=[0.5, -1.0], stamp=1.0)
    assert est.n == 2
    assert list(rep.new_ids) == [5, 7] and list(rep.observed_ids) == [5, 7]
    assert rep.innovation_ids.size == 0 and rep.innovations.shape == (0, 2)
    np.testing.assert_allclose(est.landmarks[0], [2 * math.cos(0.5), 2 * math.sin(0.5)])
    np.testing.assert_allclose(est.landmarks[1], [math.cos(-1.0), math.sin(-1.0)])
    P_before = est.covariance
    h, S = dense_S(est, 0)
    rep = est.observe(ids=np.array([5]), ranges=[2.1], bearings=[0.5], stamp=2.0)
    assert est.n == 2 and list(rep.new_ids) == [] and list(rep.innovation_ids) == [5]
    np.testing.assert_allclose(rep.innovations[0], [2.1 - h[0], wrap(0.5 - h[1])], atol=1e-12)
    np.testing.assert_allclose(rep.innovation_covariances[0], S, rtol=1e-10, atol=1e-15)
    assert est.covariance[3, 3] < P_before[3, 3]


def test_apply_is_predict_for_odometry_and_observe_for_observations() -> None:
    by_kind, by_call = Estimator(EstimatorSettings()), Estimator(EstimatorSettings())
    odo = Odometry(robot="r", stamp=0.1, dt=0.1, v=0.3, w=0.2)
    obs = Observations(robot="r", stamp=0.1, ids=np.array([4]), ranges=np.array([1.5]),
                       bearings=np.array([0.3]))
    assert by_kind.apply(odo) is None
    by_call.predict(v=0.3, w=0.2, dt=0.1, stamp=0.1)
    report = by_kind.apply(obs)
    assert list(report.new_ids) == [4]
    by_call.observe(ids=np.array([4]), ranges=[1.5], bearings=[0.3], stamp=0.1)
    np.testing.assert_array_equal(by_kind.covariance, by_call.covariance)
    np.testing.assert_array_equal(by_kind.landmarks, by_call.landmarks)
    with pytest.raises(EstimationError):  # refused as predict refuses
        by_kind.apply(Odometry(robot="r", stamp=0.2, dt=0.1, v=1e6, w=0.2))


def test_unknown_id_twice_in_a_batch_initialises_once_then_updates() -> None:
    est = Estimator(EstimatorSettings())
    rep = est.observe(ids=[9, 9], ranges=[1.0, 1.02], bearings=[0.0, 0.01], stamp=0.0)
    assert est.n == 1
    assert list(rep.new_ids) == [9] and list(rep.innovation_ids) == [9]
    assert list(rep.observed_ids) == [9] and list(rep.assigned_ids) == [9, 9]


def test_initial_pose_and_sigma() -> None:
    est = Estimator(EstimatorSettings(initial_pose=(1.0, 2.0, 4.0),
                                      initial_pose_sigma=(0.1, 0.2, 0.3)))
    np.testing.assert_allclose(est.pose, [1.0, 2.0, 4.0 - 2 * math.pi])
    np.testing.assert_allclose(est.covariance, np.diag([0.01, 0.04, 0.09]))
    default = Estimator(EstimatorSettings())
    assert np.array_equal(default.pose, np.zeros(3))
    assert np.array_equal(default.covariance, np.zeros((3, 3)))


# ----------------------------------------------------------------------------- association


def test_mahalanobis_all_equals_dense_oracle() -> None:
    rng = np.random.default_rng(1)
    est = mapped_estimator(rng, rounds=3)
    est.predict(v=0.3, w=0.2, dt=1.0, stamp=1.0)  # correlate pose and map
    z = (2.3, 0.4)
    d2 = association.mahalanobis_all(est.store.x, est.store.L, est.n, z_range=z[0], z_bearing=z[1],
                                     var_range=SIG_R**2, var_bearing=SIG_B**2)
    for j in range(est.n):
        h, S = dense_S(est, j)
        nu = np.array([z[0] - h[0], wrap(z[1] - h[1])])
        assert d2[j] == pytest.approx(float(nu @ np.linalg.solve(S, nu)), rel=1e-9)


def test_association_picks_the_right_landmark_and_creates_new_ones() -> None:
    rng = np.random.default_rng(2)
    est = mapped_estimator(rng)
    pose = np.zeros(3)
    right = wrong = other = 0
    for _ in range(200):
        lid = int(rng.choice(list(TRUE_MAP)))
        r, b = measure(pose, TRUE_MAP[lid])
        rep = est.observe(ids=[-1], ranges=[r + rng.normal(0, SIG_R)],
                          bearings=[wrap(b + rng.normal(0, SIG_B))], stamp=1.0)
        got = int(rep.assigned_ids[0])
        if got == lid:
            right += 1
        elif got in TRUE_MAP:
            wrong += 1
        else:
            other += 1
    assert wrong == 0
    assert right >= 190, f"only {right}/200 associated (ambiguous or new: {other})"
    assert est.n == len(TRUE_MAP) + sum(1 for i in est.landmark_ids if i >= 1_000_000)
    # an unseen landmark far from all others becomes a new one with a fresh id ...
    n0 = est.n
    unseen = np.array([-2.5, -2.5])
    r, b = measure(pose, unseen)
    rep = est.observe(ids=[-1], ranges=[r], bearings=[b], stamp=2.0)
    fresh = int(rep.new_ids[0])
    assert est.n == n0 + 1 and fresh >= 1_000_000 and list(rep.assigned_ids) == [fresh]
    # ... which the next anonymous sighting of it matches
    rep = est.observe(ids=[-1], ranges=[r + 0.01], bearings=[b], stamp=3.0)
    assert list(rep.assigned_ids) == [fresh] and list(rep.innovation_ids) == [fresh]


def test_anonymous_ids_count_up_from_the_base_and_skip_taken_ids() -> None:
    est = Estimator(EstimatorSettings(anonymous_id_base=500))
    est.observe(ids=[500], ranges=[1.0], bearings=[0.0], stamp=0.0)
    rep = est.observe(ids=[-1, -1], ranges=[3.0, 3.0], bearings=[1.5, -1.5], stamp=0.0)
    assert list(rep.new_ids) == [501, 502]


def test_ambiguous_observation_is_discarded_without_changing_state() -> None:
    rng = np.random.default_rng(3)
    est = mapped_estimator(rng)
    j = est.index_of(8)
    h, S = dense_S(est, j)
    # range offset δ with d² = δ²·(S⁻¹)_rr = 11.5, between 9.21 and 27.63
    delta = math.sqrt(11.5 / np.linalg.inv(S)[0, 0])
    before = snapshot(est)
    rep = est.observe(ids=[-1], ranges=[h[0] + delta], bearings=[h[1]], stamp=1.0)
    assert rep.rejected == 1 and rep.ambiguous == 1 and list(rep.assigned_ids) == [-1]
    assert_same(before, snapshot(est))
    # just inside the gate it is a match, just beyond the new-landmark threshold a new one
    for d2, kind in ((9.0, "match"), (20.0, "ambiguous"), (28.5, "new")):
        delta = math.sqrt(d2 / np.linalg.inv(S)[0, 0])
        d = association.mahalanobis_all(est.store.x, est.store.L, est.n, z_range=h[0] + delta,
                                        z_bearing=h[1], var_range=SIG_R**2,
                                        var_bearing=SIG_B**2)
        decision = association.decide(d, association.Gates())
        assert decision.kind == kind
        assert decision.d2 == pytest.approx(d2, rel=1e-9)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kwargs", [
    {"v": math.nan, "w": 0.0, "dt": 0.1}, {"v": 0.1, "w": math.inf, "dt": 0.1},
    {"v": 0.1, "w": 0.0, "dt": math.nan}, {"v": 0.1, "w": 0.0, "dt": -0.1},
])
def test_bad_odometry_raises_and_leaves_state_unchanged(kwargs: dict[str, float]) -> None:
    est = mapped_estimator(np.random.default_rng(4), rounds=2)
    before = snapshot(est)
    with pytest.raises(EstimationError):
        est.predict(stamp=1.0, **kwargs)
    assert_same(before, snapshot(est))


@pytest.mark.parametrize("batch", [
    {"ids": [3, 77], "ranges": [1.0, math.nan], "bearings": [0.0, 0.0]},
    {"ids": [3], "ranges": [1.0], "bearings": [math.inf]},
    {"ids": [3, 8], "ranges": [1.0], "bearings": [0.0, 0.1]},
    {"ids": [3], "ranges": [-1.0], "bearings": [0.0]},
    {"ids": [-2], "ranges": [1.0], "bearings": [0.0]},
    {"ids": [1.5], "ranges": [1.0], "bearings": [0.0]},
])
def test_bad_observations_raise_and_leave_state_unchanged(batch: dict[str, list]) -> None:
    est = mapped_estimator(np.random.default_rng(5), rounds=2)
    before = snapshot(est)
    with pytest.raises(EstimationError):
        est.observe(stamp=1.0, **batch)
    assert_same(before, snapshot(est))
    with pytest.raises(EstimationError):
        est.observe(ids=[3], ranges=[1.0], bearings=[0.0], stamp=math.nan)


def test_settings_are_validated_at_load() -> None:
    s = load_settings(EstimatorSettings, None, {"sigma_v": "0.1", "fault": "map-update",
                                                "faulty_features": "3,5"})
    assert s.sigma_v == 0.1 and s.faulty_features == (3, 5)
    with pytest.raises(ConfigError, match="fault"):
        load_settings(EstimatorSettings, None, {"fault": "bogus"})
    with pytest.raises(ConfigError, match="faulty feature"):
        load_settings(EstimatorSettings, None, {"fault": "map-update"})
    with pytest.raises(ConfigError, match="sigma_range"):
        load_settings(EstimatorSettings, None, {"sigma_range": 0.0})
    with pytest.raises(ConfigError, match="gate_chi2"):
        load_settings(EstimatorSettings, None, {"gate_chi2": 30.0})
    with pytest.raises(ConfigError, match="unknown"):
        load_settings(EstimatorSettings, None, {"sigma_vv": 1.0})


# ----------------------------------------------------------------------------- storage


def test_capacity_growth_keeps_values() -> None:
    rng = np.random.default_rng(6)
    small = Estimator(EstimatorSettings(), capacity=1)
    large = Estimator(EstimatorSettings(), capacity=64)
    for k in range(40):
        v, w = rng.uniform(0, 0.5), rng.normal(0, 0.3)
        z = (rng.uniform(0.5, 3), rng.uniform(-1.5, 1.5))
        old = int(rng.integers(0, k)) if k else 0
        zo = measure(small.pose, small.landmarks[small.index_of(old)]) if k else z
        for est in (small, large):
            est.predict(v=v, w=w, dt=0.1, stamp=k)
            est.observe(ids=[k], ranges=[z[0]], bearings=[z[1]], stamp=k)
            est.observe(ids=[old], ranges=[zo[0] + 0.01], bearings=[zo[1]], stamp=k)
    assert small.capacity == 64  # 1 → 2 → 4 … → 64: six doublings, values carried over
    np.testing.assert_allclose(small.covariance, large.covariance, rtol=0, atol=1e-14)
    np.testing.assert_allclose(small.landmarks, large.landmarks, rtol=0, atol=1e-14)
    assert np.array_equal(small.landmark_ids, np.arange(40))


def test_to_state_round_trips() -> None:
    est = mapped_estimator(np.random.default_rng(7), rounds=2)
    est.predict(v=0.2, w=0.1, dt=0.1, stamp=1.0)
    rep = est.observe(ids=[3, 8, -1], ranges=[2.0, 1.8, 6.0], bearings=[0.25, -0.98, 2.5],
                      stamp=1.1)
    state = est.to_state(seq=4, stamp=1.1, step="update", report=rep)
    assert state.n == est.n == len(TRUE_MAP) + 1
    assert list(state.innovation_ids) == [3, 8] and state.innovations.shape == (2, 2)
    assert list(state.new_ids) == [1_000_000]
    np.testing.assert_array_equal(state.covariance, est.covariance)
    back = SlamState.from_bytes(state.to_bytes())  # with the symmetry check
    assert back == state
    plain = Estimator(EstimatorSettings(publish_innovations=False))
    init = plain.to_state(seq=0, stamp=0.0, step="init")
    assert init.innovations is None and init.n == 0 and init.covariance.shape == (3, 3)
    assert SlamState.from_bytes(init.to_bytes()) == init


def test_covariance_stays_symmetric_psd_over_1000_random_steps() -> None:
    rng = np.random.default_rng(8)
    est = Estimator(EstimatorSettings(initial_pose_sigma=(0.01, 0.01, 0.01)))
    truth_pose = np.zeros(3)
    world = {i: rng.uniform(-6, 6, 2) for i in range(40)}
    worst = 0.0
    for k in range(1000):
        v, w = rng.uniform(0, 1), rng.normal(0, 0.5)
        truth_pose = models.motion(truth_pose, v=v, w=w, dt=0.1)
        est.predict(v=v + rng.normal(0, 0.05), w=w + rng.normal(0, 0.05), dt=0.1, stamp=k)
        seen = [i for i, m in world.items() if measure(truth_pose, m)[0] < 4.0]
        picks = rng.permutation(seen)[:5]
        ids, rs, bs = [], [], []
        for i in picks:
            r, b = measure(truth_pose, world[int(i)])
            ids.append(int(i) if rng.random() < 0.8 else -1)
            rs.append(max(0.0, r + rng.normal(0, SIG_R)))
            bs.append(wrap(b + rng.normal(0, SIG_B)))
        est.observe(ids=np.array(ids, dtype=np.int64), ranges=rs, bearings=bs, stamp=k)
        P = est.covariance
        assert np.array_equal(P, P.T)
        assert np.array_equal(est.pose_covariance, P[:3, :3])
        eig = np.linalg.eigvalsh(P)
        worst = min(worst, float(eig[0] / eig[-1]))
    assert est.n >= 20
    assert worst > -1e-12, f"P lost positive semi-definiteness: λmin/λmax = {worst:.3e}"


# ----------------------------------------------------------------------------- consistency


def test_monte_carlo_single_update_is_consistent() -> None:
    """Truth drawn from the prior, z simulated: posterior NEES averages to the dimension."""
    rng = np.random.default_rng(9)
    n = 3
    N = 3 + 2 * n
    mean = np.array([0.0, 0.0, 0.2, 2.0, 0.5, 1.5, -1.0, 3.0, 2.0])
    A = rng.normal(scale=0.02, size=(N, N))
    P = A @ A.T + np.diag([1e-4, 1e-4, 1e-5] + [4e-4] * (2 * n))
    chol = np.linalg.cholesky(P)
    trials = 3000
    nees_all, nees_pose, nees_lm, nis = [], [], [], []
    ws = ekf.Workspace.for_capacity(N)
    for _ in range(trials):
        truth = mean + chol @ rng.normal(size=N)
        z = np.array(measure(truth[:3], truth[3:5])) + rng.normal(0, [SIG_R, SIG_B])
        x = mean.copy()
        L = ekf.lower_from_symmetric(P)
        nu_r, nu_b, s00, s01, s11 = ekf.update(x, L, n, 0, z_range=z[0], z_bearing=wrap(z[1]),
                                               var_range=SIG_R**2, var_bearing=SIG_B**2, ws=ws)
        Pp = ekf.symmetric(L, N)
        e = truth - x
        e[2] = wrap(e[2])
        nees_all.append(e @ np.linalg.solve(Pp, e))
        nees_pose.append(e[:3] @ np.linalg.solve(Pp[:3, :3], e[:3]))
        nees_lm.append(e[3:5] @ np.linalg.solve(Pp[3:5, 3:5], e[3:5]))
        nu = np.array([nu_r, nu_b])
        nis.append(nu @ np.linalg.solve(np.array([[s00, s01], [s01, s11]]), nu))
    for values, dof in ((nees_all, N), (nees_pose, 3), (nees_lm, 2), (nis, 2)):
        m = float(np.mean(values))
        band = 4 * math.sqrt(2 * dof / trials)  # 4σ of the mean of χ²_dof over the trials
        assert abs(m - dof) < band, f"mean {m:.3f} for {dof} dof (±{band:.3f})"


@pytest.mark.parametrize("fault", ["none", "cross-covariance", "map-update"])
def test_published_covariance_is_the_full_symmetric_matrix_after_every_event(
        fault: str) -> None:
    """A state after predicts only reuses the last published covariance and rewrites the
    robot rows/columns (P_mm untouched by a predict, docs/estimator.md): it must equal the matrix
    materialised from scratch, bit for bit, whatever the planted fault."""
    from slamlens.services.slam.sim import Simulator
    from slamlens.services.slam.world import load_world

    settings = EstimatorSettings() if fault == "none" else EstimatorSettings(
        fault=fault, faulty_features=(3, 7))
    est = Estimator(settings)
    previous = None
    checked = {"predict": 0, "update": 0}
    for k, message in enumerate(Simulator(load_world("paper"), seed=4, loops=1).events()):
        kind = type(message).__name__
        if kind == "Odometry":
            est.predict(v=message.v, w=message.w, dt=message.dt, stamp=message.stamp)
            step = "predict"
        elif kind == "Observations":
            est.observe(ids=message.ids, ranges=message.ranges, bearings=message.bearings,
                        stamp=message.stamp)
            step = "update"
        else:
            continue
        state = est.to_state(seq=k, stamp=message.stamp, step=step)
        assert np.array_equal(state.covariance, est.covariance)  # from scratch
        assert np.array_equal(state.covariance, state.covariance.T)
        assert not state.covariance.flags.writeable
        if previous is not None:  # a new buffer each time: earlier states stay as they were
            assert not np.shares_memory(previous.covariance, state.covariance)
        previous = state
        checked[step] += 1
    assert checked["predict"] > 100 and checked["update"] > 100


def test_covariance_buffers_are_recycled_only_when_nothing_holds_them() -> None:
    """The estimator reuses a covariance buffer of an earlier state only once no state,
    array or view refers to it: a state kept by a caller never changes under it."""
    est = Estimator(EstimatorSettings())
    est.observe(ids=[1, 2, 3], ranges=[1.0, 1.5, 2.0], bearings=[0.2, -0.3, 0.5], stamp=0.1)
    kept = est.to_state(seq=1, stamp=0.1, step="update")
    snapshot = np.array(kept.covariance)
    view = kept.covariance[:, 0:3]  # the robot columns: every predict changes them
    del kept
    for k in range(10):  # nothing holds these: their buffers go round
        est.predict(v=0.2, w=0.1, dt=0.1, stamp=0.2 + 0.1 * k)
        state = est.to_state(seq=2 + k, stamp=0.2 + 0.1 * k, step="predict")
        assert not np.shares_memory(state.covariance, view)
        del state
    assert est.published.buffers.reused >= 5
    assert np.array_equal(view, snapshot[:, 0:3])  # the view kept its buffer as it was
