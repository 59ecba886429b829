"""The behaviour monitor: pure checks against independent oracles, and the Monitor class on
runs of a small dense textbook EKF (tests/unit/monitor_runs.py: correct, and with the two
planted faults of the paper scenario done by hand); its statistical tests are in
test_monitor_statistics.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.common.config import load_settings
from slamlens.common.errors import ConfigError
from slamlens.common.geometry import relative_covariance, wrap_angle
from slamlens.common.messages import Health, SlamState
from slamlens.services.monitor import checks
from slamlens.services.monitor.blame import Evidence, blame_weights
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import pose_nees, quadratic_forms_2x2
from tests.unit.monitor_runs import feed, run, violations, with_cov


# -- the pure checks against per-pair textbook oracles --------------------------------------
def random_psd(rng: np.random.Generator, N: int, rank: int | None = None) -> np.ndarray:
    A = rng.normal(size=(N, rank or N))
    return A @ A.T


def oracle_growth(P_prev: np.ndarray, P_cur: np.ndarray, n: int, tol: float) -> set:
    """Per-pair loop: P_d from slamlens.common.geometry, eigvalsh of the difference."""
    out = set()
    for i in range(n):
        for j in range(i + 1, n):
            D = relative_covariance(P_prev, i, j) - relative_covariance(P_cur, i, j)
            if np.linalg.eigvalsh(0.5 * (D + D.T))[0] < -tol:
                out.add((i, j))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_pair_growth_matches_a_per_pair_eigvalsh_oracle(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 25))
    N = 3 + 2 * n
    P_prev = random_psd(rng, N)
    # a correct update subtracts a PSD term: nothing may grow
    P_down = P_prev - random_psd(rng, N, rank=2) * 0.01
    found = checks.pair_growth(P_prev[3:, 3:], P_down[3:, 3:], rtol=1e-9, atol=1e-12)
    assert found.count == 0 and found.checked == n * (n - 1) // 2
    # an arbitrary symmetric change: some pairs grow, some shrink; same set as the oracle
    E = rng.normal(size=(N, N)) * 0.05
    P_cur = P_prev + 0.5 * (E + E.T)
    found = checks.pair_growth(P_prev[3:, 3:], P_cur[3:, 3:], rtol=0.0, atol=0.0)
    expected = oracle_growth(P_prev, P_cur, n, 0.0)
    assert 0 < len(expected) < n * (n - 1) // 2
    assert {tuple(p) for p in found.index.tolist()} == expected
    for (i, j), g in zip(found.index.tolist(), found.value, strict=True):
        D = relative_covariance(P_prev, i, j) - relative_covariance(P_cur, i, j)
        assert g == pytest.approx(-np.linalg.eigvalsh(D)[0], rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_feature_growth_matches_eigvalsh_of_each_block(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(1, 20))
    P_prev = random_psd(rng, 2 * n)
    E = rng.normal(size=(2 * n, 2 * n)) * 0.1
    P_cur = P_prev + 0.5 * (E + E.T)
    found = checks.feature_growth(P_prev, P_cur, rtol=0.0, atol=0.0)
    expected = {i for i in range(n) if np.linalg.eigvalsh(
        P_prev[2 * i:2 * i + 2, 2 * i:2 * i + 2] - P_cur[2 * i:2 * i + 2, 2 * i:2 * i + 2])[0] < 0}
    assert set(found.index.tolist()) == expected


def test_growth_in_one_direction_at_constant_area_is_a_violation() -> None:
    """A glyph can keep its area (det P_d) while growing along one axis: Loewner catches it."""
    P_prev = np.zeros((7, 7))
    P_prev[3:, 3:] = np.diag([0.04, 0.01, 0.0, 0.0])  # P_d(1,2) = diag(0.04, 0.01)
    P_cur = P_prev.copy()
    P_cur[3:, 3:] = np.diag([0.02, 0.02, 0.0, 0.0])  # det unchanged, y grows 2×
    assert np.linalg.det(relative_covariance(P_cur, 0, 1)) == pytest.approx(
        np.linalg.det(relative_covariance(P_prev, 0, 1)))
    found = checks.pair_growth(P_prev[3:, 3:], P_cur[3:, 3:], rtol=1e-9, atol=1e-12)
    assert found.index.tolist() == [[0, 1]]
    assert found.value[0] == pytest.approx(0.01)


def test_tolerance_is_relative_to_the_blocks_not_to_a_tiny_p_d() -> None:
    """Strongly correlated features: P_d ≪ P_ii; a rounding-size change must not alarm,
    a change of 1e-6 of the blocks must."""
    big = 1.0
    P = np.full((4, 4), 0.0)
    P[np.ix_([0, 2], [0, 2])] = big
    P[np.ix_([1, 3], [1, 3])] = big
    P += np.diag([1e-8] * 4)  # P_d = 2e-8·I
    rounding = P + 1e-15 * np.array([[1, 0, -1, 0], [0, 0, 0, 0], [-1, 0, 1, 0], [0] * 4])
    assert checks.pair_growth(P, rounding, rtol=1e-9, atol=1e-12).count == 0
    grown = P.copy()
    grown[0, 0] += 1e-6
    assert checks.pair_growth(P, grown, rtol=1e-9, atol=1e-12).count == 1


def test_cholesky_fast_path_agrees_with_eigvalsh() -> None:
    rng = np.random.default_rng(7)
    for trial in range(40):
        N = int(rng.integers(3, 30))
        P = random_psd(rng, N, rank=int(rng.integers(1, N + 1)))
        if trial % 2:
            P -= 10.0 ** rng.uniform(-6, 0) * np.outer(*(2 * [rng.normal(size=N)]))
        tol = 1e-9 * np.max(np.diag(P)) + 1e-12
        expected = np.linalg.eigvalsh(P)[0] < -tol
        got = checks.min_eigenvalue_if_indefinite(P, rtol=1e-9, atol=1e-12)
        assert (got is not None) == expected
        if got is not None:
            assert got[0] == pytest.approx(np.linalg.eigvalsh(P)[0])


def test_structure_matches_entrywise_loops() -> None:
    rng = np.random.default_rng(21)
    for _ in range(10):
        N = int(rng.integers(3, 25))
        P = random_psd(rng, N, rank=int(rng.integers(1, N + 1)))
        for _ in range(3):  # plant asymmetries and |ρ| > 1 at random entries
            a, b = rng.choice(N, size=2, replace=False)
            P[a, b] += rng.choice([0.0, 1e-6, 3.0]) * math.sqrt(P[a, a] * P[b, b] + 1e-12)
        asym, corr = checks.structure(P, rtol_symmetry=1e-9, rtol_correlation=1e-9, atol=1e-12)
        want_asym, want_corr = set(), set()
        for a in range(N):
            for b in range(a + 1, N):
                s_ab = math.sqrt(abs(P[a, a] * P[b, b]))
                if abs(P[a, b] - P[b, a]) > 1e-9 * s_ab + 1e-12:
                    want_asym.add((a, b))
                if abs(P[a, b] + P[b, a]) / 2 > s_ab * (1 + 1e-9) + 1e-12:
                    want_corr.add((a, b))
        assert {tuple(x) for x in asym.index.tolist()} == want_asym
        assert {tuple(x) for x in corr.index.tolist()} == want_corr


def test_pose_nees_closed_form_matches_solve() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        P = random_psd(rng, 3) * 10.0 ** rng.uniform(-6, 0)
        pose, truth = rng.normal(size=3), rng.normal(size=3)
        e = pose - truth
        e[2] = wrap_angle(e[2])
        got = pose_nees(pose, P, truth, condition_max=1e10)
        if np.linalg.cond(P) < 1e6:
            assert got == pytest.approx(e @ np.linalg.solve(P, e), rel=1e-8)
    singular = np.diag([1e-3, 1e-3, 0.0])
    assert pose_nees(np.zeros(3), singular, np.zeros(3), condition_max=1e10) is None


def test_quadratic_forms_match_solve() -> None:
    rng = np.random.default_rng(3)
    S = np.stack([random_psd(rng, 2) + 0.1 * np.eye(2) for _ in range(20)])
    e = rng.normal(size=(20, 2))
    expected = [float(ei @ np.linalg.solve(Si, ei)) for ei, Si in zip(e, S, strict=True)]
    assert quadratic_forms_2x2(e, S) == pytest.approx(expected, rel=1e-12)
    S[0] = np.diag([1.0, -1.0])
    assert np.isnan(quadratic_forms_2x2(e, S)[0])


def test_common_landmarks_handles_append_reorder_and_removal() -> None:
    a, b = checks.common_landmarks(np.array([5, 7, 9]), np.array([5, 7, 9, 11]))
    assert a.tolist() == [0, 1, 2] and b.tolist() == [0, 1, 2]
    a, b = checks.common_landmarks(np.array([5, 7, 9]), np.array([9, 5, 12]))
    assert a.tolist() == [0, 2] and b.tolist() == [1, 0]


# -- the Monitor on dense-EKF runs ---------------------------------------------------------
def test_correct_run_raises_nothing_and_reports_statistics(correct_run) -> None:
    states, truths = correct_run
    monitor = Monitor(MonitorSettings())
    healths = feed(monitor, states, truths)
    assert violations(healths) == []
    assert all(h.ok and h.suspects.size == 0 for h in healths)
    assert [h.seq for h in healths] == [s.seq for s in states]
    last = healths[-1].statistics
    assert last["pairs_checked"] == 15.0 and last["pairs_growing"] == 0.0
    for key in ("nees_pose", "nees_pose_lo", "nees_pose_hi", "nees_pose_window_mean",
                "nis_window_mean", "nis_window_lo", "nis_window_hi", "nees_features_mean"):
        assert key in healths[-1].statistics or key in healths[-2].statistics, key
    summary = monitor.summary
    assert summary.states == len(states) and summary.violations == {}
    assert summary.onset_seq is None and summary.phase == "" and summary.suspects == ()


def test_gaps_are_compared_across_without_false_alarms(correct_run) -> None:
    states, truths = correct_run
    rng = np.random.default_rng(5)
    kept = [s for s in states if rng.random() > 0.3]
    monitor = Monitor(MonitorSettings())
    healths = feed(monitor, kept, truths)
    assert violations(healths) == []
    assert monitor.summary.gaps == len(states) - len(kept) - (kept[0].seq - states[0].seq)
    assert sum(h.statistics["gap"] for h in healths) == monitor.summary.gaps


def first_suspected(healths: list[Health], faulty: set[int], onset: float) -> int:
    """Number of update states after onset until the suspects became exactly ``faulty``
    and stayed so to the end of the run."""
    updates = 0
    first = None
    for h, step in healths:
        if h.stamp < onset:
            assert h.ok and h.suspects.size == 0, "false alarm before the onset"
            continue
        updates += step == "update"
        if set(h.suspects.tolist()) == faulty:
            first = updates if first is None else first
        else:
            first = None
    assert first is not None, "faulty features never (stably) suspected"
    return first


@pytest.mark.parametrize("faulty", [(2,), (1, 6)])
def test_map_update_fault_names_exactly_the_faulty_features(faulty: tuple[int, ...]) -> None:
    states, truths = run(seed=2, map_fault=faulty, onset=8.0)
    monitor = Monitor(MonitorSettings())
    healths = feed(monitor, states, truths)
    n_updates = first_suspected(list(zip(healths, [s.step for s in states], strict=True)),
                                set(faulty), 8.0)
    assert n_updates <= 3
    kinds = {v.kind for v in violations(healths)}
    assert {"feature", "pair"} <= kinds
    for v in violations(healths):
        if v.kind in ("pair", "feature"):
            assert set(v.ids) & set(faulty) and v.phase == "update" and v.value > v.bound
    summary = monitor.summary
    assert summary.suspects == tuple(sorted(faulty)) and summary.phase == "update"
    # the fault acts after the first update at t ≥ 8 s: that is the onset, not later
    assert summary.onset_seq == next(s.seq for s in states
                                     if s.stamp >= 8.0 and s.step == "update")


def test_cross_covariance_fault_is_reported_as_a_prediction_fault() -> None:
    states, truths = run(seed=3, cross_fault=(3,), onset=8.0)
    monitor = Monitor(MonitorSettings())
    healths = feed(monitor, states, truths)
    n_updates = first_suspected(list(zip(healths, [s.step for s in states], strict=True)),
                                {3}, 8.0)
    assert n_updates <= 2
    preds = [v for v in violations(healths) if v.kind == "prediction"]
    assert preds and all(v.phase == "predict" and v.ids == (3,) for v in preds)
    assert monitor.summary.phase == "predict"
    assert monitor.summary.violations["prediction"] == len(preds)


def test_faults_are_still_caught_with_gaps() -> None:
    rng = np.random.default_rng(11)
    for kw, faulty in ((dict(map_fault=(6,)), {6}), (dict(cross_fault=(2,)), {2})):
        states, _ = run(seed=4, onset=8.0, **kw)
        kept = [s for s in states if rng.random() > 0.3]
        monitor = Monitor(MonitorSettings())
        healths = feed(monitor, kept)
        first_suspected(list(zip(healths, [s.step for s in kept], strict=True)), faulty, 8.0)


# -- hand-planted single-state faults ------------------------------------------------------

def test_asymmetry_psd_and_correlation_are_reported_with_the_feature(correct_run) -> None:
    states, _ = correct_run
    base = states[-1]
    fid = int(base.landmark_ids[2])
    P = base.covariance.copy()
    P[3 + 4, 3 + 5] += 1e-4  # one asymmetric pair of entries in the third feature's block,
    P[3 + 5, 3 + 4] -= 1e-4  # sym(P) unchanged: only the symmetry check can see it
    h = Monitor(MonitorSettings()).check(with_cov(base, P))
    assert [v.kind for v in h.violations] == ["symmetry"] and h.violations[0].ids == (fid,)
    P = base.covariance.copy()
    a, b = 0, 3 + 2 * 2
    P[a, b] = P[b, a] = 1.5 * math.sqrt(P[a, a] * P[b, b])
    h = Monitor(MonitorSettings()).check(with_cov(base, P))
    kinds = {v.kind: v for v in h.violations}
    assert set(kinds) == {"correlation", "psd"}
    assert kinds["correlation"].ids == (fid,) and kinds["correlation"].value == pytest.approx(0.5)
    assert fid in kinds["psd"].ids and not h.ok
    assert h.suspects.size == 0  # not theorem growth: no blame


def test_prediction_check_flags_a_changed_map_block_and_negative_noise(correct_run) -> None:
    states, _ = correct_run
    k = next(i for i, s in enumerate(states) if s.step == "predict" and s.n >= 4 and i > 50)
    prev, cur = states[k - 1], states[k]
    ok = Monitor(MonitorSettings())
    ok.check(prev)
    assert ok.check(cur).ok
    P = cur.covariance.copy()
    c = 3 + 2 * 3
    P[c:c + 2, c:c + 2] *= 0.999  # shrinking: pair/feature checks pass, but a predict must not
    mon = Monitor(MonitorSettings())
    mon.check(prev)
    h = mon.check(with_cov(cur, P, seq=cur.seq))
    assert [(v.kind, v.ids, v.phase) for v in h.violations] == [
        ("prediction", (int(cur.landmark_ids[3]),), "predict")]
    P = cur.covariance.copy()
    P[:3, :3] = prev.covariance[:3, :3] - 1e-4 * np.diag([1.0, 0.0, 0.0])
    mon = Monitor(MonitorSettings())
    mon.check(prev)
    h = mon.check(with_cov(cur, P, seq=cur.seq))
    assert ("prediction", ()) in [(v.kind, v.ids) for v in h.violations]


def test_prediction_check_needs_consecutive_states(correct_run) -> None:
    states, _ = correct_run
    k = next(i for i, s in enumerate(states) if s.step == "predict" and i > 50)
    P = states[k].covariance.copy()
    P[3:5, 3:5] *= 0.999
    mon = Monitor(MonitorSettings())
    mon.check(states[k - 2])  # k−1 missed: an update lies between, P_mm may legally shrink
    assert mon.check(with_cov(states[k], P, seq=states[k].seq)).ok


def test_seq_going_back_is_a_restart_not_a_violation(correct_run) -> None:
    states, _ = correct_run
    mon = Monitor(MonitorSettings())
    for s in states[200:230]:
        mon.check(s)
    healths = [mon.check(s) for s in states[:30]]
    assert all(h.ok for h in healths) and mon.summary.restarts == 1


def test_a_duplicate_state_is_neither_a_restart_nor_an_alarm(correct_run) -> None:
    states, _ = correct_run
    mon = Monitor(MonitorSettings())
    healths = [mon.check(s) for s in (states[100], states[101], states[101], states[102])]
    assert all(h.ok for h in healths) and mon.summary.restarts == 0


def test_a_restart_forgets_the_old_runs_suspects() -> None:
    states, _ = run(seed=3, steps=120, cross_fault=(1,), onset=2.0)
    mon = Monitor(MonitorSettings())
    feed(mon, states)
    assert mon.summary.suspects == (1,)
    correct, _ = run(seed=3, steps=20)
    healths = feed(mon, correct)
    assert mon.summary.restarts == 1 and healths[-1].suspects.size == 0
    assert mon.summary.violations["prediction"] > 0  # counts are kept


def test_absurd_but_finite_covariances_give_a_decodable_health(correct_run) -> None:
    states, _ = correct_run
    base = states[-1]
    mon = Monitor(MonitorSettings())
    mon.check(base)
    P = base.covariance * 1e300
    P[5, 6] = -P[5, 6]  # and broken: asymmetric, |ρ| > 1 nowhere near representable
    h = mon.check(with_cov(base, P))
    assert not h.ok
    assert Health.from_bytes(h.to_bytes()) == h


def test_a_removed_landmark_is_counted_not_alarmed(correct_run) -> None:
    states, _ = correct_run
    s = states[-1]
    keep = [0, 1, 3, 4, 5]
    rows = np.r_[0:3, [3 + 2 * i + a for i in keep for a in (0, 1)]]
    pruned = SlamState(robot="r", seq=s.seq + 1, stamp=s.stamp, step="update", pose=s.pose,
                       landmark_ids=s.landmark_ids[keep], landmarks=s.landmarks[keep],
                       covariance=s.covariance[np.ix_(rows, rows)])
    mon = Monitor(MonitorSettings())
    mon.check(s)
    h = mon.check(pruned)
    assert h.ok and h.statistics["landmarks_removed"] == 1.0



# -- pinpointing -------------------------------------------------------------------------
def test_blame_covers_growing_pairs_with_the_fewest_features() -> None:
    star = np.array([[4, j] for j in (1, 2, 3, 5, 6)])
    assert blame_weights(direct=(), pairs=star, prior={}) == {4: 1.0}
    two = np.array([[4, 1], [4, 2], [4, 5], [7, 1], [7, 3], [4, 7]])
    assert blame_weights(direct=(), pairs=two, prior={}) == {4: 1.0, 7: 1.0}
    assert blame_weights(direct=(9,), pairs=np.array([[9, 1], [2, 3]]), prior={3: 0.5}) == {
        9: 1.0, 3: 1.0}
    assert blame_weights(direct=(), pairs=np.array([[2, 3]]), prior={}) == {2: 0.5, 3: 0.5}


def test_evidence_is_stable_and_a_one_off_blame_fades() -> None:
    ev = Evidence(half_life=50.0, suspect_score=0.75, suspect_ratio=0.1)
    ev.step({8: 0.5})
    assert ev.suspects == ()  # an ambiguous half blame alone is not enough
    for k in range(100):
        ev.step({4: 1.0} if k % 2 else {})
        assert ev.suspects == (() if k == 0 else (4,))  # stable across the quiet states
    ev.step({8: 1.0})
    assert ev.suspects == (4,)  # 8 is far below 10 % of 4's evidence
    for _ in range(500):
        ev.step({})
    assert ev.suspects == ()
    ev.step({1: 1.0}, present=[1])
    ev.step({}, present=[2])
    assert ev.scores == {}


# -- messages and settings -----------------------------------------------------------------
def test_health_with_a_prediction_violation_round_trips() -> None:
    states, _ = run(seed=3, steps=120, cross_fault=(1,), onset=2.0)
    healths = feed(Monitor(MonitorSettings()), states)
    h = next(h for h in healths if not h.ok)
    assert Health.from_bytes(h.to_bytes()) == h


def test_settings_load_with_validation(tmp_path) -> None:
    path = tmp_path / "monitor.toml"
    path.write_text("rtol_growth = 1e-8\nnis_window = 20\n")
    s = load_settings(MonitorSettings, path, {"significance": 1e-4})
    assert (s.rtol_growth, s.nis_window, s.significance) == (1e-8, 20, 1e-4)
    with pytest.raises(ConfigError, match="nis_windw"):
        load_settings(MonitorSettings, None, {"nis_windw": 3})
    with pytest.raises(ConfigError, match="nis_window"):
        load_settings(MonitorSettings, None, {"nis_window": 0})
