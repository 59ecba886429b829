"""The iterated update (``update_iterations``) against a dense textbook iterated EKF written
here (Bell & Cathey 1993; Bar-Shalom, Li & Kirubarajan 2001, §10.5) and against scipy's
minimiser of the cost it converges to.

The oracle builds the full 2×N H at each iterate, carries the innovation back to the prior
(ν = z − h(xᵢ) + H (xᵢ − x̂)) and multiplies dense matrices; it shares no code with
services/slam/ekf.py. Converged, the iterate is the maximum a posteriori estimate of one
observation: argmin ½‖x − x̂‖²_P⁻¹ + ½‖z − h(x)‖²_R⁻¹ — which scipy finds on its own.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from slamlens.services.slam import ekf
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings
from tests.unit.test_ekf_oracle import random_state, wrap

SIG_R, SIG_B = 0.05, 0.02
R = np.diag([SIG_R ** 2, SIG_B ** 2])
RTOL = 1e-8
ITERATIONS = 50


def measure(x: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
    """h(x) and its full 2×N Jacobian H at x (landmark j)."""
    a = 3 + 2 * j
    dx, dy = x[a] - x[0], x[a + 1] - x[1]
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    H = np.zeros((2, x.size))
    H[:, 0:3] = [[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]]
    H[:, a:a + 2] = [[dx / r, dy / r], [-dy / q, dx / q]]
    return np.array([r, math.atan2(dy, dx) - x[2]]), H


def constrained(H: np.ndarray, j: int, null: tuple[float, float, float, float]) -> np.ndarray:
    """OC: each row of H on its five columns made orthogonal to the unobservable directions
    (x, y translation; rotation about the origin) at ``null``, by least squares."""
    a = 3 + 2 * j
    cols = [0, 1, 2, a, a + 1]
    rx, ry, mx, my = null
    N5 = np.array([[1, 0, -ry], [0, 1, rx], [0, 0, 1], [1, 0, -my], [0, 1, mx]], float)
    out = H.copy()
    h = H[:, cols]
    out[:, cols] = h - h @ N5 @ np.linalg.solve(N5.T @ N5, N5.T)
    return out


def dense_iterated(x: np.ndarray, P: np.ndarray, j: int, z: np.ndarray, iterations: int,
                   null: tuple[float, float, float, float] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    xi = x.copy()
    for k in range(iterations + (null is not None)):
        h, H = measure(xi, j)
        if null is not None and k == iterations:  # OC: at the MAP point, H made blind
            H = constrained(H, j, null)
        nu = z - h
        nu[1] = wrap(nu[1])
        nu = nu + H @ (xi - x)
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        xi = x + K @ nu
    P2 = P - K @ S @ K.T
    return xi, 0.5 * (P2 + P2.T)


def observation(rng: np.random.Generator, x: np.ndarray, j: int,
                noise: tuple[float, float] = (0.1, 0.05)) -> np.ndarray:
    h, _ = measure(x, j)
    z = h + rng.normal(0, noise)
    z[1] = wrap(z[1])
    return z


def kernel(x: np.ndarray, P: np.ndarray, n: int, j: int, z: np.ndarray, iterations: int,
           **linearisation: tuple[float, float, float, float]
           ) -> tuple[np.ndarray, np.ndarray, tuple[float, ...]]:
    N = x.size
    xb = np.zeros(N + 4)
    xb[:N] = x
    L = np.triu(np.full((N + 4, N + 4), np.nan), 1)  # the kernels never read it
    L[:N, :N] += np.tril(P)
    ws = ekf.Workspace.for_capacity(N + 4)
    out = ekf.update(xb, L, n, j, z_range=z[0], z_bearing=z[1], var_range=SIG_R ** 2,
                     var_bearing=SIG_B ** 2, ws=ws, iterations=iterations, **linearisation)
    return xb[:N].copy(), ekf.symmetric(L, N), out


def assert_close(actual: np.ndarray, expected: np.ndarray, what: str) -> None:
    scale = max(1.0, float(np.max(np.abs(expected))))
    err = float(np.max(np.abs(actual - expected)))
    assert err <= RTOL * scale, f"{what}: max error {err:.3e} (scale {scale:.2e})"


@pytest.mark.parametrize("seed", range(20))
def test_the_converged_update_equals_the_dense_iterated_ekf(seed: int) -> None:
    rng = np.random.default_rng(400 + seed)
    n = int(rng.integers(1, 21))
    x, P = random_state(rng, n)
    j = int(rng.integers(0, n))
    z = observation(rng, x, j)
    xe, Pe = dense_iterated(x, P, j, z, ITERATIONS)
    xk, Pk, out = kernel(x, P, n, j, z, ITERATIONS)
    assert_close(xk, xe, "x")
    assert_close(Pk, Pe, "P")
    # what it returns is the innovation before the update (the monitor's NIS), as the EKF's
    # (OC's: its H at the prior, made blind)
    _, _, first = kernel(x, P, n, j, z, 1)
    assert out == first


@pytest.mark.parametrize("seed", range(10))
def test_oc_iterates_with_constrained_jacobians(seed: int) -> None:
    rng = np.random.default_rng(500 + seed)
    n = int(rng.integers(1, 11))
    x, P = random_state(rng, n)
    j = int(rng.integers(0, n))
    a = 3 + 2 * j
    null = (x[0] + rng.normal(0, 0.2), x[1] + rng.normal(0, 0.2),
            x[a] + rng.normal(0, 0.2), x[a + 1] + rng.normal(0, 0.2))
    z = observation(rng, x, j)
    xe, Pe = dense_iterated(x, P, j, z, ITERATIONS, null=null)
    xk, Pk, _ = kernel(x, P, n, j, z, ITERATIONS, null=null)
    assert_close(xk, xe, "x")
    assert_close(Pk, Pe, "P")


@pytest.mark.parametrize("seed", range(5))
def test_the_converged_update_is_the_map_estimate_scipy_finds(seed: int) -> None:
    """A wide prior (metres, tens of degrees) where one EKF step is far from the MAP and
    Gauss-Newton converges slowly (the iteration may take ~100 steps)."""
    rng = np.random.default_rng(600 + seed)
    n = 3
    x, P = random_state(rng, n, spread=0.5)
    j = int(rng.integers(0, n))
    truth = x + rng.multivariate_normal(np.zeros(x.size), P)
    z = observation(rng, truth, j, noise=(SIG_R, SIG_B))
    whiten_prior = np.linalg.inv(np.linalg.cholesky(P))

    def residuals(v: np.ndarray) -> np.ndarray:
        e = z - measure(v, j)[0]
        e[1] = wrap(e[1])
        return np.concatenate([whiten_prior @ (v - x), e / [SIG_R, SIG_B]])

    def cost(v: np.ndarray) -> float:
        return 0.5 * float(residuals(v) @ residuals(v))

    best = least_squares(residuals, x, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    xk, _, _ = kernel(x, P, n, j, z, 500)
    xekf, _, _ = kernel(x, P, n, j, z, 1)
    assert np.max(np.abs(xk - best)) <= 1e-6
    assert cost(xk) <= cost(best) + 1e-12
    assert cost(xekf) > cost(xk)  # the EKF step stops short of it


@pytest.mark.parametrize(("seed", "iterations"), [(s, k) for s in range(5) for k in (2, 3)])
def test_a_few_iterations_equal_as_many_dense_ones(seed: int, iterations: int) -> None:
    """A budget smaller than convergence needs: the update linearised at the last iterate,
    as the dense IEKF with as many iterations (each step lowers J here, so none is
    halved)."""
    rng = np.random.default_rng(700 + seed)
    n = int(rng.integers(1, 11))
    x, P = random_state(rng, n, spread=0.3)
    j = int(rng.integers(0, n))
    z = observation(rng, x, j, noise=(0.3, 0.2))
    xe, Pe = dense_iterated(x, P, j, z, iterations)
    xk, Pk, _ = kernel(x, P, n, j, z, iterations)
    assert_close(xk, xe, "x")
    assert_close(Pk, Pe, "P")


def test_one_iteration_is_the_ekf_and_fej_is_never_iterated() -> None:
    rng = np.random.default_rng(800)
    n = 6
    x, P = random_state(rng, n, spread=0.3)
    j = 2
    z = observation(rng, x, j, noise=(0.3, 0.2))
    a = 3 + 2 * j
    N = x.size
    xb, L, ws = np.zeros(N + 4), np.tril(P), ekf.Workspace.for_capacity(N)
    xb[:N] = x
    ekf.update(xb, L, n, j, z_range=z[0], z_bearing=z[1], var_range=SIG_R ** 2,
               var_bearing=SIG_B ** 2, ws=ws)
    x1, P1, _ = kernel(x, P, n, j, z, 1)
    assert np.array_equal(x1, xb[:N]) and np.array_equal(P1, ekf.symmetric(L, N))
    at = (x[0] + 0.1, x[1] - 0.1, x[a] + 0.05, x[a + 1])
    xf, Pf, _ = kernel(x, P, n, j, z, 1, at=at)
    xfi, Pfi, _ = kernel(x, P, n, j, z, ITERATIONS, at=at)
    assert np.array_equal(xf, xfi) and np.array_equal(Pf, Pfi)


def test_the_estimator_iterates_when_asked() -> None:
    """``update_iterations`` reaches the kernel: a first sighting from a robot whose heading
    is uncertain, then a second one; the estimates differ from the EKF's and the iterated
    one's covariance stays symmetric positive definite."""
    def run(iterations: int) -> Estimator:
        est = Estimator(EstimatorSettings(sigma_v=0.3, sigma_w=0.6, sigma_range=SIG_R,
                                          sigma_bearing=SIG_B, update_iterations=iterations))
        for _ in range(200):
            est.predict(v=0.5, w=0.3, dt=0.05, stamp=0.0)
        est.observe(ids=[1, 2], ranges=[2.0, 3.0], bearings=[0.3, -0.8], stamp=1.0)
        for _ in range(200):
            est.predict(v=0.5, w=-0.3, dt=0.05, stamp=2.0)
        est.observe(ids=[1, 2], ranges=[4.5, 2.2], bearings=[1.9, 0.4], stamp=3.0)
        return est

    ekf_run, iterated = run(1), run(ITERATIONS)
    assert not np.allclose(ekf_run.pose, iterated.pose)
    P = iterated.to_state(seq=1, stamp=3.0, step="update").covariance
    assert np.array_equal(P, P.T) and np.linalg.eigvalsh(P).min() > 0
