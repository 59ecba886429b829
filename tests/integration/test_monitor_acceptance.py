"""Acceptance of the behaviour monitor on the paper scenario (docs/monitor.md).

The real chain, in-process: Simulator("paper") → Estimator (docs/estimator.md) → Monitor, one state
per event as the estimator service publishes them, truth delivered in stream order.

* Correct runs, 20 seeds: no violation, ever — also with 30 % of the states dropped; and the
  monitor's NEES is right: its mean across the seeds at fixed times is χ²-consistent.
* Planted faults, 20 seeds each, 1 or 2 faulty features chosen per seed, acting from
  t = 20 s (after the first loop, every feature initialised): the suspects are exactly the
  faulty features within 20 updates of the onset and stay so to the end of the run, with
  and without 30 % of the states dropped; the prediction-step fault is reported as such.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.stats import chi2

from slamlens.common.messages import Health, Odometry, SlamState, Truth
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator, first_seen_times
from slamlens.services.slam.world import load_world

SEEDS = range(20)
ONSET = 20.0  # s
UNTIL = ONSET + 12.0  # s: faulty runs stop 120 updates after the onset (6× the 20 allowed)
DROP = 0.3
WORLD = load_world("paper")

Event = tuple[str, SlamState | Truth]


@pytest.fixture(autouse=True)
def _quiet_estimator(caplog: pytest.LogCaptureFixture) -> None:
    # the cross-covariance fault makes the estimator reject many updates, one log line each
    caplog.set_level(logging.ERROR, logger="slamlens.estimator")


def run_chain(seed: int, *, until: float = float("inf"), **fault: object) -> list[Event]:
    """States (one per event, seq +1 each) and truths, in the order a monitor receives them,
    for the default run (three loops) or up to the stamp ``until``."""
    est = Estimator(EstimatorSettings(**fault))  # type: ignore[arg-type]
    stream: list[Event] = [("state", est.to_state(seq=0, stamp=0.0, step="init"))]
    seq = 0
    for event in Simulator(WORLD, seed=seed).events():
        if event.stamp > until:
            break
        if isinstance(event, Truth):
            stream.append(("truth", event))
            continue
        seq += 1
        if isinstance(event, Odometry):
            est.predict(v=event.v, w=event.w, dt=event.dt, stamp=event.stamp)
            state = est.to_state(seq=seq, stamp=event.stamp, step="predict")
        else:
            report = est.observe(ids=event.ids, ranges=event.ranges, bearings=event.bearings,
                                 stamp=event.stamp)
            state = est.to_state(seq=seq, stamp=event.stamp, step="update", report=report)
        stream.append(("state", state))
    return stream


def monitor_stream(stream: list[Event], *, drop: float = 0.0, seed: int = 0
                   ) -> tuple[list[tuple[Health, str]], Monitor]:
    """Feed a fresh Monitor; with ``drop`` > 0 that fraction of the states never arrives."""
    rng = np.random.default_rng(10_000 + seed)
    monitor = Monitor(MonitorSettings())
    out = []
    for kind, message in stream:
        if kind == "truth":
            monitor.add_truth(message)  # type: ignore[arg-type]
        elif not (drop and message.seq > 0 and rng.random() < drop):
            out.append((monitor.check(message), message.step))  # type: ignore[union-attr]
    return out, monitor


def assert_clean(healths: list[tuple[Health, str]], seed: int, label: str) -> None:
    bad = [(h.seq, v.kind, v.ids, v.detail) for h, _ in healths for v in h.violations]
    assert not bad, f"seed {seed} ({label}): false alarms {bad[:5]}"
    assert all(h.ok and h.suspects.size == 0 for h, _ in healths), f"seed {seed} ({label})"


def updates_until_pinpointed(healths: list[tuple[Health, str]], faulty: set[int], *,
                             seed: int, label: str) -> int:
    """Updates after the onset until the suspects are exactly ``faulty`` for good."""
    updates, first = 0, None
    for h, step in healths:
        if h.stamp < ONSET:
            assert h.ok and h.suspects.size == 0, f"seed {seed} ({label}): alarm before onset"
            continue
        updates += step == "update"
        if set(h.suspects.tolist()) == faulty:
            first = updates if first is None else first
        else:
            assert first is None, (f"seed {seed} ({label}): suspects {h.suspects} at seq "
                                   f"{h.seq} after being exactly {sorted(faulty)}")
    assert first is not None, f"seed {seed} ({label}): {sorted(faulty)} never pinpointed"
    return first


def faulty_features(seed: int) -> tuple[int, ...]:
    seen = first_seen_times(WORLD)
    candidates = sorted(i for i, t in seen.items() if t < ONSET - 1.0)
    assert len(candidates) == 15  # every feature is initialised well before the onset
    rng = np.random.default_rng(seed)
    return tuple(sorted(int(i) for i in rng.choice(candidates, size=1 + seed % 2,
                                                   replace=False)))


# -- correct runs --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def correct_runs() -> dict[int, list[tuple[Health, str]]]:
    runs = {}
    for seed in SEEDS:
        stream = run_chain(seed)
        healths, _ = monitor_stream(stream)
        assert_clean(healths, seed, "all states")
        dropped, monitor = monitor_stream(stream, drop=DROP, seed=seed)
        assert_clean(dropped, seed, f"{DROP:.0%} of the states dropped")
        assert monitor.summary.gaps > 0.2 * len(healths)
        runs[seed] = healths
    return runs


def test_correct_paper_runs_never_raise_a_violation(correct_runs) -> None:
    assert len(correct_runs) == len(SEEDS) >= 20  # (the fixture asserted every seed clean)
    for healths in correct_runs.values():
        assert len(healths) > 1000  # the default run: three loops, every event a state
        stats = healths[-1][0].statistics
        assert stats["pairs_checked"] == 105.0  # 15 features, all compared
        assert stats["nees_pose_window_lo"] < stats["nees_pose_window_mean"] \
            < stats["nees_pose_window_hi"]
        assert stats["nis_window_lo"] < stats["nis_window_mean"] < stats["nis_window_hi"]


def test_monitor_nees_is_chi2_consistent_across_seeds(correct_runs) -> None:
    """Across independent seeds (not along one run) N·mean NEES ~ χ²(N·dof): an oracle for
    the monitor's NEES formulas (pose 3 dof with wrapped heading, features 2 dof)."""
    N = len(correct_runs)
    pose_lo, pose_hi = chi2.ppf([5e-4, 1 - 5e-4], 3 * N) / N
    for seq in (200, 500, 800, 1050):
        values = [run[seq][0].statistics["nees_pose"] for run in correct_runs.values()]
        assert pose_lo < np.mean(values) < pose_hi, (seq, np.mean(values))
        feats = [run[seq][0].statistics["nees_features_mean"] for run in correct_runs.values()]
        assert 0.5 * 2 < np.mean(feats) < 2.0 * 2, (seq, np.mean(feats))


# -- planted faults ------------------------------------------------------------------------
@pytest.mark.parametrize("seed", SEEDS)
def test_map_update_fault_is_pinpointed(seed: int) -> None:
    faulty = faulty_features(seed)
    stream = run_chain(seed, until=UNTIL, fault="map-update", faulty_features=faulty,
                       fault_onset=ONSET)
    healths, monitor = monitor_stream(stream)
    assert updates_until_pinpointed(healths, set(faulty), seed=seed, label="all") <= 20
    summary = monitor.summary
    assert summary.phase == "update" and summary.suspects == faulty
    first_faulty_update = next(m.seq for kind, m in stream if kind == "state"
                               and m.stamp >= ONSET and m.step == "update")
    assert summary.onset_seq == first_faulty_update
    grown = [v for h, _ in healths for v in h.violations]
    assert {"pair", "feature"} <= {v.kind for v in grown}
    assert all(set(v.ids) & set(faulty) for v in grown if v.kind in ("pair", "feature"))
    dropped, _ = monitor_stream(stream, drop=DROP, seed=seed)
    assert updates_until_pinpointed(dropped, set(faulty), seed=seed, label="dropped") <= 20


@pytest.mark.parametrize("seed", SEEDS)
def test_cross_covariance_fault_is_pinpointed_in_the_predict_step(seed: int) -> None:
    faulty = faulty_features(seed)
    stream = run_chain(seed, until=UNTIL, fault="cross-covariance", faulty_features=faulty,
                       fault_onset=ONSET)
    healths, monitor = monitor_stream(stream)
    assert updates_until_pinpointed(healths, set(faulty), seed=seed, label="all") <= 20
    summary = monitor.summary
    assert summary.phase == "predict" and summary.suspects == faulty
    prediction = [v for h, _ in healths for v in h.violations if v.kind == "prediction"]
    assert prediction and all(v.phase == "predict" for v in prediction)
    assert {v.ids for v in prediction} == {(f,) for f in faulty}
    dropped, _ = monitor_stream(stream, drop=DROP, seed=seed)
    assert updates_until_pinpointed(dropped, set(faulty), seed=seed, label="dropped") <= 20
