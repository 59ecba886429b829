"""The monitor on the invariant EKF's states (services/monitor/invariant.py): its updates
compared in ξ, its unobservable directions at its own estimates. On the simulated paper
world no theorem breaks; the same states without the flag break the δ growth theorem
(the check is not vacuous); the standard EKF's states labelled invariant gain information
in the unobservable directions (planted); after a gap the growth is not checked."""

from __future__ import annotations

import dataclasses
from collections import Counter
from functools import cache

import numpy as np
import pytest

from slamlens.common.messages import SlamState
from slamlens.services.monitor import invariant
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.slam.consistency import run, world_settings
from slamlens.services.slam.world import load_world

THEOREMS = ("feature", "pair", "prediction", "unobservable", "psd", "symmetry", "correlation")


@cache
def states(linearisation: str, seed: int = 0) -> tuple[SlamState, ...]:
    world = load_world("paper")
    out = run(world, seed=seed, loops=2, collect_states=True,
              settings=world_settings(world, linearisation=linearisation)).states
    assert len(out) > 300
    return out


def labelled(state: SlamState, flag: bool) -> SlamState:
    diagnostics = dict(state.diagnostics or {})
    diagnostics.pop(invariant.INVARIANT_FLAG, None)
    if flag:
        diagnostics[invariant.INVARIANT_FLAG] = 1.0
    return dataclasses.replace(state, diagnostics=diagnostics)


def violations(run_states, **settings: object) -> tuple[Counter[str], Counter[str]]:
    """Violations by kind and statistics seen, over every state checked in order."""
    monitor = Monitor(MonitorSettings(**settings))
    kinds: Counter[str] = Counter()
    seen: Counter[str] = Counter()
    for state in run_states:
        health = monitor.check(state)
        kinds.update(v.kind for v in health.violations)
        seen.update(k for k in health.statistics)
    return kinds, seen


def test_the_invariant_ekfs_states_break_no_theorem() -> None:
    run_states = states("invariant")
    assert all(invariant.declares_invariant(s) for s in run_states)
    kinds, seen = violations(run_states)
    assert not any(kinds[k] for k in THEOREMS), kinds
    # the unobservable check ran: the map's heading σ on nearly every state
    assert seen["unobservable_heading_sd_deg"] > 0.9 * len(run_states)
    assert seen["unobservable_growth"] > 0.9 * len(run_states)


def test_without_the_flag_its_updates_grow_the_map_in_the_standard_error() -> None:
    """In δ an update carries P to the new estimate (J P Jᵀ): the landmarks' blocks grow,
    so a monitor that compared in δ would call this consistent filter faulty."""
    kinds, _ = violations([labelled(s, False) for s in states("invariant")])
    assert kinds["feature"] + kinds["pair"] > 10


def test_the_standard_ekf_labelled_invariant_gains_information() -> None:
    """Planted: the standard EKF's updates without the step to the new estimate gain
    information in the unobservable directions at the estimates (its overconfidence)."""
    kinds, _ = violations([labelled(s, True) for s in states("standard")])
    assert kinds["unobservable"] > 10


@pytest.mark.parametrize("keep_every", [2, 3])
def test_after_a_gap_the_growth_is_not_checked(keep_every: int) -> None:
    run_states = states("invariant")
    thinned = run_states[::keep_every]
    kinds, seen = violations(thinned)
    assert seen["growth_unchecked"] == len(thinned) - 1
    assert not any(kinds[k] for k in THEOREMS), kinds


def test_the_invariant_covariance_is_t_inverse_p_t_inverse_transposed() -> None:
    """P_ξ against the dense T⁻¹ P T⁻ᵀ of a random state."""
    state = states("invariant")[-1]
    N = state.covariance.shape[0]
    T = np.eye(N)
    T[0, 2], T[1, 2] = -state.pose[1], state.pose[0]
    T[3::2, 2], T[4::2, 2] = -state.landmarks[:, 1], state.landmarks[:, 0]
    Ti = np.linalg.inv(T)
    np.testing.assert_allclose(invariant.invariant_covariance(state),
                               Ti @ state.covariance @ Ti.T, rtol=1e-9, atol=1e-12)
