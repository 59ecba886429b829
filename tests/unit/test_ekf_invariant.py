"""The estimator's invariant EKF (``--linearisation invariant``, services/slam/ekf_invariant.py)
against the dense right-invariant EKF written from the group (services/harness/dense_inekf.py:
P in the invariant error ξ, H without a heading column, the exponential on SE_{1+n}(2)):
after every input of a real run and of the simulated paper world, to rounding; its rank-2k
pass against numpy; a refused step writes nothing; what it cannot do is refused."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.config import load_settings
from slamlens.common.errors import ConfigError
from slamlens.common.messages import Observations, Odometry, Truth
from slamlens.services.harness.dense_inekf import DenseInvariantEkf
from slamlens.services.slam import ekf, ekf_invariant
from slamlens.services.slam.consistency import world_settings
from slamlens.services.slam.ekf_storage import rank2k_lower
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world
from tests.unit.dense_runs import run_both

REPO = Path(__file__).resolve().parents[2]
SMALL = REPO / "tests" / "fixtures" / "mrclam_small"


@pytest.mark.parametrize("gate", [None, 0.5])
def test_the_estimator_is_the_dense_invariant_ekf_over_a_real_run(gate: float | None) -> None:
    """MRCLAM robot 1's first minutes with the shipped profile's noise (its range terms
    too); a gate tight enough to refuse some sightings refuses the same ones."""
    run = load_mrclam(SMALL, 1)
    settings = replace(load_settings(EstimatorSettings, REPO / "deploy" / "mrclam.toml"),
                       linearisation="invariant", robot=run.robot)
    if gate is not None:
        settings = replace(settings, innovation_gate_chi2=gate)
    est, dense = Estimator(settings), DenseInvariantEkf(settings)
    updates = run_both(est, dense, run.events(truth=False), whole_every=50)
    assert updates > 50 and est.n >= 5
    assert est.gated == dense.gated and (dense.gated > 0) == (gate is not None)


@pytest.mark.parametrize("seed", range(2))
def test_the_estimator_is_the_dense_invariant_ekf_on_the_paper_world(seed: int) -> None:
    world = load_world("paper")
    settings = world_settings(world, linearisation="invariant")
    events = [e for e in Simulator(world, seed=seed, loops=1).events()
              if not isinstance(e, Truth)]
    est, dense = Estimator(settings), DenseInvariantEkf(settings)
    assert run_both(est, dense, events, whole_every=50) > 100


def test_the_rank_2k_pass_is_numpys_on_the_lower_triangle() -> None:
    rng = np.random.default_rng(3)
    size, N = 40, 31
    L = rng.normal(size=(size, size))
    at, bt = rng.normal(size=(3, size)), rng.normal(size=(3, size))
    blas, plain = L.copy(), L.copy()
    rank2k_lower(blas, at, bt, N)
    rank2k_lower(plain, at, bt, N, use_blas=False)
    lower = np.tril_indices(N)
    expected = L[:N, :N] + at[:, :N].T @ bt[:, :N] + bt[:, :N].T @ at[:, :N]
    np.testing.assert_allclose(blas[:N, :N][lower], expected[lower], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(plain[:N, :N][lower], expected[lower], rtol=1e-12,
                               atol=1e-12)
    assert np.array_equal(blas[N:], L[N:]) and np.array_equal(blas[:, N:], L[:, N:])


def test_the_retraction_is_the_group_exponential() -> None:
    """x̂⁻ + Kν → exp(T⁻¹Kν)·x̂⁻, against the dense filter's exponential (written from
    the group's rotation and V(α)), for a large turn and a tiny one."""
    rng = np.random.default_rng(5)
    for alpha in (0.7, 1e-12):
        prior = rng.uniform(-4, 4, 9)
        step = rng.normal(size=9) * 0.3
        step[2] = alpha
        x = prior + step
        ekf_invariant.retract(x, prior, 9)
        dense = DenseInvariantEkf(EstimatorSettings(), capacity=3)
        dense.x[:9], dense.n = prior, 9
        T = dense.transform()
        dense.retract(np.linalg.solve(T, step))
        np.testing.assert_allclose(x, dense.x[:9], rtol=0, atol=1e-12)


def test_a_refused_update_writes_nothing() -> None:
    settings = EstimatorSettings(linearisation="invariant", sigma_v=0.1, sigma_w=0.1)
    est = Estimator(settings)
    est.apply(Odometry(robot="robot1", stamp=0.1, v=0.5, w=0.1, dt=0.1))
    est.apply(Observations(robot="robot1", stamp=0.2, ids=np.array([1, 2]),
                           ranges=np.array([2.0, 3.0]), bearings=np.array([0.1, -0.5])))
    x, P = est.store.x.copy(), est.covariance
    with pytest.raises(ekf.GatedObservationError):
        ekf_invariant.update(est.store.x, est.store.L, est.n, 0, z_range=40.0, z_bearing=2.0,
                             var_range=1e-4, var_bearing=1e-4, ws=est.store.ws, gate=9.0,
                             guard=ekf.Guard())
    assert np.array_equal(est.store.x, x) and np.array_equal(est.covariance, P)
    assert est.store.ws.deferred == 0


def test_the_iterated_update_is_refused_for_it() -> None:
    with pytest.raises(ConfigError, match="invariant"):
        EstimatorSettings(linearisation="invariant", update_iterations=3)


def test_tune_fits_it_only_without_the_iterated_update() -> None:
    from slamlens.services.slam.cli import _linearisations
    from slamlens.services.slam.settings import TuneSettings

    assert "invariant" in _linearisations(TuneSettings(linearisation="all"))
    assert "invariant" not in _linearisations(TuneSettings(linearisation="all",
                                                           update_iterations=3))
    with pytest.raises(ConfigError, match="iterated"):
        _linearisations(TuneSettings(linearisation="invariant", update_iterations=3))
