"""The monitor's verdict in words: one wording for every view (page, picture, terminal).

``Health.verdict`` is the robot's verdict now (docs/monitor.md): ``ok``, ``fault`` (an
estimator fault: a covariance theorem or a structural property broken) or ``tuning``
(only NEES / NIS outside their bands: inconsistent tuning or model mismatch), kept up by
``Health.standing`` (under ``ok``, at most a NIS window below its band while the truth bears
the pose covariance out). The web page's top bar and violations panel, the picture's legend,
``slamlens demo``'s summary line and the monitor's log all say it with these functions,
so they cannot contradict each other. Pure: plain Python numbers in, text out (no numpy
reprs, pairs written low–high, each kind named once).
"""

from __future__ import annotations

from collections.abc import Sequence

from slamlens.common.messages import Health, Violation

#: the verdict in words, as every view shows it
WORDS = {"ok": "ok", "fault": "estimator fault",
         "tuning": "inconsistent tuning or model mismatch"}

#: why a NIS window below its band may stand under "ok" (docs/monitor.md, "The verdict")
CONSERVATIVE = "NIS below its band while the pose NEES is in its band: S is conservative"
#: states after the newest pose NEES window judged beyond which that "ok" names its seq
#: (the truth stopped; its word stands until a window fails — docs/monitor.md)
TRUTH_QUIET_STATES = 50

#: what each kind of violation is, as a reader names it
KIND_NAMES = {"pair": "pair", "feature": "feature", "prediction": "prediction",
              "symmetry": "asymmetric covariance", "psd": "covariance not PSD",
              "correlation": "correlation beyond ±1", "nees": "NEES", "nis": "NIS",
              "unobservable": "spurious information in an unobservable direction"}


def below_band(v: Violation) -> bool:
    """A statistical window (NEES, NIS) that left its band from below: smaller than the
    covariance says."""
    return v.kind in ("nees", "nis") and v.bound is not None and v.value < v.bound


def conservative(health: Health) -> bool:
    """"ok" with a NIS window below its band standing (docs/monitor.md, "The verdict")."""
    return health.verdict == "ok" and any(v.kind == "nis" and below_band(v)
                                          for v in health.standing)


def _ids(ids: Sequence[int]) -> list[int]:
    return sorted(int(i) for i in ids)


def violation_head(v: Violation) -> str:
    """What is violated, e.g. "pair 3–12", "feature 3", "NEES pose", "NIS",
    "covariance not PSD (features 3, 7)"."""
    ids = _ids(v.ids)
    if v.kind == "pair" and len(ids) == 2:
        return f"pair {ids[0]}–{ids[1]}"
    if v.kind == "feature" and len(ids) == 1:
        return f"feature {ids[0]}"
    name = KIND_NAMES.get(v.kind, v.kind)
    if v.kind == "nees" and not ids:
        return "NEES pose"
    if not ids:
        return name
    if len(ids) == 1:
        return f"{name} feature {ids[0]}"
    return f"{name} (features {', '.join(str(i) for i in ids)})"


def violation_text(v: Violation) -> str:
    """One line for one violation: what, the monitor's sentence (or the value) and, for a
    standing one, since when and how often."""
    text = violation_head(v)
    if v.detail:
        text += f": {v.detail}"
    else:
        key = "statistic" if v.kind in ("nees", "nis") else "growth"
        text += f": {key} {float(v.value):.3g}"
        if v.bound is not None:
            text += f" (bound {float(v.bound):.3g})"
    if v.first_step is not None:
        count = "" if v.count is None else f", in {int(v.count)} states"
        text += f" (since seq {int(v.first_step)}{count})"
    return text


def verdict_text(health: Health) -> str:
    """The verdict with its start: "ok", "estimator fault since seq 812" …"""
    words = WORDS.get(health.verdict, health.verdict)
    if health.verdict != "ok" and health.verdict_since is not None:
        words += f" since seq {int(health.verdict_since)}"
    return words


def summary_text(health: Health, *, max_items: int = 3) -> str:
    """The verdict in one line: "estimator fault since seq 812: pair 3–12, feature 3 (+2
    more); suspects 3, 12" — what the top bar, the legend and the terminal say."""
    text = verdict_text(health)
    if health.verdict == "ok":
        if not conservative(health):
            return text
        judged = health.statistics.get("nees_pose_judged_seq")
        if judged is not None and health.seq - judged > TRUTH_QUIET_STATES:
            return f"{text} ({CONSERVATIVE}; pose NEES last judged at seq {int(judged)})"
        return f"{text} ({CONSERVATIVE})"
    heads: list[str] = []
    for v in health.standing:
        head = violation_head(v)
        if head not in heads:
            heads.append(head)
    if heads:
        more = len(heads) - max_items
        text += ": " + ", ".join(heads[:max_items]) + (f" (+{more} more)" if more > 0 else "")
    suspects = _ids(health.suspects.tolist())
    if suspects:
        text += "; suspects " + ", ".join(str(s) for s in suspects)
    return text
