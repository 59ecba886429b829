"""The shipped Estimator and a dense oracle fed the same inputs, compared after each one
(tests/unit/test_ekf_dense_run.py: the textbook EKF; test_ekf_invariant.py: the invariant
EKF written in its own error)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Protocol

import numpy as np

from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam.estimator import Estimator


class DenseFilter(Protocol):
    """What the comparison reads of a dense oracle."""

    x: np.ndarray

    @property
    def pose_covariance(self) -> np.ndarray: ...

    def apply(self, message: Odometry | Observations
              ) -> list[tuple[np.ndarray, np.ndarray]]: ...

    def landmarks(self) -> tuple[np.ndarray, np.ndarray]: ...

    def covariance(self) -> np.ndarray: ...


def run_both(est: Estimator, dense: DenseFilter, events: Iterable[Odometry | Observations],
             *, whole_every: int | None = None) -> int:
    """Each input into both; their innovations, S, pose and P_vv compared after every one,
    the whole covariances every ``whole_every`` inputs (None: never), the maps and whole
    covariances at the end. Returns the updates compared."""
    updates = 0
    for k, m in enumerate(events, start=1):
        report = est.apply(m)
        applied = dense.apply(m)
        if not isinstance(m, Odometry):
            assert report is not None and len(report.innovation_ids) == len(applied)
            for (nu, S), got_nu, got_S in zip(applied, report.innovations,
                                              report.innovation_covariances, strict=True):
                np.testing.assert_allclose(got_nu, nu, rtol=1e-6, atol=1e-9)
                np.testing.assert_allclose(got_S, S, rtol=1e-6, atol=1e-12)
            updates += len(applied)
        pose = est.pose
        np.testing.assert_allclose(pose[:2], dense.x[:2], rtol=0, atol=1e-9)
        assert abs(math.remainder(pose[2] - dense.x[2], 2 * math.pi)) < 1e-9
        np.testing.assert_allclose(est.pose_covariance, dense.pose_covariance, rtol=1e-6,
                                   atol=1e-12)
        if whole_every is not None and k % whole_every == 0:
            np.testing.assert_allclose(est.covariance, dense.covariance(), rtol=1e-6,
                                       atol=1e-12)
    ids, landmarks = dense.landmarks()
    assert est.landmark_ids.tolist() == ids.tolist()
    np.testing.assert_allclose(est.landmarks, landmarks, rtol=0, atol=1e-9)
    np.testing.assert_allclose(est.covariance, dense.covariance(), rtol=1e-6, atol=1e-12)
    return updates
