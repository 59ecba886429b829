"""The one verdict per robot: what stands, how it clears, fault versus tuning."""

from __future__ import annotations

from slamlens.common.messages import Health, Violation
from slamlens.services.monitor.verdict import WORDS, Verdict


def v(kind: str, ids: tuple[int, ...] = (), value: float = 1.0, step: int = 0) -> Violation:
    return Violation(kind=kind, ids=ids, step=step, value=value)


def test_a_fault_stands_through_clean_states_until_cleared() -> None:
    verdict = Verdict(clear_after=10)
    assert verdict.update(1, [], ()) == "ok"
    assert verdict.update(2, [v("pair", (12, 3))], (3, 12)) == "fault"
    # clean states, suspects still named: the fault stands (a clean predict proves nothing)
    assert all(verdict.update(k, [], (3, 12)) == "fault" for k in range(3, 30))
    # the suspects cleared, but the violation was seen less than 10 states ago? no: long ago
    assert verdict.update(30, [], ()) == "ok"
    assert verdict.since is None


def test_without_suspects_a_violation_stands_for_clear_after_states() -> None:
    verdict = Verdict(clear_after=10)
    verdict.update(5, [v("psd")], ())
    assert [verdict.update(k, [], ()) for k in (6, 15)] == ["fault", "fault"]
    assert verdict.update(16, [], ()) == "ok"


def test_statistics_alone_are_tuning_and_a_fault_outranks_them() -> None:
    verdict = Verdict(clear_after=50)
    assert verdict.update(1, [v("nees")], ()) == "tuning"
    assert verdict.since == 1
    assert verdict.update(2, [v("nis"), v("feature", (4,))], ()) == "fault"
    assert verdict.since == 2
    assert WORDS["tuning"] == "inconsistent tuning or model mismatch"


def test_each_standing_violation_is_listed_once_faults_first_pairs_low_high() -> None:
    verdict = Verdict(clear_after=100)
    verdict.update(1, [v("nees", value=9.0), v("pair", (12, 3), value=1e-4)], (3, 12))
    verdict.update(2, [v("pair", (3, 12), value=3e-4)], (3, 12))
    standing = verdict.standing()
    assert (standing[0].kind, standing[0].ids) == ("pair", (3, 12))  # the worst one kept
    pair = standing[0]
    assert (pair.first_step, pair.step, pair.count, pair.value) == (1, 2, 2, 3e-4)
    assert len(standing) == 2 and standing[1].kind == "nees"


def test_health_carries_the_verdict_on_the_wire() -> None:
    import numpy as np

    verdict = Verdict()
    verdict.update(7, [v("pair", (3, 12))], (3, 12))
    h = Health(robot="r", seq=7, stamp=1.0, ok=False, suspects=np.array([3, 12]),
               violations=(v("pair", (3, 12)),), verdict=verdict.verdict,
               verdict_since=verdict.since, standing=verdict.standing())
    back = Health.from_bytes(h.to_bytes())
    assert back == h and back.verdict == "fault" and back.standing[0].first_step == 7


def test_a_timid_nis_is_tuning_unless_the_truth_bears_the_pose_covariance_out() -> None:
    """A NIS window below its band (value < bound) does not make ``tuning`` while the pose
    NEES is in its band; above its band, or without the truth, it does; a NEES standing
    makes ``tuning`` whatever the NIS."""
    low = Violation(kind="nis", ids=(), step=1, value=0.5, bound=0.9)
    high = Violation(kind="nis", ids=(), step=1, value=4.0, bound=3.7)
    verdict = Verdict(clear_after=50)
    assert verdict.update(1, [low], ()) == "tuning"  # no truth (yet)
    assert verdict.update(2, [], (), pose_consistent=True) == "ok"
    assert [s.kind for s in verdict.standing()] == ["nis"]  # still listed
    assert verdict.update(3, [], (), pose_consistent=False) == "tuning"
    assert verdict.update(4, [high], (), pose_consistent=True) == "tuning"
    assert len(verdict.standing()) == 2  # the two sides stand apart
    other = Verdict(clear_after=50)
    other.update(1, [low, v("nees", value=20.0)], (), pose_consistent=True)
    assert other.verdict == "tuning"
    timid_nees = Violation(kind="nees", ids=(), step=1, value=0.01, bound=0.2)
    assert Verdict().update(1, [timid_nees], (), pose_consistent=True) == "tuning"


def test_a_nis_violation_clears_only_after_a_nis_window_passed() -> None:
    """Its windows come with innovations, which may be far apart: clear_after states without
    a failed window are not evidence by themselves; a passing window after it is needed too."""
    nis = Violation(kind="nis", ids=(), step=1, value=4.0, bound=3.7)
    verdict = Verdict(clear_after=10)
    verdict.update(1, [nis], ())
    assert {verdict.update(k, [], ()) for k in range(2, 500)} == {"tuning"}  # no window
    assert verdict.update(500, [], (), passed=("nis",)) == "ok"  # long ago, and one passed
    # a pass soon after: it still stands its clear_after states, then clears
    verdict.update(600, [nis], ())
    verdict.update(603, [], (), passed=("nis",))
    assert [verdict.update(k, [], ()) for k in (610, 611)] == ["tuning", "ok"]
    # a new failure after a pass needs a new pass
    verdict.update(700, [nis], ())
    verdict.update(701, [], (), passed=("nis",))
    verdict.update(702, [nis], ())
    assert verdict.update(800, [], ()) == "tuning"
    # the same state's newest window decides: failed then passed counts as passed after it
    other = Verdict(clear_after=10)
    other.update(1, [nis], (), passed=("nis",))
    assert other.update(12, [], ()) == "ok"


def test_a_nis_pass_clears_no_other_kind_and_other_kinds_keep_their_rule() -> None:
    verdict = Verdict(clear_after=10)
    verdict.update(1, [v("nees"), v("nis")], ())
    assert verdict.update(5, [], (), passed=("nis",)) == "tuning"
    assert [s.kind for s in verdict.standing()] == ["nees", "nis"]
    assert verdict.update(12, [], ()) == "ok"  # the NEES by clear_after, the NIS by both
