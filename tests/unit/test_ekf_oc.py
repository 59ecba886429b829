"""Observability-Constrained Jacobians (``--linearisation oc``) against a dense textbook
OC-EKF written here, and the property it exists for.

The oracle keeps FEJ's points (the robot's propagated position, each landmark's first
estimate) for F, the augmentation Jacobian and N; it evaluates each H at the latest
estimates and makes it blind to N with a least-squares projection on the rows of N that H
touches (H* = H − H U U⁺, U⁺ from numpy's pseudo-inverse), then runs the dense EKF
equations. It shares no code with services/slam/ekf.py or linearisation.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.services.slam import ekf
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings
from tests.unit.test_ekf_fej import DenseFej

SIG_V, SIG_W, SIG_R, SIG_B = 0.08, 0.06, 0.05, 0.02
RTOL = 1e-10
P0 = np.diag([0.01, 0.01, 0.005]) ** 2


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def rot(p: np.ndarray) -> np.ndarray:
    """J p, J = [[0, −1], [1, 0]]: how a point moves under a rotation about the origin."""
    return np.array([-p[1], p[0]])


def h_at(robot: np.ndarray, landmark: np.ndarray, theta: float) -> np.ndarray:
    """h = (range, bearing) of ``landmark`` from a robot at (robot, theta)."""
    d = landmark - robot
    return np.array([math.hypot(*d), math.atan2(d[1], d[0]) - theta])


def jacobian(f, x: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """Central differences (the oracle's H: no hand-written derivative)."""
    cols = []
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = eps
        a, b = f(x + e), f(x - e)
        d = a - b
        d[1] = wrap(d[1])
        cols.append(d / (2 * eps))
    return np.column_stack(cols)


class DenseOc(DenseFej):
    """A dense OC-EKF: DenseFej's F, Gv and points, and H at the estimates projected onto
    H N = 0 (the only difference: :meth:`jacobian`)."""

    def __init__(self) -> None:
        super().__init__(np.zeros(3), P0)

    def constrained_h(self, j: int) -> tuple[np.ndarray, list[int]]:
        """H on the five columns (x, y, θ, mx, my) it touches, and those columns."""
        a = 3 + 2 * j
        cols = [0, 1, 2, a, a + 1]
        H = jacobian(lambda s: h_at(s[:2], s[3:5], s[2]), self.x[cols])
        U = np.vstack([np.column_stack([np.eye(2), rot(self.robot_point)]), [[0, 0, 1]],
                       np.column_stack([np.eye(2), rot(self.first[j])])])
        return H - H @ U @ np.linalg.pinv(U), cols

    def jacobian(self, j: int) -> np.ndarray:
        h5, cols = self.constrained_h(j)
        H = np.zeros((2, self.x.size))
        H[:, cols] = h5
        return H


def settings(linearisation: str = "oc") -> EstimatorSettings:
    return EstimatorSettings(sigma_v=SIG_V, sigma_w=SIG_W, sigma_range=SIG_R,
                             sigma_bearing=SIG_B, linearisation=linearisation,
                             initial_pose_sigma=(0.01, 0.01, 0.005))


def close(actual: np.ndarray, expected: np.ndarray, what: str, rtol: float = RTOL) -> None:
    scale = max(1.0, float(np.max(np.abs(expected))))
    err = float(np.max(np.abs(np.asarray(actual) - expected)))
    assert err <= rtol * scale, f"{what}: max error {err:.3e} (scale {scale:.2e})"


def drive(seed: int, steps: int, est: Estimator, oracle: DenseOc | None = None,
          every=None, odometry_bias: float = 0.0) -> None:
    """A robot wandering among ten landmarks: odometry every step, a batch every third
    (landmarks within 3 m). ``odometry_bias`` makes first estimates drift from the latest
    ones, so OC's H differs from FEJ's."""
    rng = np.random.default_rng(seed)
    lms = rng.uniform(-4, 4, size=(10, 2))
    true = np.zeros(3)
    for k in range(steps):
        v, w, dt = rng.uniform(0.2, 0.8), rng.normal(0, 0.6), 0.1
        true = np.array([true[0] + v * dt * math.cos(true[2]),
                         true[1] + v * dt * math.sin(true[2]), wrap(true[2] + w * dt)])
        vm, wm = v + rng.normal(0, SIG_V), w + rng.normal(0, SIG_W) + odometry_bias
        est.predict(v=vm, w=wm, dt=dt, stamp=k * dt)
        if oracle is not None:
            oracle.predict(vm, wm, dt)
        if every is not None:
            every(est, "predict")
        if k % 3:
            continue
        seen = [i for i in rng.permutation(10) if np.hypot(*(lms[i] - true[:2])) < 3.0]
        zs = np.array([h_at(true[:2], lms[i], true[2]) + rng.normal(0, [SIG_R, SIG_B])
                       for i in seen]).reshape(-1, 2)
        rep = est.observe(ids=np.array(seen, dtype=np.int64) + 6, ranges=zs[:, 0],
                          bearings=zs[:, 1], stamp=k * dt)
        if oracle is not None:  # a batch's new landmarks are mapped after its updates
            known = [(i, z) for i, z in zip(seen, zs, strict=True) if i + 6 in oracle.ids]
            for (i, z), nu_k, S_k in zip(known, rep.innovations,
                                         rep.innovation_covariances, strict=True):
                nu, S = oracle.update(oracle.ids.index(i + 6), z)
                close(nu_k, nu, f"innovation at step {k}", 1e-7)
                close(S_k, S, f"S at step {k}", 1e-7)
            for i, z in zip(seen, zs, strict=True):
                if i + 6 not in oracle.ids:
                    oracle.initialise(i + 6, z)
        if every is not None:
            every(est, "update")


@pytest.mark.parametrize("seed", range(4))
def test_oc_estimator_equals_the_dense_oc_ekf(seed: int) -> None:
    """x and P after every step equal the dense OC-EKF's (its H from central differences
    and a pseudo-inverse: 1e-7, the differences' own error)."""
    est = Estimator(settings())
    oracle = DenseOc()
    checked = []

    def compare(e: Estimator, step: str) -> None:
        assert list(e.landmark_ids) == oracle.ids
        N = 3 + 2 * e.n
        close(np.concatenate([e.pose, e.landmarks.reshape(-1)]), oracle.x[:N], "x", 1e-7)
        close(e.covariance, oracle.P, "P", 1e-7)
        checked.append(e.n)

    drive(seed, 150, est, oracle, every=compare, odometry_bias=0.05)
    assert max(checked) >= 5


def test_the_update_kernel_projects_h_and_equals_fej_at_fej_points() -> None:
    """ekf.update with ``null``: the dense projection of H at the estimates; and when the
    estimates are the null-space points, FEJ's update exactly (h* = h there)."""
    rng = np.random.default_rng(3)
    n, j = 5, 2
    N = 3 + 2 * n
    x = np.concatenate([[0.2, -0.1, 0.4], rng.uniform(-4, 4, 2 * n)])
    A = rng.normal(scale=0.1, size=(N, N))
    P = A @ A.T + 1e-4 * np.eye(N)
    robot, first = np.array([0.5, 0.1]), x[7:9] + [0.4, -0.3]
    ws = ekf.Workspace.for_capacity(N + 2)

    def run(**points) -> tuple[np.ndarray, np.ndarray, tuple]:
        xb, L = np.zeros(N + 2), np.zeros((N + 2, N + 2))
        xb[:N], L[:N, :N] = x, np.tril(P)
        out = ekf.update(xb, L, n, j, z_range=2.0, z_bearing=0.3, var_range=SIG_R ** 2,
                         var_bearing=SIG_B ** 2, ws=ws, **points)
        return xb[:N].copy(), ekf.symmetric(L, N), out

    xo, Po, out = run(null=(*robot, *first))
    oracle = DenseOc()
    oracle.x, oracle.P, oracle.robot_point = x.copy(), P.copy(), robot
    oracle.first = [np.zeros(2), np.zeros(2), first]
    h5, _ = oracle.constrained_h(j)
    assert np.max(np.abs(h5 @ np.vstack([np.column_stack([np.eye(2), rot(robot)]),
                                         [[0, 0, 1]],
                                         np.column_stack([np.eye(2), rot(first)])]))) < 1e-6
    nu, S = oracle.update(j, np.array([2.0, 0.3]))
    close(np.array(out[:2]), nu, "ν", 1e-7)
    close(np.array([[out[2], out[3]], [out[3], out[4]]]), S, "S", 1e-7)
    close(xo, oracle.x, "x", 1e-7)
    close(Po, oracle.P, "P", 1e-7)
    here = (float(x[0]), float(x[1]), float(x[7]), float(x[8]))
    xa, Pa, _ = run(null=here)
    xb, Pb, _ = run(at=here)
    close(xa, xb, "x at FEJ's points")
    close(Pa, Pb, "P at FEJ's points")


@pytest.mark.parametrize("seed", range(3))
def test_oc_never_gains_information_in_the_unobservable_directions(seed: int) -> None:
    """Nᵀ P⁻¹ N (dense inverse, N at the points the states show) is non-increasing in the
    Loewner order along an OC run with drifting first estimates, to rounding."""
    est = Estimator(settings())
    seen = DenseOc()
    infos: list[np.ndarray] = []

    def record(e: Estimator, step: str) -> None:
        if step == "predict":
            seen.robot_point = e.pose[:2].copy()
        for lid, m in zip(e.landmark_ids[len(seen.ids):], e.landmarks[len(seen.ids):],
                          strict=True):
            seen.ids.append(int(lid))
            seen.first.append(np.array(m, dtype=float))
        Nm = seen.null_space()
        infos.append(Nm.T @ np.linalg.solve(e.covariance, Nm))

    drive(seed, 150, est, every=record, odometry_bias=0.05)
    growth = []
    for a, b in zip(infos, infos[1:], strict=False):
        scale = np.sqrt(np.outer(np.diag(a), np.diag(a)))
        growth.append(float(np.linalg.eigvalsh((b - a) / scale).max()))
    assert max(growth) < 1e-7, max(growth)
    assert len(seen.ids) >= 5


def test_oc_is_its_own_filter_declares_fej_points_and_restores_them() -> None:
    """OC differs from FEJ and from the standard EKF once first estimates drift, says it
    keeps FEJ's points (the monitor's flag), and a checkpoint with its points continues
    bit for bit."""
    runs = {lin: Estimator(settings(lin)) for lin in ("standard", "fej", "oc")}
    for e in runs.values():
        drive(4, 120, e, odometry_bias=0.05)
    oc = runs["oc"]
    assert not np.array_equal(oc.covariance, runs["fej"].covariance)
    assert not np.array_equal(oc.covariance, runs["standard"].covariance)
    assert oc.diagnostics().get("linearisation.fej") == 1.0
    state = oc.to_state(seq=1, stamp=12.0, step="predict")
    b = Estimator(settings())
    b.restore(state, linearisation=oc.linearisation_points())
    lid = int(oc.landmark_ids[0])
    for e in (oc, b):
        e.predict(v=0.5, w=0.1, dt=0.1, stamp=12.1)
        e.observe(ids=[lid], ranges=[1.5], bearings=[0.2], stamp=12.1)
    assert np.array_equal(oc.covariance, b.covariance) and np.array_equal(oc.pose, b.pose)
