"""The behaviour monitor (docs/monitor.md): checks each SlamState, returns a Health, names suspects.

``Monitor`` is the thin stateful class that assembles the Health: it keeps the last
*received* state (the Loewner order is transitive, so a stream with gaps is compared across
them), the NIS window, the blame evidence and the verdict, and hands the rest to the parts
that each do one job: the batched screen (``screen``), the covariance theorems on each state
(``theorems``, over the pure checks of ``checks``), the truth and NEES bookkeeping
(``truth``), the unobservable directions (``unobservable``) and the pinpointing (``blame``).

Checks per state (docs/monitor.md has the full list and the reasons for each tolerance):

* on the state alone: symmetry, positive semi-definiteness, |correlation| ≤ 1;
* against the last received state: every common feature's P_ii and every common pair's P_d
  non-increasing in the Loewner order ("feature", "pair");
* after a predict that immediately follows the last received state: P_mm unchanged,
  P_vm = Fx·P_vm, process noise PSD ("prediction", phase "predict");
* with truth: NEES of pose and features; with innovations: NIS ("nees", "nis"), as windowed
  tests at a documented significance.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from slamlens.common.arrays import frozen_array
from slamlens.common.messages import Health, SlamState, Truth, Violation
from slamlens.services.monitor import checks, invariant, theorems
from slamlens.services.monitor.blame import Evidence, blame_weights
from slamlens.services.monitor.screen import Screen, Screened
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import (
    NIS_READING,
    BlockTerms,
    WindowTest,
    quadratic_forms_2x2,
    window_detail,
)
from slamlens.services.monitor.truth import TruthTracker
from slamlens.services.monitor.unobservable import (
    UnobservableCheck,
    declares_fej,
    declares_invariant,
)
from slamlens.services.monitor.verdict import Verdict

log = logging.getLogger(__name__)

#: Kinds that say the covariance theorems were broken (a fault onset); nees / nis are
#: statistical and do not make suspects.
BLAME_KINDS = ("pair", "feature", "prediction")
_NO_IDS = frozen_array(np.zeros(0), "<i8")  #: read-only: one for every Health without suspects


@dataclass(frozen=True)
class MonitorSummary:
    """What the monitor has seen since its last reset."""

    states: int  #: states checked
    violations: dict[str, int]  #: count of violations by kind (before the per-state cap)
    suspects: tuple[int, ...]  #: current suspects (feature ids)
    onset_seq: int | None  #: seq of the first state with a violation
    onset_stamp: float | None  #: its stamp, s
    phase: str  #: "predict" / "update" / "" : where the covariance faults show up most
    gaps: int  #: states missed (seq jumps)
    restarts: int  #: times seq went backwards (estimator restarted): baseline reset
    scores: dict[int, float] = field(default_factory=dict)  #: blame evidence per feature


class Monitor:
    """Checks each state against the theory and the previous state; see module docstring."""

    def __init__(self, settings: MonitorSettings) -> None:
        self.settings = settings
        s = settings
        self._nis = WindowTest(dof=2, window=s.nis_window, alpha=s.significance,
                               band=s.nis_dependence,
                               measure_after=s.nis_measure_after * s.nis_window)
        self._nis_passed = False  #: the newest NIS window of the state being checked passed
        self._evidence = Evidence(half_life=s.evidence_half_life,
                                  suspect_score=s.suspect_score, suspect_ratio=s.suspect_ratio)
        self._verdict = Verdict(clear_after=s.clear_after,
                                max_listed=s.max_violations_per_kind)
        self._unobservable = UnobservableCheck()
        self._truth = TruthTracker(settings)
        self._screen = Screen(settings, self._unobservable)
        self.reset()

    # -- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything: previous state, truths, windows, evidence, counts."""
        self._prev: SlamState | None = None
        self._truth.reset()
        self._nis.reset()
        self._evidence.reset()
        self._verdict.reset()
        self._unobservable.reset()
        self._counts: Counter[str] = Counter()
        self._phase_counts: Counter[str] = Counter()
        self._states = 0
        self._gaps = 0
        self._restarts = 0
        self._onset: tuple[int, float] | None = None
        self._screen.reset()

    def _restart(self) -> None:
        """A new run of the estimator: drop what belonged to the old one (not the counts)."""
        self._truth.restart()
        self._nis.reset()
        self._evidence.reset()
        self._verdict.reset()
        self._unobservable.reset()

    def new_map(self) -> None:
        """A new epoch (a map started from scratch): nothing of the old map compares."""
        self._restarts += 1
        self._restart()
        self._prev = None
        self._truth.frame_reset()

    @property
    def summary(self) -> MonitorSummary:
        """Counts by kind, current suspects, onset and the fault phase guess."""
        phase = ""
        if self._phase_counts:
            phase = self._phase_counts.most_common(1)[0][0]
        return MonitorSummary(
            states=self._states, violations=dict(self._counts),
            suspects=self._evidence.suspects,
            onset_seq=None if self._onset is None else self._onset[0],
            onset_stamp=None if self._onset is None else self._onset[1],
            phase=phase, gaps=self._gaps, restarts=self._restarts,
            scores=dict(self._evidence.scores))

    # -- truth ---------------------------------------------------------------------------
    def add_truth(self, truth: Truth) -> None:
        """Keep a truth (simulator, dataset or tracked pose) for states of a nearby stamp.

        States already checked that were waiting for this truth get their NEES now; their
        window results are reported with the next state checked.
        """
        self._truth.add(truth)

    @property
    def truth_missing(self) -> int:
        """States whose truth came too far from them to be matched (the buffers' bounds):
        what the NEES windows miss, counted (states with no truth source at all: none)."""
        return self._truth.missing

    # -- the batched screen -------------------------------------------------------------
    def prepare(self, states: Sequence[SlamState]) -> None:
        """Screen a burst of states at once, as stacks (``checks.screen_alone`` /
        ``screen_pairs``): each is then :meth:`check` ed in this order and skips the
        tests the screen found clean. A state checked without being prepared, or after
        another previous state than the screen assumed, is screened on its own, so the
        Health of a burst is the Health of the same states checked one by one."""
        self._screen.prepare(self._prev, states)

    # -- the check -----------------------------------------------------------------------
    def check(self, state: SlamState, *,
              extra_statistics: dict[str, float] | None = None) -> Health:
        """Check one state; returns its Health (robot, seq, stamp of the state checked),
        with ``extra_statistics`` (what the caller knows: backlog, losses) among its own."""
        stats: dict[str, float] = dict(extra_statistics or {})
        found: list[Violation] = []
        prev = self._prev
        if prev is not None and state.seq < prev.seq:
            log.warning("state seq went back from %d to %d: estimator restarted, new baseline",
                        prev.seq, state.seq)
            self._restarts += 1
            self._restart()
            prev = None
        self._truth.follow_frame(state)
        gap = 0 if prev is None else max(state.seq - prev.seq - 1, 0)
        self._gaps += gap
        stats["gap"] = float(gap)

        pairs = theorems.NO_PAIRS
        direct: list[int] = []
        screened = self._screen.take(state, prev)
        self._unobservable.advance(state)
        s = self.settings
        # huge-but-finite covariances may overflow products: the comparisons still decide
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            found += theorems.check_alone(s, state, structure_clean=screened.structure,
                                          psd_clean=screened.psd)
            both = None if prev is None else invariant.compared(prev, state)
            if both is not None:  # the invariant EKF compares its updates in ξ
                pair = screened.pair if both[1] is state else None
                pairs, direct, more = theorems.check_against(
                    s, *both, stats, pair, before=screened.before)
                found += more
            elif prev is not None:
                stats["growth_unchecked"] = 1.0
            found += self._statistics(state, stats, screened.terms)
            found += self._check_unobservable(state, screened, stats)
        found += self._truth.take_late()
        if self.truth_missing:
            stats["truth_missing"] = float(self.truth_missing)
        return self._health(state, found, stats, direct, pairs)

    def _health(self, state: SlamState, found: list[Violation], stats: dict[str, float],
                direct: list[int], pairs: np.ndarray) -> Health:
        """Blame, counts, onset and verdict from what ``state`` broke; its Health."""
        weights = blame_weights(direct=direct, pairs=pairs, prior=self._evidence.scores)
        self._evidence.step(weights, present=state.landmark_ids)
        suspects = self._evidence.suspects
        if self._evidence.scores:
            stats["suspect_score_max"] = max(self._evidence.scores.values())

        for v in found:
            self._counts[v.kind] += 1
            if v.kind in BLAME_KINDS:
                self._phase_counts[v.phase] += 1
        if found and self._onset is None:
            self._onset = (state.seq, state.stamp)
        self._prev = state
        self._states += 1
        verdict = self._verdict.update(
            state.seq, [_finite(v) for v in found], suspects,
            pose_consistent=self._truth.pose_nees_in_band(),
            passed=("nis",) if self._nis_passed else ())
        self._nis_passed = False
        return Health(robot=state.robot, seq=state.seq, stamp=state.stamp, ok=not found,
                      suspects=frozen_array(suspects, "<i8") if suspects else _NO_IDS,
                      violations=tuple(_finite(v) for v in self._cap(found)),
                      statistics={k: v for k, v in stats.items() if math.isfinite(v)},
                      verdict=verdict, verdict_since=self._verdict.since,
                      standing=self._verdict.standing())

    def _cap(self, found: list[Violation]) -> list[Violation]:
        """At most ``max_violations_per_kind`` per kind, the largest values first."""
        limit = self.settings.max_violations_per_kind
        by_kind: dict[str, list[Violation]] = {}
        for v in found:
            by_kind.setdefault(v.kind, []).append(v)
        out: list[Violation] = []
        for group in by_kind.values():
            if len(group) > limit:
                group = sorted(group, key=lambda v: -v.value)[:limit]
            out += group
        return out

    # -- the unobservable directions (unobservable.py) -----------------------------------
    def _check_unobservable(self, state: SlamState, screened: Screened,
                            stats: dict[str, float]) -> list[Violation]:
        s = self.settings
        if s.check_unobservable == "off":
            return []
        factor = screened.factor
        if factor is None:  # not screened PSD (the stack failed, or P is not): one alone
            factor = checks.psd_factor(state.covariance, rtol=s.rtol_psd, atol=s.atol_growth)
        found = self._unobservable.step(state, factor)
        stats.update(found.statistics)
        v = found.violation(state, rtol=s.rtol_unobservable,
                            theorem=s.check_unobservable == "always" or declares_fej(state)
                            or declares_invariant(state))
        return [] if v is None else [v]

    # -- statistics ----------------------------------------------------------------------
    def _statistics(self, state: SlamState, stats: dict[str, float], terms: BlockTerms
                    ) -> list[Violation]:
        """NIS of the state's innovations (windowed), then its NEES (truth.py)."""
        out: list[Violation] = []
        if state.innovations is not None and state.innovation_covariances is not None \
                and state.innovations.shape[0]:
            nis = quadratic_forms_2x2(state.innovations, state.innovation_covariances)
            bad_S = np.flatnonzero(~np.isfinite(nis))
            for k in bad_S:
                f = int(state.innovation_ids[k]) if state.innovation_ids is not None else -1
                out.append(Violation(
                    kind="psd", ids=(f,) if f >= 0 else (), step=state.seq, value=0.0,
                    phase=state.step, detail=f"innovation covariance S of feature {f} is not "
                                             f"positive definite"))
            good = nis[np.isfinite(nis)]
            if good.size:
                stats["nis"] = float(good.mean())
                stats["nis_lo"], stats["nis_hi"] = self._nis.sample_lo, self._nis.sample_hi
            for r in self._nis.add(good):
                self._nis_passed = not r.failed  # the newest window of this state decides
                if r.failed:
                    out.append(Violation(
                        kind="nis", ids=(), step=state.seq, value=r.mean, bound=r.edge,
                        phase="update",
                        detail=window_detail("mean NIS", r, "innovations", NIS_READING)))
        if self._nis.sliding_mean is not None:
            stats["nis_window_mean"] = self._nis.sliding_mean
            stats["nis_window_lo"], stats["nis_window_hi"] = self._nis.lo, self._nis.hi
            stats["nis_tau"] = self._nis.tau
        return out + self._truth.check(state, stats, terms)


def _finite(v: Violation) -> Violation:
    """Health carries finite numbers only (decoders reject NaN/∞): clip overflows."""
    if math.isfinite(v.value) and (v.bound is None or math.isfinite(v.bound)):
        return v
    clip = 1e300
    value = clip if math.isnan(v.value) else max(-clip, min(clip, v.value))
    bound = None if v.bound is None or math.isnan(v.bound) else max(-clip, min(clip, v.bound))
    return dataclasses.replace(v, value=value, bound=bound)
