"""One verdict per robot that a person can trust.

``Health.ok`` says whether *this* state broke anything; a person wants to know whether the
estimator is right *now*, and a single clean state proves nothing while a fault stands (an
update fault shows only on update states, for instance). :class:`Verdict` keeps the
violations that stand and gives one word for them:

* ``fault`` — a covariance theorem or a structural property is broken (pair, feature,
  prediction, symmetry, psd, correlation, unobservable): a programming fault in the
  estimator;
* ``tuning`` — only the statistical tests fail (NEES / NIS outside their bands): the filter
  is overconfident or its models do not fit the data, but it computes what it should;
* ``ok`` — nothing stands, or only a NIS window *below* its band while the truth says the
  pose covariance is right (the newest pose NEES window judged passed, none stands
  failed): the innovations are smaller than S, so S is conservative, and the state's
  covariance — what the verdict is about — is borne out by the truth. Real sensors do this
  when their errors persist between sightings (R then holds a part the innovations do not
  see). It stays listed in the standing violations. The truth's word stands until a pose
  NEES window fails, also where the truth stops (a robot out of the motion-capture area):
  evidence stands until evidence contradicts it, as for a failed NIS window below.
  Without any truth a timid NIS makes ``tuning``.

Clearance rule (docs/monitor.md): a violation stands from the state it was seen in until
``clear_after`` further states were checked without it (same kind, same ids); a ``fault``
also stands while the monitor names any suspect (its blame evidence decays with the
monitor's half-life). A NIS violation also needs a NIS window that passed after it: its
windows complete only as innovations come (on real data hundreds or thousands of states
apart), so states without one are no evidence that the innovations fit again.
The page, the picture's legend, the terminal and ``slamlens status``
all show this one verdict and its standing violations.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from slamlens.common.messages import Violation
from slamlens.common.verdict import (  # noqa: F401  (the one wording: common/verdict.py)
    WORDS,
    below_band,
    summary_text,
)

FAULT_KINDS = ("pair", "feature", "prediction", "symmetry", "psd", "correlation",
               "unobservable")
TUNING_KINDS = ("nees", "nis")
#: kinds that clear only once a window of theirs passed, too (module docstring)
CLEARED_BY_A_PASS = ("nis",)
VERDICTS = ("ok", "fault", "tuning")
_RANK = {k: i for i, k in enumerate(FAULT_KINDS + TUNING_KINDS)}


@dataclass
class _Standing:
    first: int  #: seq where first seen
    last: int  #: seq where last seen
    count: int  #: states it was seen in
    worst: Violation  #: the largest value seen
    shown: Violation | None = None  #: as listed (rebuilt only when it changed)
    passed: bool = False  #: a window of its kind passed since it was last seen


class Verdict:
    """The standing violations and the one-word verdict (module docstring)."""

    def __init__(self, *, clear_after: int = 200, max_listed: int = 20) -> None:
        self.clear_after = int(clear_after)
        self.max_listed = int(max_listed)
        self.reset()

    def reset(self) -> None:
        self._standing: dict[tuple[str, tuple[int, ...], bool], _Standing] = {}
        self._listed: tuple[Violation, ...] | None = ()  #: None: to be rebuilt
        self.verdict = "ok"
        self.since: int | None = None  #: seq where the current verdict began

    def update(self, seq: int, found: list[Violation], suspects: tuple[int, ...], *,
               pose_consistent: bool = False, passed: tuple[str, ...] = ()) -> str:
        """Take the violations of state ``seq`` and the current suspects; the verdict.
        ``pose_consistent``: the truth's latest word is that the pose covariance is right (module
        docstring: a NIS window below its band then does not make ``tuning``). ``passed``:
        the kinds of :data:`CLEARED_BY_A_PASS` whose newest window, at this state, passed
        (a failed window of the same state before it then counts as passed after)."""
        for v in found:
            key = (v.kind, tuple(sorted(v.ids)), below_band(v))  # two sides stand apart
            s = self._standing.get(key)
            if s is None:
                self._standing[key] = _Standing(first=seq, last=seq, count=1, worst=v)
            else:
                s.last, s.count, s.shown, s.passed = seq, s.count + 1, None, False
                if v.value > s.worst.value:
                    s.worst = v
            self._listed = None
        for key, s in self._standing.items():
            if key[0] in passed:
                s.passed = True
        expired = [k for k, s in self._standing.items() if seq - s.last > self.clear_after
                   and (s.passed or k[0] not in CLEARED_BY_A_PASS)]
        for key in expired:
            del self._standing[key]
            self._listed = None
        kinds = {kind for kind, _, low in self._standing
                  if not (kind == "nis" and low and pose_consistent)}
        if kinds & set(FAULT_KINDS) or suspects:
            verdict = "fault"
        elif kinds & set(TUNING_KINDS):
            verdict = "tuning"
        else:
            verdict = "ok"
        if verdict != self.verdict:
            self.verdict, self.since = verdict, (None if verdict == "ok" else seq)
        return verdict

    def standing(self) -> tuple[Violation, ...]:
        """The standing violations, faults first then the largest, each once with the
        seq where it began (``first_step``) and how many states showed it."""
        if self._listed is not None:  # nothing changed since the last state: on a hot path
            return self._listed
        items = sorted(self._standing.values(),
                       key=lambda s: (_RANK.get(s.worst.kind, 99), -s.worst.value))
        for s in items[:self.max_listed]:
            if s.shown is None:
                s.shown = dataclasses.replace(s.worst, step=s.last, first_step=s.first,
                                              count=s.count)
        self._listed = tuple(s.shown for s in items[:self.max_listed])  # type: ignore[misc]
        return self._listed

    @property
    def standing_count(self) -> int:
        return len(self._standing)
