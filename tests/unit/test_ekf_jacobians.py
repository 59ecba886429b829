"""Fx, Fu, Hv, Hm, Gv, Gz against central finite differences of the docs/estimator.md functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.services.slam import ekf, models

EPS = 1e-6
TOL = 1e-7  # central differences: O(eps²) truncation plus O(1e-16/eps) rounding


def wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2 * math.pi) - math.pi


def numeric_jacobian(f, at: np.ndarray, angle_rows: tuple[int, ...] = ()) -> np.ndarray:
    """Central differences; rows that are angles are differenced modulo 2π."""
    at = np.asarray(at, dtype=float)
    cols = []
    for k in range(at.size):
        d = np.zeros_like(at)
        d[k] = EPS
        diff = f(at + d) - f(at - d)
        for r in angle_rows:
            diff[r] = wrap(diff[r])
        cols.append(diff / (2 * EPS))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("seed", range(10))
def test_motion_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi)])
    v, w, dt = rng.normal(0, 1), rng.normal(0, 1), rng.uniform(0.01, 0.5)
    Fx, Fu = models.motion_jacobians(pose, v=v, w=w, dt=dt)
    num_Fx = numeric_jacobian(lambda p: models.motion(p, v=v, w=w, dt=dt), pose, (2,))
    num_Fu = numeric_jacobian(lambda u: models.motion(pose, v=u[0], w=u[1], dt=dt),
                              np.array([v, w]), (2,))
    np.testing.assert_allclose(Fx, num_Fx, atol=TOL)
    np.testing.assert_allclose(Fu, num_Fu, atol=TOL)


@pytest.mark.parametrize("seed", range(10))
def test_observation_jacobians(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi)])
    lm = pose[:2] + rng.uniform(0.3, 4) * np.array([math.cos(t := rng.uniform(0, 6.28)),
                                                    math.sin(t)])
    Hv, Hm = models.observation_jacobians(pose, lm)
    num_Hv = numeric_jacobian(lambda p: models.observe(p, lm), pose, (1,))
    num_Hm = numeric_jacobian(lambda m: models.observe(pose, m), lm, (1,))
    np.testing.assert_allclose(Hv, num_Hv, atol=TOL)
    np.testing.assert_allclose(Hm, num_Hm, atol=TOL)


def test_observation_jacobian_where_bearing_wraps() -> None:
    """Landmark behind the robot: h's bearing jumps between ±π, the derivative must not."""
    pose = np.array([0.0, 0.0, 0.0])
    lm = np.array([-2.0, 1e-9])
    Hv, Hm = models.observation_jacobians(pose, lm)
    np.testing.assert_allclose(Hv, numeric_jacobian(lambda p: models.observe(p, lm), pose, (1,)),
                               atol=TOL)
    np.testing.assert_allclose(Hm, numeric_jacobian(lambda m: models.observe(pose, m), lm, (1,)),
                               atol=TOL)


@pytest.mark.parametrize("seed", range(10))
def test_inverse_observation_jacobians(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi)])
    r, phi = rng.uniform(0.1, 5), rng.uniform(-math.pi, math.pi)
    Gv, Gz = models.inverse_observation_jacobians(pose, range_m=r, bearing=phi)
    num_Gv = numeric_jacobian(lambda p: models.inverse_observation(p, range_m=r, bearing=phi),
                              pose)
    num_Gz = numeric_jacobian(
        lambda z: models.inverse_observation(pose, range_m=z[0], bearing=z[1]), np.array([r, phi]))
    np.testing.assert_allclose(Gv, num_Gv, atol=TOL)
    np.testing.assert_allclose(Gz, num_Gz, atol=TOL)


def test_inverse_observation_inverts_observe() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi)])
        r, phi = rng.uniform(0.1, 5), rng.uniform(-math.pi, math.pi)
        m = models.inverse_observation(pose, range_m=r, bearing=phi)
        np.testing.assert_allclose(models.observe(pose, m), [r, phi], atol=1e-12)


def test_kernel_jacobians_match_model_jacobians() -> None:
    """The kernels' inline Jacobians are the model functions' (update uses H = [Hv | Hm])."""
    rng = np.random.default_rng(9)
    pose = np.array([0.3, -0.2, 0.7])
    lm = np.array([1.5, 0.9])
    x = np.concatenate([pose, lm])
    A = rng.normal(scale=0.1, size=(5, 5))
    P = A @ A.T + 1e-3 * np.eye(5)
    Hv, Hm = models.observation_jacobians(pose, lm)
    H = np.hstack([Hv, Hm])
    R = np.diag([0.05**2, 0.02**2])
    S = H @ P @ H.T + R
    L = ekf.lower_from_symmetric(P, capacity=7)
    xb = np.zeros(7)
    xb[:5] = x
    out = ekf.update(xb, L, 1, 0, z_range=1.3, z_bearing=0.1, var_range=R[0, 0],
                     var_bearing=R[1, 1], ws=ekf.Workspace.for_capacity(7))
    np.testing.assert_allclose([[out[2], out[3]], [out[3], out[4]]], S, rtol=1e-12)
