"""The behaviour monitor (docs/monitor.md): checks each SlamState, returns a Health, names suspects.

``Monitor`` is the thin stateful class around the pure checks of ``monitor_checks``, the
statistics of ``monitor_stats`` and the pinpointing of ``monitor_blame``. It keeps only what
the next comparison needs: the last *received* state (the Loewner order is transitive, so a
stream with gaps is compared across them), recent truths, windows and blame evidence.

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

import bisect
import dataclasses
import logging
import math
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from slamlens.common.arrays import frozen_array
from slamlens.common.geometry import compose2, inverse2, transform2
from slamlens.common.messages import Health, SlamState, Truth, Violation
from slamlens.services.monitor import checks
from slamlens.services.monitor.blame import Evidence, blame_weights
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import (
    BlockTerms,
    FeatureWindows,
    WindowTest,
    block_terms,
    feature_nees,
    match_ids,
    pose_nees,
    quadratic_forms_2x2,
)
from slamlens.services.monitor.unobservable import (
    UnobservableCheck,
    declares_fej,
    predict_points,
)
from slamlens.services.monitor.verdict import Verdict

log = logging.getLogger(__name__)

#: Kinds that say the covariance theorems were broken (a fault onset); nees / nis are
#: statistical and do not make suspects.
BLAME_KINDS = ("pair", "feature", "prediction")
_add_reduce, _max_reduce = np.add.reduce, np.maximum.reduce
_NO_IDS = frozen_array(np.zeros(0), "<i8")  #: read-only: one for every Health without suspects
_NO_PAIRS = frozen_array(np.zeros((0, 2)), "<i8")
#: truths kept for matching: all those a state still to come may need (no older than the
#: newest state checked, less the tolerance), up to this many (a memory bound, counted)
_TRUTH_BUFFER = 8192
_PENDING = 256  # states kept waiting for a late truth (beyond: counted ``truth_missing``)


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


@dataclass
class _Pending:
    """A checked state still waiting for its truth (truth may arrive after the state)."""

    seq: int
    stamp: float
    pose: np.ndarray
    Pvv: np.ndarray
    ids: np.ndarray
    landmarks: np.ndarray
    terms: BlockTerms


@dataclass(frozen=True)
class _Screened:
    """What the batched screen (``monitor_checks.screen_*``) proved clean for one state."""

    state: SlamState  #: the state screened (held: its id keys the screen)
    prev: SlamState | None  #: the previous state the pair tests assumed
    structure: bool  #: no asymmetry, no |ρ| > 1
    psd: bool  #: PSD within tolerance
    #: against ``prev`` (same landmarks, same order): (map block unchanged, nothing grew,
    #: predict-step tests pass); None: the per-state tests decide
    pair: tuple[bool, bool, bool] | None
    terms: BlockTerms  #: the features' own blocks, for their NEES
    factor: np.ndarray | None  #: lower Cholesky factor of sym(P) + tol·I (PSD screen)
    #: where this state's prediction Fx is measured from (None: not checkable)
    before: np.ndarray | None


class Monitor:
    """Checks each state against the theory and the previous state; see module docstring."""

    def __init__(self, settings: MonitorSettings) -> None:
        self.settings = settings
        s = settings
        self._nis = WindowTest(dof=2, window=s.nis_window, alpha=s.significance, dependent=False)
        self._nees_pose = WindowTest(dof=3, window=s.nees_window, alpha=s.significance,
                                     dependent=True)
        self._nees_features = FeatureWindows(window=s.nees_window, alpha=s.significance)
        self._evidence = Evidence(half_life=s.evidence_half_life,
                                  suspect_score=s.suspect_score, suspect_ratio=s.suspect_ratio)
        self._truth_sigma2 = np.square(np.resize(np.asarray(s.truth_pose_sigma, float), 3))
        self._truth_cov = np.diag(self._truth_sigma2)  #: added to Pvv for the pose NEES
        self._verdict = Verdict(clear_after=s.clear_after,
                                max_listed=s.max_violations_per_kind)
        self._unobservable = UnobservableCheck()
        self.reset()

    # -- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything: previous state, truths, windows, evidence, counts."""
        self._prev: SlamState | None = None
        self._truth_stamps: list[float] = []
        self._truths: list[Truth] = []
        self._pending: deque[_Pending] = deque()
        self._pending_span = (math.inf, -math.inf)  #: bounds of the stamps waiting
        self._late: list[Violation] = []
        self._checked_stamp = -math.inf  #: stamp of the newest state checked
        self._truth_seen = False  #: any truth (or tracked pose) ever came
        self._pending_dropped = 0  #: states pushed out of those waiting for a truth
        self._truth_dropped = 0  #: truths pushed out of the buffer before their state came
        #: (the state's and the truth's landmark ids as bytes, their match_ids)
        self._id_match: tuple[tuple[bytes, bytes], tuple[np.ndarray, np.ndarray]] | None = None
        self._nis.reset()
        self._nees_pose.reset()
        self._nees_features.reset()
        self._evidence.reset()
        self._verdict.reset()
        self._unobservable.reset()
        self._frame_reset()
        self._counts: Counter[str] = Counter()
        self._phase_counts: Counter[str] = Counter()
        self._states = 0
        self._gaps = 0
        self._restarts = 0
        self._onset: tuple[int, float] | None = None
        self._screens: dict[int, _Screened] = {}

    def _restart(self) -> None:
        """A new run of the estimator: drop what belonged to the old one (not the counts)."""
        self._pending.clear()
        self._pending_span = (math.inf, -math.inf)
        self._late = []
        self._nis.reset()
        self._nees_pose.reset()
        self._nees_features.reset()
        self._evidence.reset()
        self._verdict.reset()
        self._unobservable.reset()

    def new_map(self) -> None:
        """A new epoch (a map started from scratch): nothing of the old map compares."""
        self._restarts += 1
        self._restart()
        self._prev = None
        self._frame_reset()

    # -- the map frame of the truth ------------------------------------------------------
    def _frame_reset(self) -> None:
        self._initial_pose = np.zeros(3)  #: the estimator's x_v(0) (its init state says)
        self._origin_stamp: float | None = None  #: when the robot stood at the map origin
        self._map_from_truth: np.ndarray | None = None  #: None: truth is in the map frame

    def _follow_frame(self, state: SlamState) -> None:
        """Truth is given in its own world frame; the map frame is the robot's pose at
        the map's origin (docs/protocol.md). When a state says when that was (``origin_stamp``),
        truth is re-expressed in the map frame — identity for a map started where the
        truth's frame starts, a real change for a map restarted mid-run."""
        if state.step == "init":
            self._initial_pose = np.array(state.pose, dtype=float)
        if state.origin_stamp is None or state.origin_stamp == self._origin_stamp:
            return
        at_origin = self._match_truth(state.origin_stamp, aligned=False)
        if at_origin is None:
            return  # no truth of that instant (yet): try again with the next state
        self._origin_stamp = state.origin_stamp
        T = compose2(self._initial_pose, inverse2(at_origin.pose))
        moved = float(np.hypot(T[0], T[1])) > 1e-9 or abs(float(T[2])) > 1e-12
        self._map_from_truth = T if moved else None
        if moved:
            log.info("truth re-expressed in the map frame of the robot's pose at t = %.3f s "
                     "(%.3f m, %.3f m, %.3f rad)", state.origin_stamp, *at_origin.pose)

    def _aligned(self, truth: Truth) -> Truth:
        T = self._map_from_truth
        if T is None:
            return truth
        return dataclasses.replace(truth, pose=compose2(T, truth.pose),
                                   landmarks=transform2(T, truth.landmarks)
                                   if truth.landmarks.size else truth.landmarks)

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
        self._truth_seen = True
        k = bisect.bisect_right(self._truth_stamps, truth.stamp)
        self._truth_stamps.insert(k, truth.stamp)
        self._truths.insert(k, truth)
        tol = self.settings.truth_tolerance_s
        if len(self._truths) > _TRUTH_BUFFER:
            # those no state to come can match go first (states come in stamp order);
            # then, only if the monitor is that far behind, the oldest (counted)
            stale = bisect.bisect_left(self._truth_stamps, self._checked_stamp - tol)
            drop = max(1, min(stale, len(self._truths) - _TRUTH_BUFFER // 2))
            if stale == 0:
                self._truth_dropped += 1
            del self._truth_stamps[:drop]
            del self._truths[:drop]
        lo, hi = self._pending_span
        # no waiting state near: the stamps of those waiting lie in [lo, hi] and rounded
        # subtraction is monotone, so no |p.stamp − stamp| ≤ tol (the loop's test) holds
        if not self._pending or truth.stamp - hi > tol or lo - truth.stamp > tol:
            return
        still: deque[_Pending] = deque(maxlen=_PENDING)
        for p in self._pending:
            if abs(p.stamp - truth.stamp) <= tol:
                _, _, late = self._nees(p.pose, p.Pvv, p.ids, p.landmarks, p.terms,
                                        self._aligned(truth), seq=p.seq)
                self._late.extend(late)
            else:
                still.append(p)
        self._pending = still
        self._pending_span = (min((p.stamp for p in still), default=math.inf),
                              max((p.stamp for p in still), default=-math.inf))

    @property
    def truth_missing(self) -> int:
        """States whose truth came too far from them to be matched (the buffers' bounds):
        what the NEES windows miss, counted (states with no truth source at all: none)."""
        return (self._pending_dropped if self._truth_seen else 0) + self._truth_dropped

    def _match_truth(self, stamp: float, *, aligned: bool = True) -> Truth | None:
        if not self._truths:
            return None
        k = bisect.bisect_left(self._truth_stamps, stamp)
        best = None
        for j in (k - 1, k):
            if 0 <= j < len(self._truths):
                d = abs(self._truth_stamps[j] - stamp)
                if d <= self.settings.truth_tolerance_s and (best is None or d < best[0]):
                    best = (d, j)
        if best is None:
            return None
        truth = self._truths[best[1]]
        return self._aligned(truth) if aligned else truth

    # -- the batched screen -------------------------------------------------------------
    def prepare(self, states: Sequence[SlamState]) -> None:
        """Screen a burst of states at once, as stacks (``monitor_checks.screen_alone`` /
        ``screen_pairs``): each is then :meth:`check` ed in this order and skips the
        tests the screen found clean. A state checked without being prepared, or after
        another previous state than the screen assumed, is screened on its own, so the
        Health of a burst is the Health of the same states checked one by one."""
        self._screens = {}
        prev = self._prev
        start = 0
        # where each state's prediction linearised, followed through the whole burst
        before = predict_points(self._unobservable.robot, [prev, *states[:-1]], list(states))
        for k in range(1, len(states) + 1):  # runs of one covariance size
            if k == len(states) or states[k].covariance.shape != states[start].covariance.shape:
                self._screen_run(prev, states[start:k], before[start:k])
                prev = states[k - 1]
                start = k

    def _screen_run(self, prev: SlamState | None, run: Sequence[SlamState],
                    before: list[np.ndarray | None] | None = None) -> None:
        s = self.settings
        P = np.stack([x.covariance for x in run])
        K, N = len(run), P.shape[1]
        n = (N - 3) // 2
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            at = np.arange(n)
            blocks = P[:, 3:, 3:].reshape(K, n, 2, n, 2)[:, at, :, at, :]  # [n, K, 2, 2]
            terms = block_terms(blocks.transpose(1, 0, 2, 3),
                                condition_max=s.nees_condition_max)
            alone = checks.screen_alone(P, rtol_symmetry=s.rtol_symmetry,
                                        rtol_correlation=s.rtol_correlation,
                                        rtol_psd=s.rtol_psd, atol=s.atol_growth)
            prevs = [prev, *run[:-1]]
            if before is None:  # one state, after the last one checked
                before = predict_points(self._unobservable.robot, prevs, list(run))
            # the same landmarks in the same order (int64 ids: equal iff their bytes are)
            same = np.array([p is not None and p.landmark_ids.shape == x.landmark_ids.shape
                             and p.landmark_ids.tobytes() == x.landmark_ids.tobytes()
                             for p, x in zip(prevs, run, strict=True)], dtype=bool)
            pairs = None
            if same.any():
                lead = (prev.covariance[None] if same[0] and prev is not None
                        else np.zeros_like(P[:1]))
                P_ext = np.concatenate([lead, P])
                poses = np.stack([np.zeros(3) if p is None else p.pose
                                  for p in [prevs[0], *run]])
                for k, xy in enumerate(before):  # FEJ: from the propagated position
                    if xy is not None:
                        poses[k, :2] = xy
                predict = np.array([s.check_prediction and x.step == "predict"
                                    and p is not None and x.seq == p.seq + 1
                                    and xy is not None
                                    for p, x, xy in zip(prevs, run, before, strict=True)],
                                   dtype=bool)
                at = np.flatnonzero(same)
                whole = at.size == K
                pairs = checks.screen_pairs(
                    P_ext[:-1] if whole else P_ext[at], P if whole else P[at],
                    poses[:-1] if whole else poses[at], poses[1:] if whole else poses[at + 1],
                    predict if whole else predict[at], rtol_growth=s.rtol_growth,
                    atol_growth=s.atol_growth, rtol_prediction=s.rtol_prediction)
                slot = np.full(K, -1)
                slot[at] = np.arange(at.size)
        structure, psd = alone.structure.tolist(), alone.psd.tolist()
        found = None
        if pairs is not None:
            found = (slot.tolist(), pairs.unchanged.tolist(), pairs.growth.tolist(),
                     pairs.prediction.tolist())
        for k, x in enumerate(run):
            pair = None
            if found is not None and found[0][k] >= 0:
                j = found[0][k]
                pair = (found[1][j], found[2][j], found[3][j])
            self._screens[id(x)] = _Screened(
                x, prevs[k], structure[k], psd[k], pair, terms[k],
                alone.factors[k] if alone.factors else None, before[k])

    def _screened(self, state: SlamState, prev: SlamState | None) -> _Screened:
        """The screen of ``state`` after ``prev`` (from :meth:`prepare`, else made now)."""
        got = self._screens.pop(id(state), None)
        if got is None or got.state is not state:
            self._screen_run(prev, [state])
            got = self._screens.pop(id(state))
        if got.prev is not prev:  # checked after another state than the screen assumed
            self._screen_run(prev, [state])
            fresh = self._screens.pop(id(state))
            got = dataclasses.replace(got, prev=prev, pair=fresh.pair, before=fresh.before)
        return got

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
        self._follow_frame(state)
        gap = 0 if prev is None else max(state.seq - prev.seq - 1, 0)
        self._gaps += gap
        stats["gap"] = float(gap)

        pairs = _NO_PAIRS
        direct: list[int] = []
        screened = self._screened(state, prev)
        self._unobservable.advance(state)
        # huge-but-finite covariances may overflow products: the comparisons still decide
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            found += self._check_alone(state, screened)
            if prev is not None:
                pairs, direct, more = self._check_against(prev, state, stats, screened.pair,
                                                          before=screened.before)
                found += more
            found += self._statistics(state, stats, screened.terms)
            found += self._check_unobservable(state, screened, stats)
        found += self._late
        self._late = []
        if self.truth_missing:
            stats["truth_missing"] = float(self.truth_missing)

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
        verdict = self._verdict.update(state.seq, [_finite(v) for v in found], suspects)
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

    # -- checks on one state ---------------------------------------------------------------
    def _check_alone(self, state: SlamState, screened: _Screened) -> list[Violation]:
        out: list[Violation] = []
        if not screened.structure:
            out += self._check_structure(state)
        if not screened.psd:
            out += self._check_psd(state)
        return out

    def _check_structure(self, state: SlamState) -> list[Violation]:
        s = self.settings
        P = state.covariance
        out: list[Violation] = []
        ids = state.landmark_ids
        asym, corr = checks.structure(P, rtol_symmetry=s.rtol_symmetry,
                                      rtol_correlation=s.rtol_correlation, atol=s.atol_growth)
        # the worst entry of each: asymmetry relative to its bound, |ρ| by its excess
        for kind, found, worst, what in (
                ("symmetry", asym, lambda f: f.value / f.bound, "P_ab ≠ P_ba"),
                ("correlation", corr, lambda f: f.value, "|ρ| > 1")):
            if not found.count:
                continue
            k = int(np.argmax(worst(found)))
            a, b = found.index[k]
            out.append(Violation(
                kind=kind, ids=_owners(ids, a, b), step=state.seq,
                value=float(found.value[k]), bound=float(found.bound[k]), phase=state.step,
                detail=f"{found.count} entries with {what}, worst {_name(ids, a)} / "
                       f"{_name(ids, b)}"))
        return out

    def _check_psd(self, state: SlamState) -> list[Violation]:
        s = self.settings
        P = state.covariance
        out: list[Violation] = []
        ids = state.landmark_ids
        neg = checks.min_eigenvalue_if_indefinite(P, rtol=s.rtol_psd, atol=s.atol_growth)
        if neg is not None:
            lam, tol, vec = neg
            # blame-free, but name the features carrying ≥ 10 % of the negative direction
            weight = vec[3:].reshape(-1, 2) ** 2
            per_feature = weight.sum(axis=1) if weight.size else np.zeros(0)
            total = float(np.sum(vec ** 2))
            heavy = (np.flatnonzero(per_feature >= 0.1 * total) if total > 0
                     else np.zeros(0, dtype=np.int64))
            out.append(Violation(
                kind="psd", ids=tuple(int(ids[i]) for i in heavy), step=state.seq,
                value=-lam, bound=tol, phase=state.step,
                detail=f"covariance not PSD: smallest eigenvalue {lam:.3g}"))
        return out

    # -- checks against the previous received state --------------------------------------
    def _check_against(self, prev: SlamState, state: SlamState, stats: dict[str, float],
                       screened: tuple[bool, bool, bool] | None = None, *,
                       before: np.ndarray | None = None
                       ) -> tuple[np.ndarray, list[int], list[Violation]]:
        s = self.settings
        out: list[Violation] = []
        direct: list[int] = []
        if screened is not None:  # the same landmarks in the same order, screened
            pos_prev = pos_cur = np.arange(prev.n)
            unchanged, no_growth, predicted = screened
        else:
            pos_prev, pos_cur = checks.common_landmarks(prev.landmark_ids,
                                                        state.landmark_ids)
            unchanged, no_growth, predicted = False, False, False
        removed = prev.n - pos_prev.shape[0]
        if removed:
            stats["landmarks_removed"] = float(removed)
        ids = prev.landmark_ids[pos_prev]
        pairs = _NO_PAIRS
        if screened is None:
            Pmm_prev = checks.map_block(prev.covariance, pos_prev)
            Pmm_cur = checks.map_block(state.covariance, pos_cur)
            # cheap sufficient test: an untouched map block (every predict) cannot grow
            unchanged = np.array_equal(Pmm_prev, Pmm_cur)
        feats = pair = None
        if not unchanged and not no_growth:
            if screened is not None:  # the screen saw growth: now the blocks are needed
                Pmm_prev = checks.map_block(prev.covariance, pos_prev)
                Pmm_cur = checks.map_block(state.covariance, pos_cur)
            delta = Pmm_prev - Pmm_cur
            feats = checks.feature_growth(Pmm_prev, Pmm_cur, rtol=s.rtol_growth,
                                          atol=s.atol_growth, delta=delta)
            pair = checks.pair_growth(Pmm_prev, Pmm_cur, rtol=s.rtol_growth,
                                      atol=s.atol_growth, delta=delta)
        m = ids.shape[0]
        stats["pairs_checked"] = float(m * (m - 1) // 2)
        stats["pairs_growing"] = float(0 if pair is None else pair.count)
        stats["features_growing"] = float(0 if feats is None else feats.count)
        growth_max = 0.0
        if feats is not None and feats.count:
            growth_max = max(growth_max, float(feats.value.max()))
            for k in self._top(feats.value):
                f = int(ids[feats.index[k]])
                out.append(Violation(
                    kind="feature", ids=(f,), step=state.seq, value=float(feats.value[k]),
                    bound=float(feats.bound[k]), phase=state.step,
                    detail=f"P_ii of feature {f} grew by {feats.value[k]:.3g} m²"))
            direct += [int(f) for f in ids[feats.index]]
        if pair is not None and pair.count:
            growth_max = max(growth_max, float(pair.value.max()))
            pairs = ids[pair.index]
            for k in self._top(pair.value):
                i, j = sorted(int(x) for x in pairs[k])  # a pair is written low–high
                out.append(Violation(
                    kind="pair", ids=(i, j), step=state.seq, value=float(pair.value[k]),
                    bound=float(pair.bound[k]), phase=state.step,
                    detail=f"P_d of features {i}, {j} grew by {pair.value[k]:.3g} m²"))
        stats["growth_max"] = growth_max
        if (s.check_prediction and state.step == "predict"
                and state.seq == prev.seq + 1 and not predicted and before is not None):
            more, blamed = self._check_prediction(prev, state, pos_prev, pos_cur, ids,
                                                  map_unchanged=unchanged, before=before)
            out += more
            direct += blamed
        return pairs, direct, out

    def _top(self, values: np.ndarray) -> np.ndarray:
        limit = self.settings.max_violations_per_kind
        if values.shape[0] <= limit:
            return np.arange(values.shape[0])
        return np.argpartition(-values, limit - 1)[:limit]

    def _check_prediction(self, prev: SlamState, state: SlamState, pos_prev: np.ndarray,
                          pos_cur: np.ndarray, ids: np.ndarray, *, map_unchanged: bool,
                          before: np.ndarray) -> tuple[list[Violation], list[int]]:
        s = self.settings
        map_changed, cross_wrong, noise = checks.prediction_residuals(
            prev.covariance, state.covariance, np.array([before[0], before[1], 0.0]),
            state.pose, pos_prev, pos_cur,
            rtol=s.rtol_prediction, atol=s.atol_growth, map_unchanged=map_unchanged)
        out: list[Violation] = []
        blamed: list[int] = []
        for k in range(map_changed.count):
            f = int(ids[map_changed.index[k]])
            blamed.append(f)
            out.append(Violation(
                kind="prediction", ids=(f,), step=state.seq, value=float(map_changed.value[k]),
                bound=float(map_changed.bound[k]), phase="predict",
                detail=f"P_mm rows of feature {f} changed in a predict (must be untouched)"))
        for k in range(cross_wrong.count):
            f = int(ids[cross_wrong.index[k]])
            blamed.append(f)
            out.append(Violation(
                kind="prediction", ids=(f,), step=state.seq, value=float(cross_wrong.value[k]),
                bound=float(cross_wrong.bound[k]), phase="predict",
                detail=f"P_v,m of feature {f} ≠ Fx·P_v,m(previous): cross-covariance not "
                       f"propagated"))
        if noise is not None:
            out.append(Violation(
                kind="prediction", ids=(), step=state.seq, value=-noise, bound=0.0,
                phase="predict",
                detail=f"Pvv − Fx·Pvv·Fxᵀ not PSD (λ_min {noise:.3g}): process noise "
                       f"negative"))
        return out, blamed

    # -- the unobservable directions (monitor_unobservable.py) ---------------------------
    def _check_unobservable(self, state: SlamState, screened: _Screened,
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
                            theorem=s.check_unobservable == "always" or declares_fej(state))
        return [] if v is None else [v]

    # -- statistics ----------------------------------------------------------------------
    def _statistics(self, state: SlamState, stats: dict[str, float], terms: BlockTerms
                    ) -> list[Violation]:
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
                if r.failed:
                    out.append(Violation(
                        kind="nis", ids=(), step=state.seq, value=r.mean, bound=_side(r),
                        phase="update", detail=f"mean NIS {r.mean:.3g} over {r.samples} "
                                               f"innovations outside [{r.lo:.3g}, {r.hi:.3g}]"))
        if self._nis.sliding_mean is not None:
            stats["nis_window_mean"] = self._nis.sliding_mean
            stats["nis_window_lo"], stats["nis_window_hi"] = self._nis.lo, self._nis.hi

        self._checked_stamp = max(self._checked_stamp, state.stamp)
        truth = self._match_truth(state.stamp)
        if truth is None:
            lo, hi = self._pending_span  # (still a bound when the oldest is pushed out)
            self._pending_span = (min(lo, state.stamp), max(hi, state.stamp))
            if len(self._pending) >= _PENDING:
                self._pending.popleft()
                self._pending_dropped += 1
            self._pending.append(_Pending(state.seq, state.stamp, state.pose,
                                          state.covariance[:3, :3], state.landmark_ids,
                                          state.landmarks, terms))
        else:
            nees_p, nees_f, more = self._nees(state.pose, state.covariance[:3, :3],
                                              state.landmark_ids, state.landmarks, terms,
                                              truth, seq=state.seq)
            out += more
            if nees_p is not None:
                stats["nees_pose"] = nees_p
                stats["nees_pose_lo"] = self._nees_pose.sample_lo
                stats["nees_pose_hi"] = self._nees_pose.sample_hi
            if nees_f.size:  # (np.mean is this sum over the count: the same float)
                stats["nees_features_mean"] = float(_add_reduce(nees_f) / nees_f.size)
                stats["nees_features_max"] = float(_max_reduce(nees_f))
        if self._nees_pose.sliding_mean is not None:
            stats["nees_pose_window_mean"] = self._nees_pose.sliding_mean
            stats["nees_pose_window_lo"] = self._nees_pose.lo
            stats["nees_pose_window_hi"] = self._nees_pose.hi
        return out

    def _nees(self, pose: np.ndarray, Pvv: np.ndarray, ids: np.ndarray, landmarks: np.ndarray,
              terms: BlockTerms, truth: Truth, *, seq: int
              ) -> tuple[float | None, np.ndarray, list[Violation]]:
        s = self.settings
        out: list[Violation] = []
        nees_p = pose_nees(pose, Pvv + self._truth_cov, truth.pose,
                           condition_max=s.nees_condition_max)
        if nees_p is not None:
            r = self._nees_pose.add_one(nees_p)
            if r is not None and r.failed:
                out.append(Violation(
                    kind="nees", ids=(), step=seq, value=r.mean, bound=_side(r),
                    detail=f"mean pose NEES {r.mean:.3g} over {r.samples} states outside "
                           f"[{r.lo:.3g}, {r.hi:.3g}]"))
        # the id sets change rarely: reuse the last match (cheaper than intersect1d); int64
        # arrays are equal exactly when their bytes are
        key = (ids.tobytes(), truth.landmark_ids.tobytes())
        cache = self._id_match
        if cache is None or cache[0] != key:
            cache = (key, match_ids(ids, truth.landmark_ids))
            self._id_match = cache
        fids, nees_f = feature_nees(ids, landmarks, terms, truth.landmarks, cache[1])
        for fid, r in self._nees_features.add(fids, nees_f):
            if r.failed:
                out.append(Violation(
                    kind="nees", ids=(fid,), step=seq, value=r.mean, bound=_side(r),
                    detail=f"mean NEES of feature {fid} {r.mean:.3g} over {r.samples} states "
                           f"outside [{r.lo:.3g}, {r.hi:.3g}]"))
        return nees_p, nees_f, out


def _finite(v: Violation) -> Violation:
    """Health carries finite numbers only (decoders reject NaN/∞): clip overflows."""
    if math.isfinite(v.value) and (v.bound is None or math.isfinite(v.bound)):
        return v
    clip = 1e300
    value = clip if math.isnan(v.value) else max(-clip, min(clip, v.value))
    bound = None if v.bound is None or math.isnan(v.bound) else max(-clip, min(clip, v.bound))
    return dataclasses.replace(v, value=value, bound=bound)


def _side(r: object) -> float:
    """The band edge a failed window crossed."""
    mean, lo, hi = r.mean, r.lo, r.hi  # type: ignore[attr-defined]
    return float(hi if mean > hi else lo)


def _name(ids: np.ndarray, index: int) -> str:
    """Human name of state index ``index``: robot x/y/θ or feature id x/y."""
    if index < 3:
        return f"robot {'xyθ'[index]}"
    k, axis = divmod(index - 3, 2)
    return f"feature {int(ids[k])} {'xy'[axis]}"


def _owners(ids: np.ndarray, *indices: int) -> tuple[int, ...]:
    """Feature ids owning the state indices given (robot indices own none)."""
    out: list[int] = []
    for index in indices:
        if index >= 3:
            f = int(ids[(index - 3) // 2])
            if f not in out:
                out.append(f)
    return tuple(out)
