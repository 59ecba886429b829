"""The First-Estimates-Jacobian EKF (``--linearisation fej``) against a dense textbook FEJ-EKF
written here (Huang, Mourikis & Roumeliotis, IJRR 2010), and the property it exists for.

The oracle keeps its own linearisation points — the robot's propagated position and each
landmark's first estimate — builds the full N×N F, the full 2×N H and the full augmentation
Jacobian at them, and multiplies dense matrices; it shares no code with
services/slam/ekf.py or linearisation.py. The property: with N(k) the unobservable
directions at those points (global x, y and rotation), the information Nᵀ P⁻¹ N never grows
under FEJ, while the standard EKF's does (the spurious information of Huang et al.).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.services.slam import ekf
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings

SIG_V, SIG_W, SIG_R, SIG_B = 0.08, 0.06, 0.05, 0.02
RTOL = 1e-10


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def J(p: np.ndarray) -> np.ndarray:
    """J p with J = [[0, −1], [1, 0]]: the derivative of a point under a rotation."""
    return np.array([-p[1], p[0]])


class DenseFej:
    """A dense FEJ-EKF: full Jacobians at the first estimates (its own bookkeeping)."""

    def __init__(self, x0: np.ndarray, P0: np.ndarray) -> None:
        self.x = x0.astype(float).copy()
        self.P = P0.astype(float).copy()
        self.robot_point = self.x[:2].copy()  # p̂(k|k−1)
        self.first: list[np.ndarray] = []
        self.ids: list[int] = []

    def predict(self, v: float, w: float, dt: float) -> None:
        x, N = self.x, self.x.size
        th = x[2]
        new = x.copy()
        new[0] += v * dt * math.cos(th)
        new[1] += v * dt * math.sin(th)
        new[2] = wrap(th + w * dt)
        F = np.eye(N)
        F[0:2, 2] = J(new[:2] - self.robot_point)  # between the propagated estimates
        G = np.zeros((N, 2))
        G[0, 0], G[1, 0], G[2, 1] = dt * math.cos(th), dt * math.sin(th), dt
        self.P = F @ self.P @ F.T + G @ np.diag([SIG_V ** 2, SIG_W ** 2]) @ G.T
        self.x = new
        self.robot_point = new[:2].copy()

    def observe(self, lid: int, z: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        if lid not in self.ids:
            self.initialise(lid, z)
            return None
        return self.update(self.ids.index(lid), z)

    def jacobian(self, j: int) -> np.ndarray:
        """H (2 × N) of landmark j's measurement, at the first estimates."""
        a = 3 + 2 * j
        e = self.first[j] - self.robot_point
        q = float(e @ e)
        r = math.sqrt(q)
        H = np.zeros((2, self.x.size))
        H[:, 0:3] = [[-e[0] / r, -e[1] / r, 0.0], [e[1] / q, -e[0] / q, -1.0]]
        H[:, a:a + 2] = [[e[0] / r, e[1] / r], [-e[1] / q, e[0] / q]]
        return H

    def update(self, j: int, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The EKF update with landmark j's measurement z (H from :meth:`jacobian`)."""
        x = self.x
        a = 3 + 2 * j
        d = x[a:a + 2] - x[:2]
        h = np.array([math.hypot(*d), math.atan2(d[1], d[0]) - x[2]])
        H = self.jacobian(j)
        nu = z - h
        nu[1] = wrap(nu[1])
        S = H @ self.P @ H.T + np.diag([SIG_R ** 2, SIG_B ** 2])
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = x + K @ nu
        self.x[2] = wrap(self.x[2])
        P = self.P - K @ S @ K.T
        self.P = 0.5 * (P + P.T)
        return nu, S

    def initialise(self, lid: int, z: np.ndarray) -> None:
        x, N = self.x, self.x.size
        r, phi = z
        al = x[2] + phi
        m = x[:2] + r * np.array([math.cos(al), math.sin(al)])
        Y = np.eye(N + 2)
        Y[N:, :N] = 0.0
        Y[N:, 0:2] = np.eye(2)
        Y[N:, 2] = J(m - self.robot_point)  # Gv at the robot's propagated position
        Y[N:, N:] = [[math.cos(al), -r * math.sin(al)], [math.sin(al), r * math.cos(al)]]
        big = np.zeros((N + 2, N + 2))
        big[:N, :N] = self.P
        big[N:, N:] = np.diag([SIG_R ** 2, SIG_B ** 2])
        self.x = np.concatenate([x, m])
        self.P = Y @ big @ Y.T
        self.first.append(m.copy())
        self.ids.append(lid)

    def null_space(self) -> np.ndarray:
        """N(k): columns global x, global y, rotation about the map origin."""
        rows = [np.column_stack([np.eye(2), J(self.robot_point)]), np.array([[0.0, 0, 1]])]
        rows += [np.column_stack([np.eye(2), J(f)]) for f in self.first]
        return np.vstack(rows)


def settings(linearisation: str = "fej") -> EstimatorSettings:
    return EstimatorSettings(sigma_v=SIG_V, sigma_w=SIG_W, sigma_range=SIG_R,
                             sigma_bearing=SIG_B, linearisation=linearisation,
                             initial_pose_sigma=(0.01, 0.01, 0.005))


def assert_close(actual: np.ndarray, expected: np.ndarray, what: str) -> None:
    scale = max(1.0, float(np.max(np.abs(expected))))
    err = float(np.max(np.abs(actual - expected)))
    assert err <= RTOL * scale, f"{what}: max error {err:.3e} (scale {scale:.2e})"


def world(rng: np.random.Generator, n: int = 10) -> np.ndarray:
    return rng.uniform(-4, 4, size=(n, 2))


def measure(rng: np.random.Generator, pose: np.ndarray, lm: np.ndarray) -> np.ndarray:
    d = lm - pose[:2]
    return np.array([math.hypot(*d) + rng.normal(0, SIG_R),
                     wrap(math.atan2(d[1], d[0]) - pose[2] + rng.normal(0, SIG_B))])


def drive(seed: int, steps: int, est: Estimator, oracle: DenseFej | None = None,
          every=None) -> None:
    """A robot wandering among landmarks: odometry every step, a batch every third step
    (each landmark within 3 m, new ones initialised, known ones updated)."""
    rng = np.random.default_rng(seed)
    lms = world(rng)
    true = np.zeros(3)
    for k in range(steps):
        v, w, dt = rng.uniform(0.2, 0.8), rng.normal(0, 0.6), 0.1
        true = np.array([true[0] + v * dt * math.cos(true[2]),
                         true[1] + v * dt * math.sin(true[2]), wrap(true[2] + w * dt)])
        vm, wm = v + rng.normal(0, SIG_V), w + rng.normal(0, SIG_W)
        est.predict(v=vm, w=wm, dt=dt, stamp=k * dt)
        if oracle is not None:
            oracle.predict(vm, wm, dt)
        if every is not None:
            every(est, "predict")
        if k % 3:
            continue
        seen = [i for i in rng.permutation(len(lms)) if np.hypot(*(lms[i] - true[:2])) < 3.0]
        zs = np.array([measure(rng, true, lms[i]) for i in seen]).reshape(-1, 2)
        rep = est.observe(ids=np.array(seen, dtype=np.int64) + 6, ranges=zs[:, 0],
                          bearings=zs[:, 1], stamp=k * dt)
        if oracle is not None:
            # FEJ maps a batch's new landmarks after its updates (docs/estimator.md)
            known = [(i, z) for i, z in zip(seen, zs, strict=True) if i + 6 in oracle.ids]
            new = [(i, z) for i, z in zip(seen, zs, strict=True) if i + 6 not in oracle.ids]
            expected = [oracle.observe(i + 6, z) for i, z in known + new]
            got = [e for e in expected if e is not None]
            for (nu, S), nu_k, S_k in zip(got, rep.innovations, rep.innovation_covariances,
                                          strict=True):
                assert_close(nu_k, nu, f"innovation at step {k}")
                assert_close(S_k, S, f"S at step {k}")
        if every is not None:
            every(est, "update")


@pytest.mark.parametrize("seed", range(6))
def test_fej_estimator_equals_the_dense_fej_ekf(seed: int) -> None:
    est = Estimator(settings())
    oracle = DenseFej(np.zeros(3), np.diag([0.01, 0.01, 0.005]) ** 2)
    checked = []

    def compare(e: Estimator, step: str) -> None:
        assert list(e.landmark_ids) == oracle.ids
        N = 3 + 2 * e.n
        assert_close(np.concatenate([e.pose, e.landmarks.reshape(-1)]), oracle.x[:N], "x")
        assert_close(e.covariance, oracle.P, "P")
        checked.append(e.n)

    drive(seed, 150, est, oracle, every=compare)
    assert max(checked) >= 5  # landmarks were mapped and updated over and over


def test_fej_and_standard_differ_and_standard_is_unchanged_by_the_option() -> None:
    """The option changes the Jacobians only when asked for: the standard estimator is the
    same with the setting written out, and FEJ gives another (close) estimate."""
    a, b, c = (Estimator(settings("standard")), Estimator(EstimatorSettings(
        sigma_v=SIG_V, sigma_w=SIG_W, sigma_range=SIG_R, sigma_bearing=SIG_B,
        initial_pose_sigma=(0.01, 0.01, 0.005))), Estimator(settings("fej")))
    for e in (a, b, c):
        drive(3, 120, e)
    assert np.array_equal(a.covariance, b.covariance) and np.array_equal(a.pose, b.pose)
    assert not np.array_equal(a.covariance, c.covariance)
    assert np.max(np.abs(a.pose - c.pose)) < 0.2
    assert "linearisation.fej" in c.diagnostics() and "linearisation.fej" not in a.diagnostics()


@pytest.mark.parametrize("at_robot", [(0.3, -0.2), (1.0, 2.0)])
def test_kernels_with_linearisation_points_equal_dense(at_robot: tuple[float, float]) -> None:
    """Each kernel alone, with explicit points, against the dense formulas."""
    rng = np.random.default_rng(17)
    n = 6
    N = 3 + 2 * n
    x = np.concatenate([[0.2, -0.1, 0.4], rng.uniform(-4, 4, 2 * n)])
    A = rng.normal(scale=0.1, size=(N, N))
    P = A @ A.T + 1e-4 * np.eye(N)
    cap = N + 4
    # predict
    xb, L = np.zeros(cap), np.zeros((cap, cap))
    xb[:N], L[:N, :N] = x, np.tril(P)
    ws = ekf.Workspace.for_capacity(cap)
    ekf.predict(xb, L, n, v=0.7, w=0.3, dt=0.1, var_v=SIG_V ** 2, var_w=SIG_W ** 2,
                at=at_robot, guard=ekf.Guard(), ws=ws)
    new = x[:3] + [0.07 * math.cos(x[2]), 0.07 * math.sin(x[2]), 0.03]
    F = np.eye(N)
    F[0:2, 2] = J(new[:2] - np.array(at_robot))
    G = np.zeros((N, 2))
    G[0, 0], G[1, 0], G[2, 1] = 0.1 * math.cos(x[2]), 0.1 * math.sin(x[2]), 0.1
    expected = F @ P @ F.T + G @ np.diag([SIG_V ** 2, SIG_W ** 2]) @ G.T
    assert_close(xb[:3], new, "x after predict")
    assert_close(ekf.symmetric(L, N), expected, "P after predict")
    # update of landmark 2 with H at (robot point, first estimate)
    first = x[7:9] + [0.15, -0.1]
    xb[:N], L[:N, :N] = x, np.tril(P)
    z = np.array([2.0, 0.3])
    out = ekf.update(xb, L, n, 2, z_range=z[0], z_bearing=z[1], var_range=SIG_R ** 2,
                     var_bearing=SIG_B ** 2, ws=ws, at=(*at_robot, *first))
    e = first - np.array(at_robot)
    q = float(e @ e)
    r = math.sqrt(q)
    H = np.zeros((2, N))
    H[:, 0:3] = [[-e[0] / r, -e[1] / r, 0.0], [e[1] / q, -e[0] / q, -1.0]]
    H[:, 7:9] = [[e[0] / r, e[1] / r], [-e[1] / q, e[0] / q]]
    d = x[7:9] - x[:2]
    nu = z - [math.hypot(*d), math.atan2(d[1], d[0]) - x[2]]
    nu[1] = wrap(nu[1])
    S = H @ P @ H.T + np.diag([SIG_R ** 2, SIG_B ** 2])
    K = P @ H.T @ np.linalg.inv(S)
    assert_close(np.array(out[:2]), nu, "ν")
    assert_close(np.array([[out[2], out[3]], [out[3], out[4]]]), S, "S")
    assert_close(xb[:N], x + K @ nu, "x after update")
    assert_close(ekf.symmetric(L, N), P - K @ S @ K.T, "P after update")
    # initialise with Gv's θ column J (m − robot point)
    xb[:N], L[:N, :N] = x, np.tril(P)
    ekf.initialise(xb, L, n, z_range=1.5, z_bearing=-0.4, var_range=SIG_R ** 2,
                   var_bearing=SIG_B ** 2, ws=ws, at=at_robot)
    al = x[2] - 0.4
    m = x[:2] + 1.5 * np.array([math.cos(al), math.sin(al)])
    Y = np.eye(N + 2)
    Y[N:, :N] = 0.0
    Y[N:, 0:2] = np.eye(2)
    Y[N:, 2] = J(m - np.array(at_robot))
    Y[N:, N:] = [[math.cos(al), -1.5 * math.sin(al)], [math.sin(al), 1.5 * math.cos(al)]]
    big = np.zeros((N + 2, N + 2))
    big[:N, :N], big[N:, N:] = P, np.diag([SIG_R ** 2, SIG_B ** 2])
    assert_close(xb[N:N + 2], m, "new landmark")
    assert_close(ekf.symmetric(L, N + 2), Y @ big @ Y.T, "P after initialise")


def information(P: np.ndarray, Nmat: np.ndarray) -> np.ndarray:
    return Nmat.T @ np.linalg.solve(P, Nmat)


@pytest.mark.parametrize("seed", range(3))
def test_fej_never_gains_information_in_the_unobservable_directions(seed: int) -> None:
    """Nᵀ P⁻¹ N (dense inverse, N at the oracle's own points) is non-increasing in the
    Loewner order along an FEJ run, to rounding; the standard EKF's grows."""
    for linearisation in ("fej", "standard"):
        est = Estimator(settings(linearisation))
        oracle = DenseFej(np.zeros(3), np.diag([0.01, 0.01, 0.005]) ** 2)
        infos: list[np.ndarray] = []

        def record(e: Estimator, step: str, oracle: DenseFej = oracle,
                   infos: list[np.ndarray] = infos) -> None:
            # the oracle's bookkeeping follows the estimator's states: the position after
            # each predict, each landmark's estimate in the first state that has it
            if step == "predict":
                oracle.robot_point = e.pose[:2].copy()
            for lid, (mx, my) in zip(e.landmark_ids[len(oracle.ids):],
                                     e.landmarks[len(oracle.ids):], strict=True):
                oracle.ids.append(int(lid))
                oracle.first.append(np.array([mx, my]))
            infos.append(information(e.covariance, oracle.null_space()))

        drive(seed, 150, est, every=record)
        growth = []
        for a, b in zip(infos, infos[1:], strict=False):
            scale = np.sqrt(np.outer(np.diag(a), np.diag(a)))
            growth.append(float(np.linalg.eigvalsh((b - a) / scale).max()))
        if linearisation == "fej":
            assert max(growth) < 1e-7, max(growth)
        else:
            assert max(growth) > 1e-3, max(growth)


def test_restore_keeps_the_first_estimates() -> None:
    """A checkpoint restored with its linearisation points continues bit for bit; without
    them, the state's estimates become the first estimates (another, still FEJ, filter)."""
    a = Estimator(settings())
    drive(5, 90, a)
    state = a.to_state(seq=1, stamp=9.0, step="predict")
    points = a.linearisation_points()
    assert points is not None and len(points["landmarks"]) == a.n
    b, c = Estimator(settings()), Estimator(settings())
    b.restore(state, linearisation=points)
    c.restore(state)
    rng = np.random.default_rng(1)
    for e in (a, b, c):
        e.predict(v=0.5, w=0.1, dt=0.1, stamp=9.1)
    lid = int(a.landmark_ids[0])
    z = (float(rng.uniform(1, 2)), 0.2)
    for e in (a, b, c):
        e.observe(ids=[lid], ranges=[z[0]], bearings=[z[1]], stamp=9.1)
    assert np.array_equal(a.covariance, b.covariance) and np.array_equal(a.pose, b.pose)
    assert not np.array_equal(a.covariance, c.covariance)


def test_a_batchs_new_landmarks_are_mapped_after_its_updates_and_published_as_first() -> None:
    """FEJ maps new landmarks after the batch's updates, from the posterior pose: the state
    publishes each new landmark at its first estimate (what a monitor takes as its
    linearisation point); two sightings of one new landmark in a batch are one, fused."""
    est = Estimator(settings())
    drive(2, 40, est)
    known = [int(i) for i in est.landmark_ids[:2]]
    before = est.landmarks[:2].copy()
    rep = est.observe(ids=[known[0], 90, known[1], 91, 91], ranges=[1.5, 2.0, 1.8, 1.0, 1.1],
                      bearings=[0.3, -0.5, 1.0, 0.2, 0.26], stamp=4.0)
    assert list(rep.new_ids) == [90, 91] and list(rep.innovation_ids) == known
    assert list(rep.assigned_ids) == [known[0], 90, known[1], 91, 91]
    assert not np.array_equal(est.landmarks[:2], before)  # the updates were applied …
    points = est.linearisation_points()
    assert points is not None
    pose = est.pose  # … before the new landmarks were mapped from the posterior pose
    for lid, z_r, z_b in ((90, 2.0, -0.5), (91, 1.05, 0.23)):
        k = list(est.landmark_ids).index(lid)
        expected = pose[:2] + z_r * np.array([math.cos(pose[2] + z_b), math.sin(pose[2] + z_b)])
        assert_close(est.landmarks[k], expected, f"landmark {lid}")
        assert points["landmarks"][lid] == est.landmarks[k].tolist()  # published = first
    # the fused one has the covariance of one sighting with R/2
    k = 3 + 2 * list(est.landmark_ids).index(91)
    al = pose[2] + 0.23
    Gz = np.array([[math.cos(al), -1.05 * math.sin(al)], [math.sin(al), 1.05 * math.cos(al)]])
    Gv = np.column_stack([np.eye(2), J(np.array(expected) - np.array(points["robot"]))])
    P = est.covariance
    fused = Gv @ P[:3, :3] @ Gv.T + Gz @ np.diag([SIG_R ** 2, SIG_B ** 2]) @ Gz.T / 2
    assert_close(P[k:k + 2, k:k + 2], fused, "P of the fused landmark")
