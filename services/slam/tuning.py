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
   are integrated with the standard model from the true pose at the window's start, and the
   error at its end is split into along-track and heading. Their variances are modelled
   per window as Σ σv²dt² (docs/estimator.md, ``motion_model = "spec"``, the default) or as
   k_d²·distance and k_t²·turn + k_hd²·distance (the opt-in terms,
   ``motion_model = "distance"``), fitted the same way, each window length weighted equally.
3. **Check and scale.** The estimator runs over every run with the fitted settings and its
   time-averaged pose NEES is measured against the truth. The sensor σ are measured
   against the truth directly, per measurement: they stay as fitted. The odometry errors
   are correlated in time (commanded, not measured, velocities), which a white-noise model
   fitted on windows underestimates, so the motion σ are multiplied by a scale c until the
   pooled mean NEES is within 2 % of 3: ln NEES is close to linear in ln c, so a secant
   on the passes so far (``scaled = "all"`` multiplies every σ instead: then P scales by c²
   and the slope is −2). The last pass is the check: each run's NEES against the band
   (:meth:`TuneResult.passes`).

No I/O besides reading the dataset (through :mod:`slamlens.services.slam.mrclam`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import optimize, stats

from slamlens.common.errors import ConfigError, SourceError
from slamlens.common.geometry import wrap_angle
from slamlens.services.slam.camera_fit import CameraFit, fit_camera, odd_cameras
from slamlens.services.slam.mrclam import MrclamRun
from slamlens.services.slam.scoring import (
    NEES_WINDOW,
    POSE_DOF,
    Evaluation,
    Progress,
    evaluate_all,
)
from slamlens.services.slam.settings import EstimatorSettings

#: window lengths of the odometry residuals, s (up to the longest blind drives of MRCLAM)
WINDOWS_S = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
#: residuals beyond this many σ are left out of a fit (then the fit is repeated)
TRIM_SIGMA = 3.0

# ------------------------------------------------------------------------------ residuals


@dataclass(frozen=True)
class SensorResiduals:
    """Per measurement with truth: the true range and bearing, and z − h; and z against
    every other landmark (a misidentified barcode is explained by another one)."""

    ranges: np.ndarray  #: measured range, m
    bearings: np.ndarray  #: measured bearing, rad
    range_errors: np.ndarray  #: z_r − h_r, m
    bearing_errors: np.ndarray  #: wrap(z_φ − h_φ), rad
    robots: np.ndarray  #: int: the robot number of each measurement
    #: [M, L] z − h against each landmark of the dataset (the named one: inf)
    other_range_errors: np.ndarray
    other_bearing_errors: np.ndarray


def sensor_residuals(runs: Sequence[MrclamRun]) -> SensorResiduals:
    rows: list[tuple[float, ...]] = []
    others_r: list[np.ndarray] = []
    others_b: list[np.ndarray] = []
    for run in runs:
        index = {int(i): k for k, i in enumerate(run.landmark_ids)}
        for t, subject, z_r, z_b in run.measurements:
            pose = run.pose_at(float(t))
            k = index.get(int(subject))
            if pose is None or k is None:
                continue
            d = run.landmarks_world - pose[:2]
            h_r = np.hypot(d[:, 0], d[:, 1])
            e_b = np.asarray(wrap_angle(z_b - (np.arctan2(d[:, 1], d[:, 0]) - pose[2])))
            e_r = z_r - h_r
            rows.append((z_r, z_b, float(e_r[k]), float(e_b[k]), run.robot_number))
            e_r[k] = e_b[k] = math.inf
            others_r.append(e_r)
            others_b.append(e_b)
    a = np.array(rows).reshape(-1, 5)
    width = max((o.size for o in others_r), default=0)
    return SensorResiduals(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4].astype(int),
                           np.array(others_r).reshape(-1, width),
                           np.array(others_b).reshape(-1, width))


def misidentified(sensor: SensorResiduals, values: dict[str, float], *,
                  gate: float = 13.82) -> np.ndarray:
    """Measurements whose named landmark is beyond the χ²₂ ``gate`` with the fitted σ while
    another landmark is inside it: a barcode read as another's (bool [M])."""
    r, phi = sensor.ranges, sensor.bearings
    var_r = (values["sigma_range"] ** 2 + (values["sigma_range_per_m"] * r) ** 2
             + (values["sigma_range_off_axis"] * r * phi ** 2) ** 2)
    var_b = values["sigma_bearing"] ** 2
    named = sensor.range_errors ** 2 / var_r + sensor.bearing_errors ** 2 / var_b
    if not sensor.other_range_errors.size:
        return np.zeros(r.size, bool)
    with np.errstate(invalid="ignore"):
        other = (sensor.other_range_errors ** 2 / var_r[:, None]
                 + sensor.other_bearing_errors ** 2 / var_b).min(axis=1)
    return (named > gate) & (other <= gate)


@dataclass(frozen=True)
class OdometryResiduals:
    """Per window: the noise model's regressors and the error of integrated odometry."""

    window_s: np.ndarray  #: the window's length
    sum_dt2: np.ndarray  #: Σ dt² of its steps (the docs/estimator.md noise scales with it)
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
    #: per robot number: the fraction of its measurements another landmark explains
    #: (a misidentified barcode: :func:`misidentified`); none enter the fit (trimmed)
    misidentified: dict[int, float] = field(default_factory=dict)
    #: per robot number: its camera's systematic errors (docs/estimator.md, the cameras)
    cameras: dict[int, CameraFit] = field(default_factory=dict)


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
    wrong = misidentified(sensor, values)
    return NoiseFit(values=values, sensor_samples=int(r.size),
                    odometry_windows=int(odo.along.size),
                    range_outliers=float(np.mean(np.abs(sensor.range_errors) > 0.5)),
                    bearing_outliers=float(np.mean(np.abs(sensor.bearing_errors) >
                                                   TRIM_SIGMA * sigma_b)),
                    misidentified={int(k): float(np.mean(wrong[sensor.robots == k]))
                                   for k in np.unique(sensor.robots)},
                    cameras=cameras(sensor, ~wrong))


def cameras(sensor: SensorResiduals, keep: np.ndarray) -> dict[int, CameraFit]:
    """Each robot's camera from its measurements in ``keep`` (misread barcodes left out)."""
    out = {}
    for k in np.unique(sensor.robots):
        mine = keep & (sensor.robots == k)
        try:
            out[int(k)] = fit_camera(sensor.bearings[mine], sensor.bearing_errors[mine],
                                     sensor.ranges[mine], sensor.range_errors[mine])
        except SourceError:
            continue  # too few fair sightings to say
    return out


# ---------------------------------------------------------------------------------- tune

NOISE_KEYS = ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing", "sigma_distance",
              "sigma_turn", "sigma_heading_per_distance", "sigma_range_per_m",
              "sigma_range_off_axis")
#: the largest scale tried: a profile needing more is a model that does not fit
MAX_SCALE = 20.0
#: the odometry σ (what the NEES scale multiplies by default)
MOTION_KEYS = ("sigma_v", "sigma_w", "sigma_distance", "sigma_turn",
               "sigma_heading_per_distance")


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
    linearisation: str = "standard"  #: the estimator's (EstimatorSettings.linearisation)
    update_iterations: int = 1  #: the estimator's (EstimatorSettings.update_iterations)
    scaled: str = "motion"  #: which σ the scale multiplies: motion or all

    @property
    def pooled_nees(self) -> float:
        return _pooled_nees(self.after)

    def passes(self, *, max_nees: float = 2 * POSE_DOF, min_windows: float = 0.8) -> bool:
        """The check: each run's time-averaged NEES ≤ ``max_nees`` and at least
        ``min_windows`` of its 100-state windows inside the 95 % band."""
        return all(e.nees_mean <= max_nees and e.window_fraction() >= min_windows
                   for e in self.after)


def _next_scale(history: list[tuple[float, float]]) -> float:
    """The next scale c from the passes so far, (ln c, ln pooled NEES): ln NEES is close to
    linear in ln c — slope −2 when every σ scales (P ∝ c²), flatter when only the motion σ
    do — so a secant through the last two passes, the slope −2 until there are two (or
    while the secant's is not clearly negative)."""
    lc, ln = history[-1]
    slope = -2.0
    if len(history) >= 2:
        lc0, ln0 = history[-2]
        if lc != lc0 and (ln - ln0) / (lc - lc0) < -0.25:
            slope = (ln - ln0) / (lc - lc0)
    return math.exp(lc + (math.log(POSE_DOF) - ln) / slope)


def in_sample_rank(result: TuneResult) -> tuple[bool, float]:
    """Orders fits by their own figures when no robot was left out: passing first, then
    the worst robot's NEES nearest 3 (in ratio)."""
    worst = max((abs(math.log(e.nees_mean / POSE_DOF)) if e.nees_mean > 0 else math.inf)
                for e in result.after)
    return not result.passes(), worst


def _pooled_nees(evaluations: Sequence[Evaluation]) -> float:
    values = np.concatenate([e.nees[np.isfinite(e.nees)] for e in evaluations])
    return float(values.mean()) if values.size else math.nan


def settings_with(base: EstimatorSettings, values: dict[str, float]) -> EstimatorSettings:
    changes: dict[str, Any] = {k: float(v) for k, v in values.items()}
    return replace(base, **changes)


def tune(runs: Sequence[MrclamRun], *, motion_model: str = "spec",
         gate_chi2: float = 13.82, base: EstimatorSettings | None = None,
         max_passes: int = 8, tolerance: float = 0.02, scaled: str = "motion",
         progress: Callable[[int, float], Progress | None] | None = None,
         executor: Executor | None = None) -> TuneResult:
    """Fit, check and scale until consistent (module docstring).

    ``scaled`` says which σ the NEES scale multiplies: ``motion`` (the odometry σ; the
    sensor σ stay as measured against the truth) or ``all``. ``progress(pass_number,
    scale)`` may return a callable that is told how many events each pass has pushed
    through (for a progress bar). With an ``executor`` the runs of a pass are scored on
    its processes.
    """
    if scaled not in ("motion", "all"):
        raise ConfigError(f"scaled {scaled!r}: motion or all")
    base = base or EstimatorSettings()
    fit = fit_noise(runs, motion_model=motion_model)
    scale = 1.0
    before: list[Evaluation] = []
    after: list[Evaluation] = []
    values: dict[str, float] = {}
    history: list[tuple[float, float]] = []
    for number in range(1, max_passes + 1):
        values = {**{k: v * (scale if scaled == "all" or k in MOTION_KEYS else 1.0)
                     for k, v in fit.values.items()}, "innovation_gate_chi2": gate_chi2}
        tick = progress(number, scale) if progress is not None else None
        after = evaluate_all(runs, settings_with(base, values), executor=executor,
                             progress=tick)
        if number == 1:
            before = after
        nees = _pooled_nees(after)
        if not (math.isfinite(nees) and nees > 0):
            break
        if abs(nees / POSE_DOF - 1) <= tolerance or number == max_passes:
            break
        history.append((math.log(scale), math.log(nees)))
        if len(history) >= 2 and nees > 3 * POSE_DOF and \
                history[-1][1] > history[-2][1] + math.log(0.9):
            break  # the scale no longer moves the NEES: noise cannot make this consistent
        new = min(max(_next_scale(history), scale / 10), scale * 10, MAX_SCALE)
        if new == scale:
            break  # at the largest scale tried
        scale = new
    return TuneResult(fit=fit, scale=scale, values=values, before=before, after=after,
                      motion_model=motion_model, passes_run=number, scaled=scaled,
                      linearisation=base.linearisation,
                      update_iterations=base.update_iterations)


#: what each setting of a profile means, physically (written next to its value)
MEANING = {
    "sigma_v": "m/s: error of the commanded speed over one odometry step (along-track "
               "variance σv²·dt² a step, docs/estimator.md)",
    "sigma_w": "rad/s: error of the commanded turn rate over one step (heading variance "
               "σω²·dt² a step)",
    "sigma_range": "m: range noise at any range (the sensor's floor)",
    "sigma_bearing": "rad: bearing noise",
    "sigma_distance": "m/√m: along-track error growing with the distance driven",
    "sigma_turn": "rad/√rad: heading error growing with the angle turned",
    "sigma_heading_per_distance": "rad/√m: heading error growing with the distance driven",
    "sigma_range_per_m": "m/m: range error in proportion to the range (a scale error)",
    "sigma_range_off_axis": "1/rad²: range error growing with range × bearing² (a marker "
                            "ranged by its apparent size off the optical axis)",
    "innovation_gate_chi2": "χ²₂: an observation whose NIS is above this is refused "
                            "(misread barcodes, reflections)",
}


def profile_toml(result: TuneResult, *, header: Sequence[str] = (),
                 notes: Sequence[str] = ()) -> str:
    """The profile as an estimator settings TOML (``--config FILE``), with how it was made
    (``header``, then the fit's figures, then ``notes``: e.g. the cross-validation), each
    setting with what it means."""
    lines = [f"# {h}" if h else "#" for h in header]
    model = ("spec: the standard model's sigma_v, sigma_w" if result.motion_model == "spec" else
             "distance: the opt-in sigma_distance, sigma_turn, sigma_heading_per_distance "
             "(not the standard model)")
    wrong = ", ".join(f"robot{k} {v:.1%}" for k, v in sorted(result.fit.misidentified.items()))
    lines += [
        f"# motion model: {model}; sigma_range_per_m and sigma_range_off_axis are opt-in "
        "range terms (not the standard model)",
        f"# fitted from {result.fit.sensor_samples} measurements and "
        f"{result.fit.odometry_windows} odometry windows; {result.fit.range_outliers:.1%} of "
        "ranges off by > 0.5 m" + (f"; barcodes read as another landmark's: {wrong}"
                                   if wrong else ""),
        f"# NEES scale c = {result.scale:.3f} on "
        + ("the motion σ (the sensor σ as measured)" if result.scaled == "motion"
           else "every σ") + f" (pooled pose NEES before: {_pooled_nees(result.before):.2f},"
        f" after: {result.pooled_nees:.2f})",
    ]
    lines += [f"# {line}" for line in camera_lines(result.fit.cameras)]
    for e in result.after:
        lines.append(f"# {e.robot} (fitted on): pose NEES {e.nees_mean:.2f}, "
                     f"{e.window_fraction():.0%} of {NEES_WINDOW}-state windows in "
                     f"[{e.band[0]:.2f}, {e.band[1]:.2f}], landmark RMSE {e.landmark_rmse:.3f} m "
                     f"({e.landmark_rmse_rigid:.3f} m after a rigid fit)")
    lines += [f"# {n}" if n else "#" for n in notes]
    lines += ["", f'linearisation = "{result.linearisation}"']
    if result.update_iterations > 1:
        lines.append(f"update_iterations = {result.update_iterations}  # the iterated EKF: "
                     "at most this many linearisations of each update (docs/estimator.md)")
    for key in (*NOISE_KEYS, "innovation_gate_chi2"):
        if key in result.values:
            lines.append(f"{key} = {_number(result.values[key])}  # {MEANING[key]}")
    return "\n".join(lines) + "\n"


def camera_lines(fits: dict[int, CameraFit]) -> list[str]:
    """The cameras against the truth, and those the lab should calibrate (one line each)."""
    if not fits:
        return []
    lines = ["cameras against the truth (bearing offset and scale, range scale): "
             + "; ".join(f"robot{k} {c.text()}" for k, c in sorted(fits.items()))]
    for k, what in sorted(odd_cameras(fits).items()):
        lines.append(f"robot{k}'s camera differs from the others' ({', '.join(what)}): "
                     "calibrate it — a profile fitted on other robots cannot hold that "
                     "(docs/estimator.md)")
    return lines


def _number(value: float) -> str:
    text = f"{value:.4g}"
    return text if ("." in text or "e" in text) else text + ".0"
