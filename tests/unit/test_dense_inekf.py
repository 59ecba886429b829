"""The dense right-invariant EKF (services/harness/dense_inekf.py) that measures the invariant
EKF on real data: its error map T against the group's exponential (finite differences),
its H blind to global translation and rotation at any estimate, and its consistency on
the simulated paper world against the truth (Monte-Carlo)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from slamlens.common.geometry import wrap_angle
from slamlens.services.harness.dense_inekf import DenseInvariantEkf
from slamlens.services.slam.consistency import run
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.world import load_world


def filled(seed: int, landmarks: int = 4) -> DenseInvariantEkf:
    """A filter with a random pose, random landmarks and a random PSD P."""
    rng = np.random.default_rng(seed)
    ekf = DenseInvariantEkf(EstimatorSettings(), capacity=landmarks + 1)
    n = 3 + 2 * landmarks
    ekf.x[:n] = rng.uniform(-5, 5, n)
    ekf.x[2] = rng.uniform(-math.pi, math.pi)
    ekf.n = n
    ekf.index = {10 + k: 3 + 2 * k for k in range(landmarks)}
    A = rng.normal(size=(n, n))
    ekf.P[:n, :n] = A @ A.T * 1e-2 + np.eye(n) * 1e-3
    return ekf


@pytest.mark.parametrize("seed", range(5))
def test_the_standard_error_of_a_small_invariant_one_is_t_times_it(seed: int) -> None:
    ekf = filled(seed)
    before = ekf.x[:ekf.n].copy()
    xi = np.random.default_rng(100 + seed).normal(size=ekf.n) * 1e-6
    T = ekf.transform()
    ekf.retract(xi)  # X ← exp(ξ)·X, written from the group, not from T
    delta = ekf.x[:ekf.n] - before
    delta[2] = wrap_angle(delta[2])
    np.testing.assert_allclose(delta, T @ xi, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_an_update_is_blind_to_global_translation_and_rotation_at_any_estimate(
        seed: int) -> None:
    """No observation, at any estimate, moves the filter along ξ's translations or its
    rotation about the origin: those rows of P stay as they were (here: zero)."""
    ekf = filled(seed)
    n = ekf.n
    N = np.zeros((n, 3))
    N[[0] + list(range(3, n, 2)), 0] = 1.0  # translation in x
    N[[1] + list(range(4, n, 2)), 1] = 1.0  # translation in y
    N[2, 2] = 1.0  # rotation about the origin
    # P with no uncertainty along N: the projection off N
    Q = np.eye(n) - N @ np.linalg.pinv(N)
    ekf.P[:n, :n] = Q @ ekf.P[:n, :n] @ Q.T
    rng = np.random.default_rng(200 + seed)
    for lid in ekf.index:
        ekf.update(lid, float(rng.uniform(1, 6)), float(rng.uniform(-1, 1)))
    np.testing.assert_allclose(N.T @ ekf.P[:n, :n] @ N, 0.0, atol=1e-12)


def nees_of_a_seed(seed: int) -> np.ndarray:
    return run(load_world("paper"), seed=seed, loops=2, make=DenseInvariantEkf).nees


def test_the_filter_is_consistent_on_the_simulated_paper_world() -> None:
    """30 seeds with the world's own noise: the mean pose NEES over the seeds, per event,
    inside the 95 % χ² band nearly everywhere, and 3 on average (independent of the
    filter: the simulator's truth)."""
    seeds = 30
    runs = [nees_of_a_seed(s) for s in range(seeds)]
    length = min(len(r) for r in runs)
    assert length > 200
    mean = np.mean([r[:length] for r in runs], axis=0)
    start = int(np.argmax(np.isfinite(mean)))  # P_vv is 0 until the first step: NaN
    assert start < 5 and np.isfinite(mean[start:]).all()
    mean = mean[start:]
    lo, hi = stats.chi2.ppf([0.025, 0.975], 3 * seeds) / seeds
    assert np.mean((mean >= lo) & (mean <= hi)) > 0.9
    assert 2.7 < float(mean.mean()) < 3.3


@pytest.mark.parametrize("seed", range(5))
def test_in_the_standard_error_an_update_is_the_ekfs_then_two_steps(seed: int) -> None:
    """docs/consistency.md's design for a sparse invariant filter, checked: in the standard
    error the update is the textbook EKF's (H at the latest estimates, with its heading
    column) followed by the exponential retraction of T⁻¹Kν and P ← J P Jᵀ,
    J = I + Ω(x̂⁺ − x̂⁻) eθᵀ."""
    ekf = filled(seed)
    n, lid = ekf.n, 11
    a = ekf.index[lid]
    x0, P0 = ekf.x[:n].copy(), ekf.covariance()
    dx, dy = x0[a] - x0[0], x0[a + 1] - x0[1]
    q, r = dx * dx + dy * dy, math.hypot(dx, dy)
    z = np.array([r + 0.05, wrap_angle(math.atan2(dy, dx) - x0[2] - 0.02)])
    H = np.zeros((2, n))  # the textbook EKF's rows (docs/estimator.md), heading column in
    H[0, [0, 1, 2, a, a + 1]] = [-dx / r, -dy / r, 0.0, dx / r, dy / r]
    H[1, [0, 1, 2, a, a + 1]] = [dy / q, -dx / q, -1.0, -dy / q, dx / q]
    S = H @ P0 @ H.T + np.diag([ekf.noise.range_variance(*z), ekf.noise.var_b])
    K = P0 @ H.T @ np.linalg.inv(S)
    nu = np.array([z[0] - r, wrap_angle(z[1] - (math.atan2(dy, dx) - x0[2]))])
    delta, P_ekf = K @ nu, P0 - K @ S @ K.T
    expected = filled(seed)
    expected.retract(np.linalg.solve(expected.transform(), delta))
    ekf.update(lid, float(z[0]), float(z[1]))
    np.testing.assert_allclose(ekf.x[:n], expected.x[:n], rtol=0, atol=1e-12)
    u = np.zeros(n)
    for t in [0] + list(range(3, n, 2)):
        moved = ekf.x[t:t + 2] - x0[t:t + 2]
        u[t:t + 2] = [-moved[1], moved[0]]  # Ω·Δt
    J = np.eye(n) + np.outer(u, np.eye(n)[2])
    np.testing.assert_allclose(ekf.covariance(), J @ P_ekf @ J.T, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_in_the_standard_error_predict_and_new_landmarks_are_the_ekfs(seed: int) -> None:
    ekf = filled(seed)
    ekf.s = EstimatorSettings(sigma_v=0.1, sigma_w=0.05)
    ekf.noise = type(ekf.noise).of(ekf.s)
    n = ekf.n
    x0, P0 = ekf.x[:n].copy(), ekf.covariance()
    v, w, dt = 0.4, -0.3, 0.2
    ekf.predict(v, w, dt)
    th = x0[2]
    F = np.eye(n)  # the textbook prediction (docs/estimator.md)
    F[0, 2], F[1, 2] = -v * dt * math.sin(th), v * dt * math.cos(th)
    Fu = np.zeros((n, 2))
    Fu[:3] = [[dt * math.cos(th), 0.0], [dt * math.sin(th), 0.0], [0.0, dt]]
    P1 = F @ P0 @ F.T + Fu @ np.diag([0.1 ** 2, 0.05 ** 2]) @ Fu.T
    np.testing.assert_allclose(ekf.covariance(), P1, rtol=1e-9, atol=1e-12)
    zr, zb = 2.5, 0.4
    ekf.initialise(99, zr, zb)
    c, s = math.cos(ekf.x[2] + zb), math.sin(ekf.x[2] + zb)
    G = np.zeros((2, n))
    G[:, :3] = [[1.0, 0.0, -zr * s], [0.0, 1.0, zr * c]]
    Gz = np.array([[c, -zr * s], [s, zr * c]])
    R = np.diag([ekf.noise.range_variance(zr, zb), ekf.noise.var_b])
    P2 = np.block([[P1, P1 @ G.T], [G @ P1, G @ P1 @ G.T + Gz @ R @ Gz.T]])
    np.testing.assert_allclose(ekf.covariance(), P2, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("change", [{"sigma_distance": 0.1}, {"update_iterations": 3},
                                    {"initial_pose_sigma": (0.1, 0.0, 0.0)}])
def test_what_the_dense_filter_does_not_model_is_refused(change: dict[str, object]) -> None:
    with pytest.raises(ValueError, match="not modelled"):
        DenseInvariantEkf(replace(EstimatorSettings(), **change))  # type: ignore[arg-type]
