"""Planted faults: the effects docs/estimator.md promises, on a small simulated run.

A robot drives a circle among six landmarks with a 180° sensor, so landmarks come in and
out of view. Every state (after each predict and each observation batch) is recorded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from slamlens.common.geometry import relative_covariance
from slamlens.services.slam import models
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings

FAULTY = (2, 5)
LANDMARKS = {i + 1: np.array([2.2 * math.cos(a), 1.0 + 2.2 * math.sin(a)])
             for i, a in enumerate(np.linspace(0, 2 * math.pi, 6, endpoint=False) + 0.3)}
DT, V, W = 0.1, 0.3, 0.3  # a circle of radius 1 m round (0, 1), one lap in ~21 s


@dataclass
class Record:
    step: str
    stamp: float
    pose: np.ndarray
    ids: list[int]
    P: np.ndarray


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def run(settings: EstimatorSettings, *, steps: int = 420, seed: int = 0) -> list[Record]:
    rng = np.random.default_rng(seed)
    est = Estimator(settings)
    truth = np.zeros(3)
    out: list[Record] = []

    def record(step: str, stamp: float) -> None:
        out.append(Record(step, stamp, est.pose, [int(i) for i in est.landmark_ids],
                          est.covariance))

    for k in range(1, steps + 1):
        stamp = k * DT
        truth = models.motion(truth, v=V, w=W, dt=DT)
        est.predict(v=V + rng.normal(0, 0.05), w=W + rng.normal(0, 0.05), dt=DT, stamp=stamp)
        record("predict", stamp)
        ids, rs, bs = [], [], []
        for lid, m in LANDMARKS.items():
            r, b = models.observe(truth, m)
            if r < 2.5 and abs(b) <= math.pi / 2:
                ids.append(lid)
                rs.append(r + rng.normal(0, 0.05))
                bs.append(wrap(b + rng.normal(0, 0.02)))
        est.observe(ids=np.array(ids, dtype=np.int64), ranges=rs, bearings=bs, stamp=stamp)
        record("update", stamp)
    return out


def pair_growth(a: Record, b: Record) -> dict[tuple[int, int], float]:
    """Largest eigenvalue of P_d(b) − P_d(a) for every pair present in both states."""
    growth = {}
    for i_a, id_i in enumerate(a.ids):
        for j_a in range(i_a + 1, len(a.ids)):
            id_j = a.ids[j_a]
            i_b, j_b = b.ids.index(id_i), b.ids.index(id_j)
            diff = relative_covariance(b.P, i_b, j_b) - relative_covariance(a.P, i_a, j_a)
            growth[(id_i, id_j)] = float(np.linalg.eigvalsh(diff)[-1])
    return growth


def min_eig_ratio(P: np.ndarray) -> float:
    e = np.linalg.eigvalsh(P)
    return float(e[0] / e[-1])


@pytest.fixture(scope="module")
def correct() -> list[Record]:
    return run(EstimatorSettings())


@pytest.fixture(scope="module")
def map_update() -> list[Record]:
    return run(EstimatorSettings(fault="map-update", faulty_features=FAULTY))


def test_correct_run_never_grows_any_pair(correct: list[Record]) -> None:
    assert len(correct[-1].ids) == 6
    for a, b in zip(correct, correct[1:], strict=False):
        for pair, g in pair_growth(a, b).items():
            assert g <= 1e-12, f"{pair} grew by {g:.2e} at {b.step} {b.stamp:.1f}"


def test_map_update_fault_grows_exactly_the_faulty_pairs(map_update: list[Record],
                                                         correct: list[Record]) -> None:
    grew: dict[tuple[int, int], int] = {}
    for a, b in zip(map_update, map_update[1:], strict=False):
        assert min_eig_ratio(b.P) > -1e-12, "P lost positive semi-definiteness"
        for pair, g in pair_growth(a, b).items():
            faulty = pair[0] in FAULTY or pair[1] in FAULTY
            if not faulty:
                assert g <= 1e-12, f"clean pair {pair} grew by {g:.2e} at {b.step} {b.stamp}"
            elif g > 1e-9:
                assert b.step == "update", "the map-update fault acts in update steps only"
                grew[pair] = grew.get(pair, 0) + 1
    faulty_pairs = {p for p in pair_growth(map_update[-2], map_update[-1])
                    if p[0] in FAULTY or p[1] in FAULTY}
    assert faulty_pairs and set(grew) == faulty_pairs
    assert min(grew.values()) >= 20, f"growth seen too rarely: {grew}"
    # over the run: each faulty pair ends far less certain than in the correct filter, and
    # less certain than when it was first seen jointly; clean pairs end as the correct ones
    last_f, last_c = map_update[-1], correct[-1]
    first = {}
    for rec in map_update:
        for pair in faulty_pairs:
            if pair not in first and pair[0] in rec.ids and pair[1] in rec.ids:
                first[pair] = rec
    for i_a, id_i in enumerate(last_f.ids):
        for j_a in range(i_a + 1, len(last_f.ids)):
            id_j = last_f.ids[j_a]
            tf = np.trace(relative_covariance(last_f.P, i_a, j_a))
            tc = np.trace(relative_covariance(last_c.P, last_c.ids.index(id_i),
                                              last_c.ids.index(id_j)))
            if (id_i, id_j) in faulty_pairs:
                r0 = first[(id_i, id_j)]
                t0 = np.trace(relative_covariance(r0.P, r0.ids.index(id_i), r0.ids.index(id_j)))
                assert tf > 5 * tc, f"{(id_i, id_j)}: {tf:.3g} vs correct {tc:.3g}"
                assert tf > t0, f"{(id_i, id_j)}: {tf:.3g} at the end vs {t0:.3g} at first"


def test_faults_respect_onset_and_feature_list(correct: list[Record]) -> None:
    onset = 15.0
    late = run(EstimatorSettings(fault="map-update", faulty_features=FAULTY, fault_onset=onset))
    for a, b in zip(correct, late, strict=True):
        if a.stamp < onset:
            assert np.array_equal(a.P, b.P) and np.array_equal(a.pose, b.pose)
    assert not np.allclose(correct[-1].P, late[-1].P)
    absent = run(EstimatorSettings(fault="cross-covariance", faulty_features=(99,)))
    for a, b in zip(correct, absent, strict=True):
        assert np.array_equal(a.P, b.P) and np.array_equal(a.pose, b.pose)


def cross_covariance_suspects(records: list[Record], tol: float = 1e-12) -> dict[int, int]:
    """What a monitor can do: around each predict, compare P_v,f(after) with Fx·P_v,f(before),
    Fx = [[1, 0, −Δy], [0, 1, Δx], [0, 0, 1]] from the published pose change."""
    counts: dict[int, int] = {}
    for a, b in zip(records, records[1:], strict=False):
        if b.step != "predict" or a.ids != b.ids:
            continue
        dx, dy = b.pose[0] - a.pose[0], b.pose[1] - a.pose[1]
        Fx = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
        for k, lid in enumerate(a.ids):
            c = slice(3 + 2 * k, 5 + 2 * k)
            expected = Fx @ a.P[0:3, c]
            scale = max(1e-300, float(np.abs(expected).max()))
            if float(np.abs(b.P[0:3, c] - expected).max()) > tol * max(1.0, scale):
                counts[lid] = counts.get(lid, 0) + 1
    return counts


def test_cross_covariance_fault_is_identifiable_from_states(correct: list[Record]) -> None:
    faulty = run(EstimatorSettings(fault="cross-covariance", faulty_features=FAULTY))
    assert cross_covariance_suspects(correct) == {}
    suspects = cross_covariance_suspects(faulty)
    assert set(suspects) == set(FAULTY)
    for f in FAULTY:  # flagged at (nearly) every predict once the feature is in the map
        mapped = sum(1 for a, b in zip(faulty, faulty[1:], strict=False)
                     if b.step == "predict" and f in a.ids and a.ids == b.ids)
        assert suspects[f] >= 0.95 * mapped, f"{f}: flagged {suspects[f]} of {mapped}"
    # the faulty blocks are exactly the previous ones (not propagated); P_vv and P_mm as usual
    for a, b in zip(faulty, faulty[1:], strict=False):
        if b.step != "predict" or a.ids != b.ids:
            continue
        for f in FAULTY:
            if f in a.ids:
                k = a.ids.index(f)
                assert np.array_equal(b.P[0:3, 3 + 2 * k:5 + 2 * k], a.P[0:3, 3 + 2 * k:5 + 2 * k])
        assert np.array_equal(b.P[3:, 3:], a.P[3:, 3:])


def test_partial_cross_covariance_fault_is_a_blend() -> None:
    """magnitude 0 = the correct filter exactly; 0.5 = half the propagation missing."""
    zero = run(EstimatorSettings(fault="cross-covariance", faulty_features=FAULTY,
                                 fault_magnitude=0.0), steps=200)
    ref = run(EstimatorSettings(), steps=200)
    for a, b in zip(ref, zero, strict=True):
        np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-15)
    half = run(EstimatorSettings(fault="cross-covariance", faulty_features=FAULTY,
                                 fault_magnitude=0.5), steps=200)
    assert set(cross_covariance_suspects(half)) == set(FAULTY)
