"""The monitor's statistical tests on dense-EKF runs (tests/unit/monitor_runs.py): the NEES
against the textbook formula, truth matched to states whichever comes first, the NIS and
NEES windows and the side they leave by, and the verdict's reading of a timid NIS."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Health, SlamState
from slamlens.common.verdict import summary_text
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import WindowTest
from tests.unit.monitor_runs import feed, violations


def test_nees_statistic_equals_the_textbook_formula(correct_run) -> None:
    states, truths = correct_run
    monitor = Monitor(MonitorSettings())
    healths = feed(monitor, states[:101], truths)
    s, t = states[100], truths[50]
    assert t.stamp == s.stamp
    e = s.pose - t.pose
    e[2] = wrap_angle(e[2])
    expected = e @ np.linalg.solve(s.covariance[:3, :3], e)
    assert healths[100].statistics["nees_pose"] == pytest.approx(expected, rel=1e-9)
    assert s.n >= 2
    per_feature = [float(d @ np.linalg.solve(Pf, d)) for d, Pf in (
        (s.landmarks[i] - t.landmarks[int(fid) - 1],
         s.covariance[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i])
        for i, fid in enumerate(s.landmark_ids))]
    assert healths[100].statistics["nees_features_mean"] == pytest.approx(np.mean(per_feature))
    assert healths[100].statistics["nees_features_max"] == pytest.approx(max(per_feature))


def test_truth_arriving_after_its_state_still_counts(correct_run) -> None:
    states, truths = correct_run
    early, late = Monitor(MonitorSettings(nees_window=10)), Monitor(MonitorSettings(
        nees_window=10))
    by_stamp = {t.stamp: t for t in truths}
    for s in states[:120]:
        early.add_truth(by_stamp[s.stamp])
        early.check(s)
    for s in states[:120]:
        late.check(s)
        late.add_truth(by_stamp[s.stamp])
    a = early.check(states[120]).statistics["nees_pose_window_mean"]
    b = late.check(states[120]).statistics["nees_pose_window_mean"]
    assert a == pytest.approx(b, rel=1e-12)


def test_the_nees_does_not_depend_on_how_far_truth_and_states_are_apart(
        correct_run, monkeypatch) -> None:
    """State and truth come from different sessions: no order between them. All truths
    before the states (a monitor behind the driver), all after (a truth source behind),
    or interleaved: the same NEES. Beyond the buffers' bounds what is missed is counted."""
    states, truths = correct_run
    states = states[:200]  # within the states that may wait for a truth (256)
    truths = [t for t in truths if t.stamp <= states[-1].stamp]
    assert truths[-1].stamp == states[-1].stamp

    def last_health(order: str) -> Health:
        monitor = Monitor(MonitorSettings(nees_window=10))
        by_stamp = {t.stamp: t for t in truths}
        if order == "truth first":
            for truth in truths:
                monitor.add_truth(truth)
        for s in states[:-1]:
            if order == "interleaved" and s.stamp in by_stamp:
                monitor.add_truth(by_stamp[s.stamp])
            monitor.check(s)
        if order == "truth last":  # every truth after its state was checked
            for truth in truths[:-1]:
                monitor.add_truth(truth)
        if order != "truth first":
            monitor.add_truth(truths[-1])
        return monitor.check(states[-1])  # reports what the late truths found, too

    def nees(h: Health) -> tuple[float | None, float | None]:
        return h.statistics.get("nees_pose_window_mean"), h.statistics.get("nees_features_mean")

    interleaved = last_health("interleaved")
    assert nees(interleaved)[0] is not None
    assert nees(last_health("truth first")) == nees(interleaved)
    late = last_health("truth last")
    assert "truth_missing" not in late.statistics
    assert late.statistics["nees_pose_window_mean"] == pytest.approx(
        interleaved.statistics["nees_pose_window_mean"], rel=1e-12)
    # a buffer too small for the distance: what it cannot keep is counted, never silent
    monkeypatch.setattr("slamlens.services.monitor.truth._TRUTH_BUFFER", 20)
    assert last_health("truth first").statistics["truth_missing"] > 0
    monkeypatch.setattr("slamlens.services.monitor.truth._PENDING", 20)
    assert last_health("truth last").statistics["truth_missing"] > 0




def test_nis_window_alarms_on_a_wrong_noise_model_only() -> None:
    rng = np.random.default_rng(9)
    S = np.array([[0.01, 0.002], [0.002, 0.004]])
    L = np.linalg.cholesky(S)

    def states(scale: float, count: int) -> list[SlamState]:
        out = []
        for k in range(count):
            nu = (L @ rng.normal(size=(2, 4))).T * scale
            out.append(SlamState(robot="r", seq=k, stamp=0.1 * k, step="update",
                                 pose=np.zeros(3), landmark_ids=np.zeros(0, dtype=np.int64),
                                 landmarks=np.zeros((0, 2)), covariance=np.zeros((3, 3)),
                                 innovation_ids=np.arange(4), innovations=nu,
                                 innovation_covariances=np.repeat(S[None], 4, axis=0)))
        return out

    good = feed(Monitor(MonitorSettings()), states(1.0, 500))
    assert violations(good) == []
    bad = feed(Monitor(MonitorSettings()), states(2.0, 50))  # S 4× too small
    nis = [v for v in violations(bad) if v.kind == "nis"]
    assert len(nis) == 4 and all(v.value > v.bound for v in nis)
    assert all(", above [" in v.detail and "overconfident" in v.detail for v in nis)
    timid = feed(Monitor(MonitorSettings()), states(0.5, 50))  # S 4× too large
    low = [v for v in violations(timid) if v.kind == "nis"]
    assert len(low) == 4 and all(v.value < v.bound for v in low)
    assert all(v.detail.startswith("mean NIS ") and " over 50 innovations, below [" in v.detail
               and "smaller than S predicts (timid" in v.detail for v in low)
    assert good[-1].statistics["nis_window_hi"] == pytest.approx(
        chi2.ppf(1 - 0.5e-6, 100) / 50)


@pytest.mark.parametrize(("scale", "side", "reading"), [
    (1e-2, "above", "larger than the covariance says (overconfident)"),
    (1e5, "below", "smaller than the covariance says (timid)")])
def test_a_nees_window_says_which_side_it_left_by(correct_run, scale, side, reading) -> None:
    """The correct run's every covariance × scale: no theorem breaks, the NEES leaves its
    band (one χ²₃ sample's at 1e-6: [1.5e-4, 32.1]) on the side the scale says."""
    states, truths = correct_run
    scaled = [dataclasses.replace(s, covariance=s.covariance * scale) for s in states]
    healths = feed(Monitor(MonitorSettings(nees_window=10)), scaled, truths)
    nees = [v for v in violations(healths) if v.kind == "nees"]
    assert {v.kind for v in violations(healths)} == {"nees"}
    pose = [v for v in nees if not v.ids]
    assert len(pose) >= 20 and all(v.detail.startswith("mean pose NEES ") for v in pose)
    assert all(f" over 10 states, {side} [" in v.detail and v.detail.endswith(reading)
               for v in nees)
    assert all((v.value > v.bound) == (side == "above") for v in nees)


def test_a_timid_nis_with_the_truth_bearing_the_pose_out_is_ok(correct_run) -> None:
    """The correct run with every S × 4 (as a filter whose R holds a persistent error the
    innovations do not see): the NIS leaves its band from below while P, and so the NEES,
    is right. With the truth the verdict is "tuning" only until the first pose NEES window
    passes, then "ok" with the NIS listed; without the truth it stays "tuning"."""
    states, truths = correct_run
    timid = [s if s.innovation_covariances is None else dataclasses.replace(
        s, innovation_covariances=s.innovation_covariances * 4.0) for s in states]
    settings = MonitorSettings(nis_window=20)  # its first window ends before the NEES's
    with_truth = feed(Monitor(settings), timid, truths)
    assert {v.kind for v in violations(with_truth)} == {"nis"}
    assert len(violations(with_truth)) >= 10
    assert all(v.value < v.bound for v in violations(with_truth))
    first_nis = next(k for k, h in enumerate(with_truth) if h.violations)
    verdicts = [h.verdict for h in with_truth]
    changes = [k for k in range(1, len(verdicts)) if verdicts[k] != verdicts[k - 1]]
    assert len(changes) == 2 and changes[0] == first_nis, changes  # ok → tuning → ok
    assert verdicts[first_nis] == "tuning" and verdicts[-1] == "ok"
    assert with_truth[-1].standing and with_truth[-1].standing[0].kind == "nis"
    blind = feed(Monitor(settings), timid)
    assert blind[-1].verdict == "tuning" and {h.verdict for h in blind[first_nis:]} == {
        "tuning"}


def test_the_truths_word_on_the_pose_stands_until_a_nees_window_fails(correct_run) -> None:
    """The same timid run, the truth given only for its first 10 s, then none for more
    states than the clearance, then a truth half a metre off the robot: "ok" (the NIS
    listed) from the first passed pose NEES window through the truthless stretch — the
    truth's word stands until evidence contradicts it — then "tuning" once a NEES window
    fails."""
    states, truths = correct_run
    timid = [s if s.innovation_covariances is None else dataclasses.replace(
        s, innovation_covariances=s.innovation_covariances * 4.0) for s in states]
    off = [dataclasses.replace(t, pose=np.asarray(t.pose) + [0.5, 0.0, 0.0])
           for t in truths if t.stamp > 23.0]
    settings = MonitorSettings(nis_window=20)
    healths = feed(Monitor(settings), timid, [t for t in truths if t.stamp <= 10.0] + off)
    stamps = np.array([h.stamp for h in healths])
    first_ok = next(k for k, h in enumerate(healths) if h.verdict == "ok" and h.standing)
    blind = np.nonzero((stamps > 10.0) & (stamps <= 23.0))[0]
    assert stamps[first_ok] <= 10.0 and blind.size > settings.clear_after
    assert all(healths[k].verdict == "ok" and healths[k].standing[0].kind == "nis"
               for k in range(first_ok, int(blind[-1]) + 1))
    # … and says on what: the seq of the last pose NEES window judged, before the stretch
    judged = healths[int(blind[-1])].statistics["nees_pose_judged_seq"]
    assert judged < healths[int(blind[0])].seq
    assert summary_text(healths[int(blind[-1])]).endswith(
        f"; pose NEES last judged at seq {int(judged)})")
    assert "last judged" not in summary_text(healths[int(blind[0]) - 1])
    assert healths[-1].verdict == "tuning"
    assert "nees" in {v.kind for v in healths[-1].standing}


def test_window_bands_follow_the_documented_distributions() -> None:
    ind = WindowTest(dof=2, window=50, alpha=1e-3, band="white")
    assert (ind.lo, ind.hi) == pytest.approx(tuple(chi2.ppf([5e-4, 1 - 5e-4], 100) / 50))
    dep = WindowTest(dof=3, window=50, alpha=1e-3, band="dependent")
    assert (dep.lo, dep.hi) == pytest.approx(tuple(chi2.ppf([5e-4, 1 - 5e-4], 3)))
    results = dep.add(np.full(120, 3.0))
    assert len(results) == 2 and not results[0].failed and dep.sliding_mean == 3.0



def test_a_failed_nis_window_stands_until_a_window_passes_however_many_states(
        correct_run) -> None:
    """Innovations sparse, as on real data: a timid first window (every S × 4), then 250
    states whose innovations the monitor is not given (more than clear_after = 200), then the
    run's own. Without a window in between there is no evidence the innovations fit again:
    "tuning" throughout; the run's next windows pass and it clears."""
    states, _ = correct_run
    settings = MonitorSettings(nis_window=20)

    def timid(s):
        return s if s.innovation_covariances is None else dataclasses.replace(
            s, innovation_covariances=s.innovation_covariances * 4.0)

    probe = feed(Monitor(settings), [timid(s) for s in states])
    failed = next(k for k, h in enumerate(probe) if h.violations)
    quiet = range(failed + 1, failed + 251)
    sparse = [timid(s) if k <= failed else dataclasses.replace(
        s, innovations=None, innovation_covariances=None, innovation_ids=None)
        if k in quiet else s for k, s in enumerate(states)]
    healths = feed(Monitor(settings), sparse)
    assert settings.clear_after == 200 and len(quiet) > settings.clear_after
    assert {healths[k].verdict for k in quiet} == {"tuning"}
    assert healths[-1].verdict == "ok" and not healths[-1].standing
