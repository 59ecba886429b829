"""Geometry helpers against their textbook definitions."""

from __future__ import annotations

import numpy as np

from slamlens.common.geometry import (
    T_from_pose2,
    all_relative_covariances,
    eig2x2_max,
    invert_T,
    pd_size_m,
    relative_covariance,
    transform_points,
)


def test_all_relative_covariances_equals_the_definition() -> None:
    rng = np.random.default_rng(3)
    for n in (2, 3, 17):
        N = 3 + 2 * n
        A = rng.normal(size=(N, N))
        P = A @ A.T
        first, second, Pd = all_relative_covariances(P, n)
        assert len(first) == n * (n - 1) // 2
        for k, (i, j) in enumerate(zip(first, second, strict=True)):
            a, b = 3 + 2 * i, 3 + 2 * j
            expected = (P[a:a + 2, a:a + 2] + P[b:b + 2, b:b + 2] - P[a:a + 2, b:b + 2]
                        - P[b:b + 2, a:a + 2])
            np.testing.assert_allclose(Pd[k], expected, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(relative_covariance(P, i, j), expected, atol=1e-12)


def test_eig_and_size_match_numpy() -> None:
    rng = np.random.default_rng(4)
    A = rng.normal(size=(500, 2, 2))
    S = A @ A.transpose(0, 2, 1)
    np.testing.assert_allclose(eig2x2_max(S), np.linalg.eigvalsh(S)[:, 1], rtol=1e-10)
    np.testing.assert_allclose(pd_size_m(S), np.sqrt(np.linalg.eigvalsh(S)[:, 1]), rtol=1e-10)


def test_rigid_transforms() -> None:
    T = T_from_pose2(np.array([1.0, 2.0, np.pi / 2]), z=0.5)
    np.testing.assert_allclose(transform_points(T, np.array([[1.0, 0.0, 0.0]])),
                               [[1.0, 3.0, 0.5]], atol=1e-12)
    np.testing.assert_allclose(invert_T(T) @ T, np.eye(4), atol=1e-12)
