"""The shipped Estimator against a dense textbook EKF (services/harness/dense_ekf.py, written
from docs/estimator.md) over whole real runs: MRCLAM robot 1's first minutes
(tests/fixtures/mrclam_small) with the shipped profile's noise, each linearisation, and all of
Victoria Park (151 landmarks, GTSAM's file with its own noise). The
kernels' own tests check one step from random states; this checks what a run strings
together — the batch order (message order, or updates before new landmarks), FEJ's points
as they move, the gate, the new landmarks' rows — after every input, to rounding."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from slamlens.common.config import load_settings
from slamlens.services.harness.dense_ekf import DenseEkf
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.victoria_park import load_victoria_park
from tests.unit.dense_runs import run_both

REPO = Path(__file__).resolve().parents[2]
SMALL = REPO / "tests" / "fixtures" / "mrclam_small"


@pytest.mark.parametrize(("linearisation", "gate", "start"), [
    ("standard", None, False), ("fej", None, False), ("oc", None, False),
    ("oc", 0.5, False),  # a gate this tight refuses a few sightings: the same ones
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
    assert est.gated == dense.gated and (dense.gated > 0) == (gate == 0.5)


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
