"""The monitor's truth and NEES bookkeeping (docs/monitor.md, "NEES").

:class:`TruthTracker` keeps the truths (simulator, dataset or camera-tracked pose) a state
still to come may need, re-expresses them in the map frame, matches each checked state with
the truth of its stamp, and runs the pose and per-feature NEES windows. A state whose truth
has not come yet waits (bounded); its NEES is computed when the truth comes, and the window
results are reported with the next state checked. It does no check of its own on the
covariance.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from slamlens.common.geometry import compose2, inverse2, transform2
from slamlens.common.messages import SlamState, Truth, Violation
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import (
    NEES_READING,
    BlockTerms,
    FeatureWindows,
    WindowTest,
    feature_nees,
    match_ids,
    pose_nees,
    window_detail,
)

log = logging.getLogger(__name__)

_add_reduce, _max_reduce = np.add.reduce, np.maximum.reduce
#: truths kept for matching: all those a state still to come may need (no older than the
#: newest state checked, less the tolerance), up to this many (a memory bound, counted)
_TRUTH_BUFFER = 8192
_PENDING = 256  # states kept waiting for a late truth (beyond: counted ``truth_missing``)


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


class TruthTracker:
    """Truths by stamp, the map frame they are re-expressed in, and the NEES windows."""

    def __init__(self, settings: MonitorSettings) -> None:
        self.settings = s = settings
        self._nees_pose = WindowTest(dof=3, window=s.nees_window, alpha=s.significance,
                                     band="dependent")
        self._nees_features = FeatureWindows(window=s.nees_window, alpha=s.significance)
        self._truth_sigma2 = np.square(np.resize(np.asarray(s.truth_pose_sigma, float), 3))
        self._truth_cov = np.diag(self._truth_sigma2)  #: added to Pvv for the pose NEES
        self.reset()

    def reset(self) -> None:
        """Forget every truth, the frame, the states waiting, the windows and the counts."""
        self._truth_stamps: list[float] = []
        self._truths: list[Truth] = []
        self._checked_stamp = -math.inf  #: stamp of the newest state checked
        self._truth_seen = False  #: any truth (or tracked pose) ever came
        self._pending_dropped = 0  #: states pushed out of those waiting for a truth
        self._truth_dropped = 0  #: truths pushed out of the buffer before their state came
        #: (the state's and the truth's landmark ids as bytes, their match_ids)
        self._id_match: tuple[tuple[bytes, bytes], tuple[np.ndarray, np.ndarray]] | None = None
        self.restart()
        self.frame_reset()

    def restart(self) -> None:
        """A new run of the estimator: drop the states waiting, the NEES results not yet
        reported and the windows (the truths and the counts stay)."""
        self._pending: deque[_Pending] = deque()
        self._pending_span = (math.inf, -math.inf)  #: bounds of the stamps waiting
        self._late: list[Violation] = []
        self._nees_pose.reset()
        self._nees_features.reset()
        #: (seq, passed) of the newest pose NEES window judged (None: none since the start)
        self._pose_window: tuple[int, bool] | None = None

    def pose_nees_in_band(self) -> bool:
        """Whether the newest pose NEES window judged since the estimator's start passed:
        the truth's latest word is that the pose covariance is right. It stands until a
        window fails, however many states come without a truth (as a failed NIS window
        stands until one passes; docs/monitor.md, "The verdict"). False before any."""
        w = self._pose_window
        return w is not None and w[1]

    def take_late(self) -> list[Violation]:
        """The NEES window results of states whose truth came after them, once each."""
        late, self._late = self._late, []
        return late

    # -- the map frame of the truth ------------------------------------------------------
    def frame_reset(self) -> None:
        self._initial_pose = np.zeros(3)  #: the estimator's x_v(0) (its init state says)
        self._origin_stamp: float | None = None  #: when the robot stood at the map origin
        self._map_from_truth: np.ndarray | None = None  #: None: truth is in the map frame

    def follow_frame(self, state: SlamState) -> None:
        """Truth is given in its own world frame; the map frame is the robot's pose at
        the map's origin (docs/protocol.md). When a state says when that was (``origin_stamp``),
        truth is re-expressed in the map frame — identity for a map started where the
        truth's frame starts, a real change for a map restarted mid-run."""
        if state.step == "init":
            self._initial_pose = np.array(state.pose, dtype=float)
        if state.origin_stamp is None or state.origin_stamp == self._origin_stamp:
            return
        at_origin = self.match(state.origin_stamp, aligned=False)
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

    # -- truth ---------------------------------------------------------------------------
    def add(self, truth: Truth) -> None:
        """Keep a truth for states of a nearby stamp; states already checked that were
        waiting for it get their NEES now (reported by :meth:`take_late`)."""
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
    def missing(self) -> int:
        """States whose truth came too far from them to be matched (the buffers' bounds):
        what the NEES windows miss, counted (states with no truth source at all: none)."""
        return (self._pending_dropped if self._truth_seen else 0) + self._truth_dropped

    def match(self, stamp: float, *, aligned: bool = True) -> Truth | None:
        """The truth nearest ``stamp`` within the tolerance (in the map frame unless
        ``aligned`` is False); None if there is none."""
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

    # -- NEES ----------------------------------------------------------------------------
    def check(self, state: SlamState, stats: dict[str, float], terms: BlockTerms
              ) -> list[Violation]:
        """The NEES of a checked state against its truth, or the state kept waiting for
        it; the window results that failed as violations, the figures into ``stats``."""
        out: list[Violation] = []
        self._checked_stamp = max(self._checked_stamp, state.stamp)
        truth = self.match(state.stamp)
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
        if self._pose_window is not None:  # whose word the verdict stands on
            stats["nees_pose_judged_seq"] = float(self._pose_window[0])
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
            if r is not None:
                self._pose_window = (seq, not r.failed)
            if r is not None and r.failed:
                out.append(Violation(
                    kind="nees", ids=(), step=seq, value=r.mean, bound=r.edge,
                    detail=window_detail("mean pose NEES", r, "states", NEES_READING)))
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
                    kind="nees", ids=(fid,), step=seq, value=r.mean, bound=r.edge,
                    detail=window_detail(f"mean NEES of feature {fid}", r, "states",
                                         NEES_READING)))
        return nees_p, nees_f, out
