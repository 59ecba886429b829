"""The shipped Estimator against a dense textbook EKF (services/harness/dense_ekf.py, written
from docs/estimator.md) over whole real runs: MRCLAM robot 1's first minutes
(tests/fixtures/mrclam_small) with the shipped profile's noise, each linearisation, and all of
Victoria Park (151 landmarks, GTSAM's file with its own noise). The
kernels' own tests check one step from random states; this checks what a run strings
together — the batch order (message order, or updates before new landmarks), FEJ's points
as they move, the gate, the new landmarks' rows — after every input, to rounding."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.config import load_settings
from slamlens.common.messages import Odometry
from slamlens.services.harness.dense_ekf import DenseEkf
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.victoria_park import load_victoria_park

REPO = Path(__file__).resolve().parents[2]
SMALL = REPO / "tests" / "fixtures" / "mrclam_small"


@pytest.mark.parametrize(("linearisation", "gate", "start"), [
    ("standard", None, False), ("fej", None, False), ("oc", None, False),
    ("oc", 1.0, False),  # a gate this tight refuses a few sightings: the same ones
    ("standard", 0.0, False),  # 0 = no gate
    ("fej", None, True)])  # from an uncertain initial pose
def test_the_estimator_is_the_dense_ekf_over_a_real_run(linearisation: str,
                                                        gate: float | None,
                                                        start: bool) -> None:
    run = load_mrclam(SMALL, 1)
    settings = replace(load_settings(EstimatorSettings, REPO / "deploy" / "mrclam.toml"),
                       linearisation=linearisation, robot=run.robot)
    if gate is not None:
        settings = replace(settings, innovation_gate_chi2=gate)
    if start:
        settings = replace(settings, initial_pose=(0.4, -0.3, 0.2),
                           initial_pose_sigma=(0.1, 0.05, 0.03))
    est, dense = Estimator(settings), DenseEkf(settings)
    updates = run_both(est, dense, run.events(truth=False))
    assert updates > 50 and est.n >= 5
    assert est.gated == dense.gated and (dense.gated > 0) == (gate == 1.0)


@pytest.mark.parametrize("linearisation", ["standard", "oc"])
def test_the_estimator_is_the_dense_ekf_over_victoria_park(linearisation: str) -> None:
    """A second real dataset, a larger map: all of Victoria Park (GTSAM's file, its own
    noise: deploy/victoria_park.toml), each step played as two Odometry, no gate."""
    settings = replace(load_settings(EstimatorSettings, REPO / "deploy" / "victoria_park.toml"),
                       linearisation=linearisation, robot="robot1")
    run = load_victoria_park(REPO.parent / "shared" / "data" / "victoria_park")
    est, dense = Estimator(settings), DenseEkf(settings)
    updates = run_both(est, dense, run.events())
    assert updates == 3640 - 151 and est.n == 151 and est.gated == dense.gated == 0


def run_both(est: Estimator, dense: DenseEkf, events) -> int:
    """Each message into both filters; their innovations, S, pose and P compared after
    every one, the maps and whole covariances at the end; the updates compared."""
    updates = 0
    for m in events:
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
        assert math.isclose(pose[0], dense.x[0], abs_tol=1e-9)
        assert math.isclose(pose[1], dense.x[1], abs_tol=1e-9)
        assert abs(math.remainder(pose[2] - dense.x[2], 2 * math.pi)) < 1e-9
        np.testing.assert_allclose(est.pose_covariance, dense.P[:3, :3], rtol=1e-6,
                                   atol=1e-12)
    ids, landmarks = dense.landmarks()
    assert est.landmark_ids.tolist() == ids.tolist()
    np.testing.assert_allclose(est.landmarks, landmarks, atol=1e-9)
    np.testing.assert_allclose(est.covariance, dense.covariance(), rtol=1e-6, atol=1e-12)
    return updates
