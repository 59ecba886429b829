"""Noise profiles fitted to runs with ground truth (``slamlens tune``), and the figures that
say whether a profile fits: pose NEES, landmark and pose RMSE, dead reckoning.

How a profile is made (docs/estimator.md, "Tuning on real data"):

1. **Sensor residuals.** For every measurement, the range and bearing predicted from the
   ground-truth pose (interpolated at its stamp) and the true landmark; e = z − h. The
   range variance is modelled as σr² + (k·r)² + (k_off·r·φ²)² (the last two are the
   opt-in terms of :class:`~slamlens.services.slam.settings.EstimatorSettings`), the bearing
   variance
   as σφ², and fitted by a trimmed Gaussian maximum likelihood (zero mean: a bias is an
   error the filter sees; residuals beyond 3σ are dropped and the fit repeated, then the
   variances corrected for the trimming) — robust to the gross outliers the innovation gate
   is there to refuse.
2. **Odometry residuals.** Windows of 1, 2, 4 … 64 s; in each, the commanded controls
   are integrated with the SPEC §4 model from the true pose at the window's start, and the
   error at its end is split into along-track and heading. Their variances are modelled
   per window as Σ σv²dt² (SPEC §4, ``motion_model = "spec"``, the default) or as
   k_d²·distance and k_t²·turn + k_hd²·distance (the opt-in terms,
   ``motion_model = "distance"``), fitted the same way, each window length weighted equally.
3. **Check and scale.** The estimator runs over every run with the fitted settings and its
   time-averaged pose NEES is measured against the truth. Scaling every σ by c leaves the
   estimate unchanged and scales P by c² (the gain does not change), so NEES/c²: the
   residual fit sets the shape of the noise, and c, from the pooled runs, sets its size:
   c ← c·sqrt(mean NEES / 3) until the pooled mean is within 2 % of 3 (the innovation gate
   refuses other observations at another scale, so a few passes). The last pass is the
   check: each run's NEES against the band (:meth:`TuneResult.passes`).

No I/O besides reading the dataset (through :mod:`slamlens.services.slam.mrclam`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import optimize, stats

from slamlens.common.errors import ConfigError, EstimationError
from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Observations, Odometry, SlamState, Truth
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import MrclamRun
from slamlens.services.slam.settings import EstimatorSettings

#: window lengths of the odometry residuals, s (up to the longest blind drives of MRCLAM)
WINDOWS_S = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
#: residuals beyond this many σ are left out of a fit (then the fit is repeated)
TRIM_SIGMA = 3.0
#: states per NEES window (issue 11's acceptance)
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
        None outside the track."""
        s = self.stamps
        if s.size == 0 or not s[0] <= t <= s[-1]:
            return None
        i = int(np.searchsorted(s, t, side="right"))
        if i >= s.size:
            return self.poses[-1].copy()
        i = max(i, 1)
        a, b = self.poses[i - 1], self.poses[i]
        span = s[i] - s[i - 1]
        f = 0.0 if span <= 0 else (t - s[i - 1]) / span
        return np.array([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]),
                         float(wrap_angle(a[2] + f * float(wrap_angle(b[2] - a[2]))))])


def pose_nees(error: np.ndarray, P: np.ndarray) -> float:
    """eᵀ P⁻¹ e for a pose error (heading wrapped); NaN while P is too ill-conditioned."""
    tr = float(np.trace(P))
    det = float(np.linalg.det(P))
    if not det > 0 or tr ** 3 / det > CONDITION_MAX:
        return math.nan
    return float(error @ np.linalg.solve(P, error))


def rigid_fit(estimated: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMSE (m) of ``estimated`` [n, 2] after the rotation and translation that fit it best
    to ``truth`` (Kabsch), and that rotation in degrees."""
    if estimated.shape[0] < 2:
        return math.nan, math.nan
    me, mt = estimated.mean(0), truth.mean(0)
    U, _, Vt = np.linalg.svd((estimated - me).T @ (truth - mt))
    D = np.diag([1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    fitted = (estimated - me) @ R.T + mt
    return (float(np.sqrt(np.mean(np.sum((fitted - truth) ** 2, axis=1)))),
            math.degrees(math.atan2(R[1, 0], R[0, 0])))


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
        e[2] = float(wrap_angle(e[2]))
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
    """The odometry of ``run.events(start, end)`` integrated alone (SPEC §4 model, from the
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
        try:
            if isinstance(message, Odometry):
                est.predict(v=message.v, w=message.w, dt=message.dt, stamp=message.stamp)
            else:
                assert isinstance(message, Observations)
                report = est.observe(ids=message.ids, ranges=message.ranges,
                                     bearings=message.bearings, stamp=message.stamp)
                scorer.add_innovations(report.innovations, report.innovation_covariances)
        except EstimationError:
            continue  # refused (counted by the estimator): no state for it
        scorer.add(message.stamp, est.pose, est.pose_covariance)
    if progress is not None:
        progress(done % 1000)
    return scorer.finish(est.landmark_ids, est.landmarks, est.diagnostics())


def event_count(run: MrclamRun, start: float | None = None, end: float | None = None) -> int:
    """Odometry steps and observation batches of :meth:`MrclamRun.events` (for progress)."""
    return sum(1 for _ in run.events(start, end, truth=False))


# ------------------------------------------------------------------------------ residuals


@dataclass(frozen=True)
class SensorResiduals:
    """Per measurement with truth: the true range and bearing, and z − h."""

    ranges: np.ndarray  #: measured range, m
    bearings: np.ndarray  #: measured bearing, rad
    range_errors: np.ndarray  #: z_r − h_r, m
    bearing_errors: np.ndarray  #: wrap(z_φ − h_φ), rad


def sensor_residuals(runs: Sequence[MrclamRun]) -> SensorResiduals:
    rows: list[tuple[float, float, float, float]] = []
    for run in runs:
        index = {int(i): k for k, i in enumerate(run.landmark_ids)}
        for t, subject, z_r, z_b in run.measurements:
            pose = run.pose_at(float(t))
            k = index.get(int(subject))
            if pose is None or k is None:
                continue
            dx, dy = run.landmarks_world[k] - pose[:2]
            h_r = math.hypot(dx, dy)
            h_b = math.atan2(dy, dx) - pose[2]
            rows.append((z_r, z_b, z_r - h_r, float(wrap_angle(z_b - h_b))))
    a = np.array(rows).reshape(-1, 4)
    return SensorResiduals(a[:, 0], a[:, 1], a[:, 2], a[:, 3])


@dataclass(frozen=True)
class OdometryResiduals:
    """Per window: the noise model's regressors and the error of integrated odometry."""

    window_s: np.ndarray  #: the window's length
    sum_dt2: np.ndarray  #: Σ dt² of its steps (the SPEC §4 noise scales with it)
    distance: np.ndarray  #: Σ |v·dt|, m
    turn: np.ndarray  #: Σ |ω·dt|, rad
    along: np.ndarray  #: truth − odometry along the start heading, m
    cross: np.ndarray  #: truth − odometry across it, m
    heading: np.ndarray  #: wrap(truth − odometry), rad


def odometry_residuals(runs: Sequence[MrclamRun],
                       windows_s: Sequence[float] = WINDOWS_S) -> OdometryResiduals:
    rows: list[tuple[float, ...]] = []
    for run in runs:
        odo = np.asarray(run.odometry)
        t, v, w = odo[:, 0], odo[:, 1], odo[:, 2]
        for tau in windows_s:
            for t_a in np.arange(t[0], t[-1] - tau, tau):
                t_b = t_a + tau
                p_a, p_b = run.pose_at(t_a), run.pose_at(t_b)
                if p_a is None or p_b is None:
                    continue
                i0 = max(int(np.searchsorted(t, t_a, side="right")) - 1, 0)
                i1 = int(np.searchsorted(t, t_b, side="left"))
                lo = np.clip(t[i0:i1], t_a, t_b)
                hi = np.clip(t[i0 + 1:i1 + 1], t_a, t_b)
                dt = hi - lo
                vs, ws = v[i0:i1][:dt.size], w[i0:i1][:dt.size]
                x, y, th = float(p_a[0]), float(p_a[1]), float(p_a[2])
                for vk, wk, hk in zip(vs.tolist(), ws.tolist(), dt.tolist(), strict=True):
                    x += vk * hk * math.cos(th)
                    y += vk * hk * math.sin(th)
                    th += wk * hk
                c, s = math.cos(p_a[2]), math.sin(p_a[2])
                ex, ey = p_b[0] - x, p_b[1] - y
                rows.append((tau, float(np.sum(dt * dt)), float(np.sum(np.abs(vs * dt))),
                             float(np.sum(np.abs(ws * dt))), c * ex + s * ey, -s * ex + c * ey,
                             float(wrap_angle(p_b[2] - th))))
    a = np.array(rows).reshape(-1, 7)
    return OdometryResiduals(*(a[:, i] for i in range(7)))


def _trim_correction(k: float = TRIM_SIGMA) -> float:
    """E[e² | |e| ≤ kσ] / σ² for a Gaussian: what trimming at kσ takes off a variance."""
    inside = 2 * stats.norm.cdf(k) - 1
    return float(1 - 2 * k * stats.norm.pdf(k) / inside)


def fit_variance(errors: np.ndarray, regressors: np.ndarray, *,
                 weights: np.ndarray | None = None, iterations: int = 10) -> np.ndarray:
    """Non-negative coefficients a of var_i = Σ_j a_j·X_ij for zero-mean errors: a trimmed
    Gaussian maximum likelihood (residuals beyond TRIM_SIGMA·σ_i left out, refitted until
    the set stays the same, then corrected for the trimming)."""
    X = np.asarray(regressors, dtype=float).reshape(errors.size, -1)
    w = np.ones(errors.size) if weights is None else np.asarray(weights, dtype=float)
    e2 = np.asarray(errors, dtype=float) ** 2
    keep = X.sum(axis=1) > 0  # a sample no term can explain (standing still) says nothing
    m = X.shape[1]
    start = np.full(m, math.log(max(float(np.mean(e2)) / max(float(np.mean(X.sum(1))), 1e-300),
                                    1e-300)))
    a = np.exp(start)
    for _ in range(iterations):
        Xk, e2k, wk = X[keep], e2[keep], w[keep]
        if m == 1:  # var = a·x: the likelihood's maximum in closed form
            a = np.array([float(np.sum(wk * e2k / Xk[:, 0]) / np.sum(wk))])
        else:
            def nll(log_a: np.ndarray, Xk: np.ndarray = Xk, e2k: np.ndarray = e2k,
                    wk: np.ndarray = wk) -> float:
                var = Xk @ np.exp(log_a) + 1e-300
                return float(np.sum(wk * (np.log(var) + e2k / var)))

            res = optimize.minimize(nll, np.log(np.maximum(a, 1e-300)), method="Nelder-Mead",
                                    options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 4000})
            a = np.exp(res.x)
        sigma = np.sqrt(X @ a + 1e-300)
        new_keep = (e2 <= (TRIM_SIGMA * sigma) ** 2) & (X.sum(axis=1) > 0)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    a = a / _trim_correction()
    a[a < 1e-12 * max(float(a.max()), 1e-300)] = 0.0  # a term the data does not support
    return a


@dataclass(frozen=True)
class NoiseFit:
    """The σ fitted from the residuals (before the NEES scale)."""

    values: dict[str, float]  #: EstimatorSettings keys → σ
    sensor_samples: int
    odometry_windows: int
    range_outliers: float  #: fraction of |range error| > 0.5 m
    bearing_outliers: float  #: fraction beyond 3 fitted σ


def fit_noise(runs: Sequence[MrclamRun], *, motion_model: str = "spec",
              range_terms: bool = True,
              windows_s: Sequence[float] = WINDOWS_S) -> NoiseFit:
    """Step 1 and 2 of the module docstring."""
    sensor = sensor_residuals(runs)
    r, phi = sensor.ranges, sensor.bearings
    if range_terms:
        X = np.column_stack([np.ones_like(r), r ** 2, (r * phi ** 2) ** 2])
        a_r = fit_variance(sensor.range_errors, X)
    else:
        a_r = np.r_[fit_variance(sensor.range_errors, np.ones((r.size, 1))), 0.0, 0.0]
    a_b = fit_variance(sensor.bearing_errors, np.ones((r.size, 1)))
    odo = odometry_residuals(runs, windows_s)
    # each window length counts the same, whatever its number of windows
    counts = {tau: int(np.sum(odo.window_s == tau)) for tau in np.unique(odo.window_s)}
    weights = np.array([1.0 / counts[tau] for tau in odo.window_s]) * odo.window_s.size
    values: dict[str, float] = {
        "sigma_range": math.sqrt(a_r[0]), "sigma_range_per_m": math.sqrt(a_r[1]),
        "sigma_range_off_axis": math.sqrt(a_r[2]), "sigma_bearing": math.sqrt(a_b[0])}
    if motion_model == "spec":
        a_v = fit_variance(odo.along, odo.sum_dt2, weights=weights)
        a_w = fit_variance(odo.heading, odo.sum_dt2, weights=weights)
        values.update(sigma_v=math.sqrt(a_v[0]), sigma_w=math.sqrt(a_w[0]),
                      sigma_distance=0.0, sigma_turn=0.0, sigma_heading_per_distance=0.0)
    elif motion_model == "distance":
        a_d = fit_variance(odo.along, odo.distance, weights=weights)
        a_h = fit_variance(odo.heading, np.column_stack([odo.turn, odo.distance]),
                           weights=weights)
        values.update(sigma_v=0.0, sigma_w=0.0, sigma_distance=math.sqrt(a_d[0]),
                      sigma_turn=math.sqrt(a_h[0]), sigma_heading_per_distance=math.sqrt(a_h[1]))
    else:
        raise ConfigError(f"motion model {motion_model!r}: spec or distance")
    sigma_b = values["sigma_bearing"]
    return NoiseFit(values=values, sensor_samples=int(r.size),
                    odometry_windows=int(odo.along.size),
                    range_outliers=float(np.mean(np.abs(sensor.range_errors) > 0.5)),
                    bearing_outliers=float(np.mean(np.abs(sensor.bearing_errors) >
                                                   TRIM_SIGMA * sigma_b)))


# ---------------------------------------------------------------------------------- tune

NOISE_KEYS = ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing", "sigma_distance",
              "sigma_turn", "sigma_heading_per_distance", "sigma_range_per_m",
              "sigma_range_off_axis")


@dataclass
class TuneResult:
    """A profile and the figures behind it."""

    fit: NoiseFit
    scale: float  #: c: every fitted σ was multiplied by it
    values: dict[str, float]  #: the profile's settings (σ after scaling, and the gate)
    before: list[Evaluation]  #: the fitted profile, unscaled
    after: list[Evaluation]  #: the profile
    motion_model: str
    passes_run: int = 0  #: estimator passes over the runs

    @property
    def pooled_nees(self) -> float:
        return _pooled_nees(self.after)

    def passes(self, *, max_nees: float = 2 * POSE_DOF, min_windows: float = 0.8) -> bool:
        """The check: each run's time-averaged NEES ≤ ``max_nees`` and at least
        ``min_windows`` of its 100-state windows inside the 95 % band."""
        return all(e.nees_mean <= max_nees and e.window_fraction() >= min_windows
                   for e in self.after)


def _pooled_nees(evaluations: Sequence[Evaluation]) -> float:
    values = np.concatenate([e.nees[np.isfinite(e.nees)] for e in evaluations])
    return float(values.mean()) if values.size else math.nan


def settings_with(base: EstimatorSettings, values: dict[str, float]) -> EstimatorSettings:
    changes: dict[str, Any] = {k: float(v) for k, v in values.items()}
    return replace(base, **changes)


def tune(runs: Sequence[MrclamRun], *, motion_model: str = "spec",
         gate_chi2: float = 13.82, base: EstimatorSettings | None = None,
         max_passes: int = 6, tolerance: float = 0.02,
         progress: Callable[[int, float], Progress | None] | None = None) -> TuneResult:
    """Fit, check and scale until consistent (module docstring).

    ``progress(pass_number, scale)`` may return a callable that is told how many events
    each pass has pushed through (for a progress bar).
    """
    base = base or EstimatorSettings()
    fit = fit_noise(runs, motion_model=motion_model)
    scale = 1.0
    before: list[Evaluation] = []
    after: list[Evaluation] = []
    values: dict[str, float] = {}
    for number in range(1, max_passes + 1):
        values = {**{k: v * scale for k, v in fit.values.items()},
                  "innovation_gate_chi2": gate_chi2}
        tick = progress(number, scale) if progress is not None else None
        after = [evaluate(run, settings_with(base, values), progress=tick) for run in runs]
        if number == 1:
            before = after
        nees = _pooled_nees(after)
        if not (math.isfinite(nees) and nees > 0):
            break
        if abs(nees / POSE_DOF - 1) <= tolerance or number == max_passes:
            break
        scale *= math.sqrt(nees / POSE_DOF)
    return TuneResult(fit=fit, scale=scale, values=values, before=before, after=after,
                      motion_model=motion_model, passes_run=number)


def profile_toml(result: TuneResult, *, header: Sequence[str] = ()) -> str:
    """The profile as an estimator settings TOML (``--config FILE``), with how it was made."""
    lines = [f"# {h}" if h else "#" for h in header]
    model = ("spec: SPEC §4's sigma_v, sigma_w" if result.motion_model == "spec" else
             "distance: the opt-in sigma_distance, sigma_turn, sigma_heading_per_distance "
             "(not SPEC §4)")
    lines += [
        f"# motion model: {model}; sigma_range_per_m and sigma_range_off_axis are opt-in "
        "range terms (not SPEC §4)",
        f"# fitted from {result.fit.sensor_samples} measurements and "
        f"{result.fit.odometry_windows} odometry windows; {result.fit.range_outliers:.1%} of "
        "ranges off by > 0.5 m",
        f"# NEES scale c = {result.scale:.3f} (pooled pose NEES before: "
        f"{_pooled_nees(result.before):.2f}, after: {result.pooled_nees:.2f})",
    ]
    for e in result.after:
        lines.append(f"# {e.robot}: pose NEES {e.nees_mean:.2f}, "
                     f"{e.window_fraction():.0%} of {NEES_WINDOW}-state windows in "
                     f"[{e.band[0]:.2f}, {e.band[1]:.2f}], landmark RMSE {e.landmark_rmse:.3f} m "
                     f"({e.landmark_rmse_rigid:.3f} m after a rigid fit)")
    lines.append("")
    for key in (*NOISE_KEYS, "innovation_gate_chi2"):
        if key in result.values:
            lines.append(f"{key} = {_number(result.values[key])}")
    return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    text = f"{value:.4g}"
    return text if ("." in text or "e" in text) else text + ".0"
