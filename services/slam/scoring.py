"""How a run's states compare with the ground truth: pose NEES, its windows and band,
pose and landmark RMSE (absolute and after a rigid fit), dead reckoning — for ``slamlens
tune`` (:mod:`slamlens.services.slam.tuning`), its cross-validation
(:mod:`slamlens.services.slam.crossval`) and the benchmarks and tests that score the real
processes' states. No I/O besides reading the dataset.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor, as_completed
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from slamlens.common.errors import EstimationError
from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Odometry, SlamState, Truth
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import MrclamRun
from slamlens.services.slam.settings import EstimatorSettings

#: states per NEES window (docs/estimator.md)
NEES_WINDOW = 100
#: the pose has 3 degrees of freedom: a consistent filter's NEES averages 3
POSE_DOF = 3
#: NEES is skipped while P_vv is this ill-conditioned (tr³/det, as the monitor)
CONDITION_MAX = 1e10

Progress = Callable[[int], object]


# ---------------------------------------------------------------------------- truth, NEES


@dataclass(frozen=True)
class TruthTrack:
    """Ground truth in the map frame: poses at stamps (interpolated between), landmarks."""

    stamps: np.ndarray  #: float64[G], increasing
    poses: np.ndarray  #: float64[G, 3]
    landmark_ids: np.ndarray  #: int64[L]
    landmarks: np.ndarray  #: float64[L, 2]

    @classmethod
    def from_mrclam(cls, run: MrclamRun, start: float | None = None) -> TruthTrack:
        stamps, poses, landmarks = run.truth_in_map_frame(start)
        return cls(stamps, poses, np.array(run.landmark_ids), landmarks)

    @classmethod
    def from_truths(cls, truths: Iterable[Truth]) -> TruthTrack:
        items = sorted(truths, key=lambda t: t.stamp)
        if not items:
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 2)))
        last = items[-1]
        return cls(np.array([t.stamp for t in items]), np.array([t.pose for t in items]),
                   np.array(last.landmark_ids), np.array(last.landmarks))

    def pose_at(self, t: float) -> np.ndarray | None:
        """The true pose at ``t`` (linear between samples, the angle the short way round);
        None outside the track. Stamps asked in increasing order cost O(1) each."""
        s = self.stamps
        if s.size == 0 or not s[0] <= t <= s[-1]:
            return None
        i = self._index_after(t)
        if i >= s.size:
            return self.poses[-1].copy()
        i = max(i, 1)
        (ax, ay, at), (bx, by, bt) = self.poses[i - 1].tolist(), self.poses[i].tolist()
        s0, s1 = float(s[i - 1]), float(s[i])
        span = s1 - s0
        f = 0.0 if span <= 0 else (t - s0) / span
        return np.array([ax + f * (bx - ax), ay + f * (by - ay),
                         _wrap(at + f * _wrap(bt - at))])

    def covers(self, t: float, *, within_s: float = 0.5, before_s: float = 0.0) -> bool:
        """Whether the track has a sample within ``within_s`` of ``t`` and of every point
        ``within_s`` apart over the ``before_s`` before it (no gap, start or end there)."""
        s = self.stamps
        for k in range(int(before_s / within_s) + 1):
            at = t - k * within_s
            i = int(np.searchsorted(s, at))
            if not any(0 <= j < s.size and abs(float(s[j]) - at) <= within_s
                       for j in (i - 1, i)):
                return False
        return True

    def _index_after(self, t: float) -> int:
        """``searchsorted(stamps, t, side="right")``, walking on from the last answer."""
        s = self.stamps
        i = getattr(self, "_hint", 0)
        if 0 < i < s.size and s[i - 1] <= t < s[i]:
            return i
        if 0 < i + 1 < s.size and s[i] <= t < s[i + 1]:
            object.__setattr__(self, "_hint", i + 1)
            return i + 1
        i = int(np.searchsorted(s, t, side="right"))
        object.__setattr__(self, "_hint", i)
        return i


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def pose_nees(error: np.ndarray, P: np.ndarray) -> float:
    """eᵀ P⁻¹ e for a pose error (heading wrapped); NaN while P is too ill-conditioned
    (tr³/det above :data:`CONDITION_MAX`, or not PD). Closed form on floats: eᵀ adj(P) e / det."""
    (a, b, c), (_, d, e_), (_, _, f) = np.asarray(P, dtype=float).tolist()
    A, B, C = d * f - e_ * e_, c * e_ - b * f, b * e_ - c * d  # adjugate (symmetric P)
    D, E, F = a * f - c * c, b * c - a * e_, a * d - b * b
    det = a * A + b * B + c * C
    tr = a + d + f
    if not (a > 0 and F > 0 and det > 0) or tr ** 3 > CONDITION_MAX * det:
        return math.nan
    x, y, t = np.asarray(error, dtype=float).tolist()
    return (A * x * x + D * y * y + F * t * t + 2.0 * (B * x * y + C * x * t + E * y * t)) / det


def _best_rotation(centred: np.ndarray, truth_centred: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rotation R that best turns ``centred`` onto ``truth_centred`` (Kabsch), with the
    singular values of their cross-covariance and the reflection guard D."""
    U, S, Vt = np.linalg.svd(centred.T @ truth_centred)
    D = np.diag([1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    return Vt.T @ D @ U.T, S, D


def _rmse(fitted: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((fitted - truth) ** 2, axis=1))))


def rigid_fit(estimated: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMSE (m) of ``estimated`` [n, 2] after the rotation and translation that fit it best
    to ``truth`` (Kabsch), and that rotation in degrees."""
    if estimated.shape[0] < 2:
        return math.nan, math.nan
    me, mt = estimated.mean(0), truth.mean(0)
    R, _, _ = _best_rotation(estimated - me, truth - mt)
    fitted = (estimated - me) @ R.T + mt
    return _rmse(fitted, truth), math.degrees(math.atan2(R[1, 0], R[0, 0]))


def similarity_fit(estimated: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMSE (m) of ``estimated`` [n, 2] after the rotation, translation and scale that fit
    it best to ``truth`` (Umeyama), and that scale: how much of a map's shape error is
    scale."""
    if estimated.shape[0] < 2:
        return math.nan, math.nan
    me, mt = estimated.mean(0), truth.mean(0)
    X = estimated - me
    R, S, D = _best_rotation(X, truth - mt)
    scale = float((S * np.diag(D)).sum() / (X ** 2).sum())
    return _rmse(scale * X @ R.T + mt, truth), scale


def nees_band(dof: int = POSE_DOF, confidence: float = 0.95) -> tuple[float, float]:
    """The two-sided ``confidence`` band of one χ²(dof) sample. It is also the band of a
    window mean of NEES along one run (the samples are strongly dependent: the monitor's
    dependence-robust band, docs/monitor.md)."""
    a = (1.0 - confidence) / 2
    return float(stats.chi2.ppf(a, dof)), float(stats.chi2.ppf(1 - a, dof))


@dataclass
class Evaluation:
    """How one run's states compare with the truth."""

    robot: str
    stamps: np.ndarray  #: float64[T], of the states scored
    nees: np.ndarray  #: float64[T], pose NEES (NaN while skipped)
    errors: np.ndarray  #: float64[T, 3], truth − estimate (heading wrapped)
    landmark_ids: np.ndarray  #: of the final map
    landmark_errors: np.ndarray  #: float64[n, 2], truth − estimate, final map
    landmark_rmse: float  #: absolute, m, final map
    landmark_rmse_rigid: float  #: after a rigid fit, m
    map_rotation_deg: float  #: the rigid fit's rotation
    dead_reckoning: np.ndarray | None = None  #: float64[T, 3] errors of odometry alone
    counts: dict[str, float] = field(default_factory=dict)  #: gated, refused …
    nis: np.ndarray | None = None  #: float64[k] NIS νᵀS⁻¹ν of every update (2 expected)
    poses: np.ndarray | None = None  #: float64[T, 3] the estimates scored (for plots)
    sigmas: np.ndarray | None = None  #: float64[T, 3] their standard deviations
    landmarks: np.ndarray | None = None  #: float64[n, 2] the final map (ids above)
    band: tuple[float, float] = field(default_factory=nees_band)

    @property
    def nees_mean(self) -> float:
        return float(np.nanmean(self.nees)) if np.isfinite(self.nees).any() else math.nan

    @property
    def nis_mean(self) -> float:
        """Mean NIS of the updates (2 for a consistent filter: 2 degrees of freedom)."""
        return float(np.mean(self.nis)) if self.nis is not None and self.nis.size else math.nan

    def windows(self, size: int = NEES_WINDOW) -> np.ndarray:
        """Means of consecutive windows of ``size`` scored states (NaN ones left out)."""
        finite = self.nees[np.isfinite(self.nees)]
        k = finite.size // size
        return finite[:k * size].reshape(k, size).mean(axis=1)

    def window_fraction(self, size: int = NEES_WINDOW) -> float:
        """Fraction of those windows inside :attr:`band`."""
        w = self.windows(size)
        lo, hi = self.band
        return float(np.mean((w >= lo) & (w <= hi))) if w.size else math.nan

    @property
    def state_fraction(self) -> float:
        """Fraction of single states whose NEES lies inside :attr:`band`."""
        finite = self.nees[np.isfinite(self.nees)]
        lo, hi = self.band
        return float(np.mean((finite >= lo) & (finite <= hi))) if finite.size else math.nan

    @property
    def pose_rmse(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.errors[:, :2] ** 2, axis=1))))

    @property
    def heading_rmse_deg(self) -> float:
        return math.degrees(float(np.sqrt(np.mean(self.errors[:, 2] ** 2))))

    def dead_reckoning_rmse(self) -> tuple[float, float]:
        """(position m, heading deg) RMSE of odometry alone over the same stamps."""
        e = self.dead_reckoning
        if e is None or not len(e):
            return math.nan, math.nan
        return (float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1)))),
                math.degrees(float(np.sqrt(np.mean(e[:, 2] ** 2)))))

    def summary(self) -> dict[str, Any]:
        dr_pos, dr_head = self.dead_reckoning_rmse()
        return {"robot": self.robot, "states": int(self.stamps.size),
                "nees_mean": round(self.nees_mean, 3),
                "windows_inside": round(self.window_fraction(), 3),
                "states_inside": round(self.state_fraction, 3),
                "nis_mean": round(self.nis_mean, 3),
                "pose_rmse_m": round(self.pose_rmse, 3),
                "heading_rmse_deg": round(self.heading_rmse_deg, 2),
                "landmark_rmse_m": round(self.landmark_rmse, 3),
                "landmark_rmse_rigid_m": round(self.landmark_rmse_rigid, 3),
                "map_rotation_deg": round(self.map_rotation_deg, 2),
                "dead_reckoning_pose_rmse_m": round(dr_pos, 3),
                "dead_reckoning_heading_rmse_deg": round(dr_head, 2),
                "landmarks": int(self.landmark_ids.size), **self.counts}


class Scorer:
    """Scores states one by one against a :class:`TruthTrack` (the states of an offline
    estimator, or those a test received from the real processes)."""

    def __init__(self, truth: TruthTrack, *, robot: str = "",
                 dead_reckoning: TruthTrack | None = None) -> None:
        self.truth = truth
        self.robot = robot
        self.dead = dead_reckoning  #: odometry alone (:func:`dead_reckoning_track`)
        self._stamps: list[float] = []
        self._nees: list[float] = []
        self._errors: list[np.ndarray] = []
        self._dr: list[np.ndarray] = []
        self._poses: list[np.ndarray] = []
        self._sigmas: list[np.ndarray] = []
        self._nis: list[float] = []

    def add_innovations(self, innovations: np.ndarray | None,
                        covariances: np.ndarray | None) -> None:
        """The NIS of one update's innovations (a state's innovations, S)."""
        if innovations is None or covariances is None or not len(innovations):
            return
        nu = np.asarray(innovations).reshape(-1, 2)
        S = np.asarray(covariances).reshape(-1, 2, 2)
        self._nis.extend(float(v) for v in np.einsum("ki,kij,kj->k", nu, np.linalg.inv(S), nu))

    def add(self, stamp: float, pose: np.ndarray, pose_covariance: np.ndarray) -> None:
        """One state: its stamp, pose and P_vv. States outside the truth are skipped."""
        true = self.truth.pose_at(stamp)
        if true is None:
            return
        self._poses.append(np.array(pose, dtype=float))
        self._sigmas.append(np.sqrt(np.maximum(np.diag(pose_covariance), 0.0)))
        e = true - pose
        e[2] = _wrap(float(e[2]))
        self._stamps.append(stamp)
        self._errors.append(e)
        self._nees.append(pose_nees(e, pose_covariance))
        dead = self.dead.pose_at(stamp) if self.dead is not None else None
        if dead is not None:
            dr = true - dead
            dr[2] = float(wrap_angle(dr[2]))
            self._dr.append(dr)

    def add_state(self, state: SlamState) -> None:
        self.add(state.stamp, np.asarray(state.pose), np.asarray(state.covariance)[:3, :3])
        self.add_innovations(state.innovations, state.innovation_covariances)

    def finish(self, landmark_ids: np.ndarray, landmarks: np.ndarray,
               counts: dict[str, float] | None = None) -> Evaluation:
        index = {int(i): k for k, i in enumerate(self.truth.landmark_ids)}
        keep = [k for k, i in enumerate(landmark_ids) if int(i) in index]
        ids = np.asarray(landmark_ids)[keep]
        est = np.asarray(landmarks).reshape(-1, 2)[keep]
        true = self.truth.landmarks[[index[int(i)] for i in ids]] if keep else np.zeros((0, 2))
        err = true - est
        rmse = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))) if keep else math.nan
        rigid, rotation = rigid_fit(est, true)
        return Evaluation(
            robot=self.robot, stamps=np.array(self._stamps), nees=np.array(self._nees),
            errors=np.array(self._errors).reshape(-1, 3), landmark_ids=ids,
            landmark_errors=err, landmark_rmse=rmse, landmark_rmse_rigid=rigid,
            map_rotation_deg=rotation, dead_reckoning=np.array(self._dr).reshape(-1, 3),
            counts=dict(counts or {}), nis=np.array(self._nis),
            poses=np.array(self._poses).reshape(-1, 3),
            sigmas=np.array(self._sigmas).reshape(-1, 3), landmarks=est)


def dead_reckoning_track(run: MrclamRun, start: float | None = None,
                         end: float | None = None) -> TruthTrack:
    """The odometry of ``run.events(start, end)`` integrated alone (the standard model, from the
    map origin): what the robot would believe with no landmarks."""
    x = y = th = 0.0
    stamps, poses = [run.origin_time(start)], [(0.0, 0.0, 0.0)]
    for m in run.events(start, end, truth=False):
        if isinstance(m, Odometry):
            d = m.v * m.dt
            x, y = x + d * math.cos(th), y + d * math.sin(th)
            th = float(wrap_angle(th + m.w * m.dt))
            stamps.append(m.stamp)
            poses.append((x, y, th))
    return TruthTrack(np.array(stamps), np.array(poses), np.zeros(0, np.int64),
                      np.zeros((0, 2)))


def evaluate(run: MrclamRun, settings: EstimatorSettings, *, start: float | None = None,
             end: float | None = None, progress: Progress | None = None) -> Evaluation:
    """Run an :class:`Estimator` with ``settings`` over ``run`` (offline) and score it."""
    est = Estimator(replace(settings, robot=run.robot))
    scorer = Scorer(TruthTrack.from_mrclam(run, start), robot=run.robot,
                    dead_reckoning=dead_reckoning_track(run, start, end))
    done = 0
    for message in run.events(start, end, truth=False):
        done += 1
        if progress is not None and done % 1000 == 0:
            progress(1000)
        assert not isinstance(message, Truth)  # events(truth=False)
        try:
            report = est.apply(message)
        except EstimationError:
            continue  # refused (counted by the estimator): no state for it
        if report is not None:
            scorer.add_innovations(report.innovations, report.innovation_covariances)
        scorer.add(message.stamp, est.pose, est.pose_covariance)
    if progress is not None:
        progress(done % 1000)
    return scorer.finish(est.landmark_ids, est.landmarks, est.diagnostics())


def evaluate_all(runs: Sequence[MrclamRun], settings: EstimatorSettings, *,
                 executor: Executor | None = None,
                 progress: Progress | None = None) -> list[Evaluation]:
    """:func:`evaluate` of every run (in ``runs`` order), on ``executor``'s processes when
    given — the runs are independent, so several cores share a pass; ``progress`` is then
    told each run's events as it finishes."""
    if executor is None:
        return [evaluate(run, settings, progress=progress) for run in runs]
    futures = {executor.submit(evaluate, run, settings): k for k, run in enumerate(runs)}
    out: list[Evaluation | None] = [None] * len(runs)
    for future in as_completed(futures):
        k = futures[future]
        out[k] = future.result()
        if progress is not None:
            progress(event_count(runs[k]))
    return [e for e in out if e is not None]


def event_count(run: MrclamRun, start: float | None = None, end: float | None = None) -> int:
    """Odometry steps and observation batches of :meth:`MrclamRun.events` (for progress)."""
    return sum(1 for _ in run.events(start, end, truth=False))
