"""The verdict in words (common/verdict.py): one wording for the page, the picture's legend
and the terminal — each kind named once, pairs low–high, plain numbers."""

from __future__ import annotations

import numpy as np

from slamlens.common.messages import Health, Violation
from slamlens.common.verdict import (
    WORDS,
    summary_text,
    verdict_text,
    violation_head,
    violation_text,
)
from slamlens.services.monitor import verdict as monitor_verdict


def health(**fields: object) -> Health:
    base: dict[str, object] = {"robot": "r", "seq": 900, "stamp": 90.0, "ok": True,
                               "suspects": np.zeros(0, np.int64)}
    return Health(**{**base, **fields})  # type: ignore[arg-type]


def test_each_violation_is_named_once_pairs_low_to_high() -> None:
    assert violation_head(Violation("pair", (12, 3), 5, 1e-3)) == "pair 3–12"
    assert violation_head(Violation("feature", (3,), 5, 1e-3)) == "feature 3"  # not doubled
    assert violation_head(Violation("nees", (), 5, 40.0)) == "NEES pose"
    assert violation_head(Violation("nees", (7,), 5, 40.0)) == "NEES feature 7"
    assert violation_head(Violation("nis", (), 5, 9.0)) == "NIS"
    assert violation_head(Violation("psd", (7, 3), 5, 1e-3)) == "covariance not PSD (features 3, 7)"
    standing = Violation("pair", (np.int64(12), np.int64(3)), np.int64(9), np.float64(2e-3),
                         first_step=np.int64(4), count=np.int64(6))
    text = violation_text(standing)
    assert text == "pair 3–12: growth 0.002 (since seq 4, in 6 states)"
    assert "np." not in text and "int64" not in text
    detailed = Violation("nees", (), 9, 40.0, bound=9.0, detail="mean pose NEES 40 over 100 "
                                                                "states, above [2.4, 3.6]")
    assert violation_text(detailed) == ("NEES pose: mean pose NEES 40 over 100 states, above "
                                        "[2.4, 3.6]")


def test_the_summary_is_the_verdict_and_what_keeps_it_up() -> None:
    assert summary_text(health()) == "ok" == WORDS["ok"]
    fault = health(verdict="fault", verdict_since=812, suspects=np.array([12, 3]), standing=(
        Violation("pair", (12, 3), 899, 2e-3, first_step=812, count=40),
        Violation("feature", (3,), 899, 1e-3, first_step=812, count=30),
        Violation("feature", (12,), 899, 1e-3, first_step=813, count=30),
        Violation("psd", (), 899, 1e-4, first_step=850, count=2)))
    assert verdict_text(fault) == "estimator fault since seq 812"
    assert summary_text(fault) == ("estimator fault since seq 812: pair 3–12, feature 3, "
                                   "feature 12 (+1 more); suspects 3, 12")
    tuning = health(verdict="tuning", verdict_since=40, standing=(
        Violation("nees", (), 899, 36.0, first_step=40, count=500),))
    assert summary_text(tuning) == ("inconsistent tuning or model mismatch since seq 40: "
                                    "NEES pose")
    # the monitor's module speaks the same words
    assert monitor_verdict.WORDS is WORDS and monitor_verdict.summary_text is summary_text


def test_spurious_information_is_an_estimator_fault_in_words() -> None:
    v = Violation("unobservable", (), 611, 0.0794, bound=1e-6, phase="update",
                  detail="information in the unobservable directions grew by 0.0794",
                  first_step=611, count=1)
    assert violation_head(v) == "spurious information in an unobservable direction"
    assert violation_text(v).startswith("spurious information in an unobservable direction: "
                                        "information in the unobservable directions grew")
    held = Health.from_bytes(health(ok=False, violations=(v,), verdict="fault",
                                    verdict_since=611, standing=(v,)).to_bytes())
    assert held.violations[0].kind == "unobservable"  # on the wire, decoded
    assert summary_text(held) == ("estimator fault since seq 611: spurious information in an "
                                  "unobservable direction")
    assert "unobservable" in monitor_verdict.FAULT_KINDS


def test_ok_with_a_timid_nis_standing_says_why_it_is_ok() -> None:
    low = Violation("nis", (), 899, 0.5, bound=0.9, first_step=60, count=300)
    assert summary_text(health(standing=(low,))) == (
        "ok (NIS below its band while the pose NEES is in its band: S is conservative)")
    # the truth judged the pose recently: nothing more to say; long ago: when
    recent = health(standing=(low,), statistics={"nees_pose_judged_seq": 880.0})
    assert summary_text(recent) == summary_text(health(standing=(low,)))
    old = health(standing=(low,), statistics={"nees_pose_judged_seq": 412.0})
    assert summary_text(old) == (
        "ok (NIS below its band while the pose NEES is in its band: S is conservative; "
        "pose NEES last judged at seq 412)")
    assert summary_text(health(statistics={"nees_pose_judged_seq": 412.0})) == "ok"
