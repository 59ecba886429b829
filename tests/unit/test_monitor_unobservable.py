"""The monitor's unobservable-directions check (docs/monitor.md): the information
N(k)ᵀ P(k)⁻¹ N(k) in global x, y and rotation must never grow.

Oracles: N rebuilt here from the states (the robot at the last predict state's pose, each
landmark at its estimate in the first state that has it) and I computed with a dense
inverse; a planted compass (an absolute heading fused into P) whose information gain is
known in closed form; the real estimator on the paper world, standard, FEJ and OC.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import linalg

from slamlens.common.messages import Health, SlamState
from slamlens.common.verdict import violation_text
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.slam import consistency
from slamlens.services.slam.world import load_world

WORLD = load_world("paper")


def states_of(linearisation: str, *, seed: int = 1, **fault: object) -> list[SlamState]:
    settings = dataclasses.replace(consistency.world_settings(WORLD,
                                                              linearisation=linearisation),
                                   **fault)  # type: ignore[arg-type]
    return list(consistency.run(WORLD, seed=seed, settings=settings,
                                collect_states=True).states)


@pytest.fixture(scope="module")
def fej_states() -> list[SlamState]:
    return states_of("fej")


@pytest.fixture(scope="module")
def standard_states() -> list[SlamState]:
    return states_of("standard")


def dense_information(states: list[SlamState]) -> dict[int, np.ndarray]:
    """seq → Nᵀ P⁻¹ N, by a dense inverse, with N from the states (the oracle)."""
    first: dict[int, np.ndarray] = {}
    robot = None
    out = {}
    for s in states:
        if s.step in ("init", "predict"):
            robot = np.asarray(s.pose[:2], float)
        for lid, xy in zip(s.landmark_ids.tolist(), s.landmarks, strict=True):
            first.setdefault(lid, np.asarray(xy, float))
        rows = [np.array([[1, 0, -robot[1]], [0, 1, robot[0]], [0, 0, 1.0]])]
        rows += [np.array([[1, 0, -first[i][1]], [0, 1, first[i][0]]])
                 for i in s.landmark_ids.tolist()]
        N = np.vstack(rows)
        if np.linalg.cond(s.covariance) < 1e10:
            out[s.seq] = N.T @ np.linalg.inv(s.covariance) @ N
    return out


def relative_growth(a: np.ndarray, b: np.ndarray) -> float:
    return float(linalg.eigh(b, a, eigvals_only=True)[-1]) - 1.0


def check_all(states: list[SlamState], **settings: object) -> list:
    mon = Monitor(MonitorSettings(**settings))  # type: ignore[arg-type]
    return [mon.check(s) for s in states]


def test_fej_never_breaks_it_and_the_statistics_follow_the_dense_oracle(fej_states) -> None:
    healths = check_all(fej_states)
    assert not any(h.violations for h in healths)  # nothing at all on a correct FEJ run
    dense = dense_information(fej_states)
    growth = [h.statistics["unobservable_growth"] for h in healths
              if "unobservable_growth" in h.statistics]
    assert len(growth) > 1000 and max(growth) < 1e-9
    for h in healths[100::97]:  # σ of the global heading from I⁻¹, against the dense I
        expected = math.degrees(math.sqrt(np.linalg.inv(dense[h.seq])[2, 2]))
        assert h.statistics["unobservable_heading_sd_deg"] == pytest.approx(expected, rel=1e-6)


def test_oc_is_held_to_the_same_theorem_and_keeps_it() -> None:
    """OC (H at the estimates, projected onto H N = 0) declares FEJ's points: the monitor
    holds it to the check, which never fires, and its growth stays at rounding."""
    states = states_of("oc")
    assert all(s.diagnostics.get("linearisation.fej") == 1.0 for s in states[1:])
    healths = check_all(states)
    assert not any(h.violations for h in healths)
    growth = [h.statistics["unobservable_growth"] for h in healths
              if "unobservable_growth" in h.statistics]
    assert len(growth) > 1000 and max(growth) < 1e-9


def test_a_standard_ekf_gains_spurious_information_reported_as_its_size(
        standard_states) -> None:
    auto = check_all(standard_states)
    assert not any(h.violations for h in auto)  # auto: a statistic for a standard EKF
    assert max(h.statistics.get("unobservable_growth", 0.0) for h in auto) > 1e-3
    held = check_all(standard_states, check_unobservable="always")
    found = [(h, v) for h in held for v in h.violations if v.kind == "unobservable"]
    assert len(found) > 100 and {v.kind for h in held for v in h.violations} == {"unobservable"}
    assert all(h.verdict == "fault" for h, _ in found)
    dense = dense_information(standard_states)
    seqs = sorted(dense)
    for h, v in found[::25]:  # the size: the growth since the state compared with
        since = int(v.detail.split("since seq ")[1].split(":")[0])
        assert since == seqs[seqs.index(h.seq) - 1] or since in dense
        assert v.value == pytest.approx(relative_growth(dense[since], dense[h.seq]), rel=1e-4)
        assert "spurious information in an unobservable direction" in violation_text(v)


def test_a_planted_compass_is_found_with_the_information_it_added(fej_states) -> None:
    """An absolute heading fused into one state's P (a compass the filter should not
    have): the information in the rotation grows by gᵀ N I⁻¹ Nᵀ g / r exactly."""
    k = next(i for i, s in enumerate(fej_states) if i > 400 and s.step == "update")
    s = fej_states[k]
    P = s.covariance
    g = np.zeros(P.shape[0])
    g[2] = 1.0
    r = 0.02 ** 2
    planted = P - np.outer(P @ g, P @ g) / (g @ P @ g + r)
    states = list(fej_states[:k]) + [dataclasses.replace(s, covariance=planted)]
    healths = check_all(states)
    found = [v for v in healths[-1].violations if v.kind == "unobservable"]
    assert len(found) == 1 and healths[-1].verdict == "fault"
    dense = dense_information(fej_states[:k + 1])
    # (P')⁻¹ = P⁻¹ + g gᵀ/r, so I' = I + (Nᵀg)(gᵀN)/r with gᵀN = N's θ row = (0, 0, 1)
    planted_info = dense[s.seq] + np.diag([0.0, 0.0, 1.0 / r])
    previous = max(q for q in dense if q < s.seq)
    expected = relative_growth(dense[previous], planted_info)
    assert expected > 0.1
    assert found[0].value == pytest.approx(expected, rel=1e-5)


def test_gaps_lose_the_landmarks_first_seen_in_them_not_the_check(fej_states) -> None:
    keep = [s for i, s in enumerate(fej_states) if i < 60 or i % 3]  # every third gone
    healths = check_all(keep)
    assert not any(h.violations for h in healths)
    unknown = [h.statistics.get("unobservable_unknown", 0.0) for h in healths]
    compared = [h for h in healths if "unobservable_growth" in h.statistics]
    # landmarks mapped in a missed state cannot be placed: from then on nothing compared
    if max(unknown) > 0:
        first_unknown = next(h.seq for h, u in zip(healths, unknown, strict=True) if u)
        assert all(h.seq < first_unknown for h in compared)
    assert len(compared) > 20


def test_fej_prediction_steps_and_a_planted_cross_covariance_fault() -> None:
    """The prediction check takes FEJ's Fx (from the last predict state's pose): a correct
    FEJ run raises nothing (above), a planted cross-covariance fault is named."""
    states = states_of("fej", seed=2, fault="cross-covariance", faulty_features=(3,),
                       fault_onset=20.0)
    healths = check_all(states)
    first = next(h for h in healths if h.violations)
    assert first.stamp >= 20.0
    named = {i for h in healths for v in h.violations if v.kind == "prediction" for i in v.ids}
    assert named == {3}
    assert any(3 in h.suspects.tolist() for h in healths)


@pytest.mark.parametrize("fault", [{}, {"fault": "cross-covariance", "faulty_features": (3,),
                                        "fault_onset": 20.0}])
def test_fej_states_in_bursts_give_the_healths_of_one_by_one(fault: dict) -> None:
    """The screen follows FEJ's linearisation points through a burst (landmarks appear
    mid-burst, so a burst is screened as several runs of one size): bursts = one by one."""
    states = states_of("fej", seed=4, **fault)[:700]
    single = [h.to_bytes() for h in check_all(states)]
    rng = np.random.default_rng(3)
    mon = Monitor(MonitorSettings())
    bursts: list[bytes] = []
    k = 0
    while k < len(states):
        burst = states[k:k + int(rng.integers(1, 80))]
        k += len(burst)
        mon.prepare(burst)
        bursts += [mon.check(s).to_bytes() for s in burst]
    assert bursts == single
    if not fault:
        assert all(not Health.from_bytes(b).violations for b in single)
