"""What MRCLAM dataset 6's odometry and range errors are, against its ground truth — the
measurements behind docs/consistency.md, "Why the NIS is low on real data".

1. **Odometry.** Over windows of T seconds, the heading change the ground truth shows minus
   the one the commanded turn rates integrate to: its mean per second (a turn-rate bias)
   and its variance per second (constant in T for white noise, growing for correlated);
   and the commanded speed's scale: over windows of 2 s in which the truth turned less than
   0.2 rad, the truth's displacement over the one the commanded (v, ω) integrate to (the
   median ratio); beside it, for comparison, the length of the truth's path over the
   commanded distance in 4 s windows, measured between every 5th, 10th and 25th truth
   sample — a measure the Vicon path's jitter and wiggle make depend on that spacing.
2. **Range.** Every sighting of a landmark against the range the ground truth gives (both
   poses from Vicon): the error's standard deviation, and the part that changes between
   consecutive sightings of one landmark less than a second apart (sd of their difference
   / √2): the rest persists from one sighting to the next; and the correlation of two
   sightings' errors by how far apart in time they are.
3. **A range calibration, left out.** The range error regressed on the sighting's geometry
   on four robots, applied to the fifth: the standard deviation left on the fifth.
4. ``--evaluate``: the estimator (offline, each robot with its left-out OC profile,
   benchmarks/profiles/oc/without-robotK.toml), with each robot's own turn-rate bias
   removed from its odometry (an oracle: it uses the truth), with its commanded speeds
   scaled by the other four robots' median ratio (part 1: the displacement's, and the
   path length's between every 10th sample), with one sighting of each landmark let
   through per 1 s and per 3 s (the rest dropped: the textbook answer to a measurement
   error that persists), with the sensor σ scaled down
   until the mean NIS is near 2, with the iterated update (``update_iterations`` 10), and
   with the left-out range calibration applied (the range σ then the sd it leaves on the
   four, constant): pose NEES, NIS (mean, median, share of the monitor's 50-innovation
   windows outside its band), the map's shape (landmark RMSE after a rigid fit) and its
   size against the truth (the similarity fit's scale).

Run: ``.venv/bin/python benchmarks/mrclam_errors.py [--evaluate]`` (≈ 20 s; ``--evaluate``
≈ 2 min on 2 cores).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from slamlens.common.errors import EstimationError
from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Observations, Odometry
from slamlens.services.harness.mrclam_pipeline import (
    DATA,
    NIS_HI,
    NIS_LO,
    NIS_WINDOW,
    OC_FOLDS,
    left_out_profile,
    nis_windows_out,
)
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import MrclamRun, load_mrclam
from slamlens.services.slam.scoring import Scorer, TruthTrack, similarity_fit

ROBOTS = (1, 2, 3, 4, 5)
WINDOWS_S = (0.25, 1.0, 4.0, 32.0)
GROSS_M = 0.5  #: range errors beyond this are gross (misreads), left out of the statistics
CONSECUTIVE_S = 1.0  #: sightings of one landmark this close are "consecutive"
GAPS_S = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)  #: buckets of time between two sightings, s
#: geometric terms of a range calibration: name → column of (range r, bearing b)
TERMS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "1": lambda r, b: np.ones_like(r), "r": lambda r, b: r, "r²": lambda r, b: r * r,
    "b": lambda r, b: b, "b²": lambda r, b: b * b, "r·b²": lambda r, b: r * b * b}
CALIBRATIONS = {"off-axis (b², r·b²)": ("b²", "r·b²"),
                "full (1, r, r², b, b², r·b²)": ("1", "r", "r²", "b", "b²", "r·b²")}
SENSOR_KEYS = ("sigma_range", "sigma_bearing", "sigma_range_per_m")
#: the sensor σ scaled down until the mean NIS is near 2 (the profile's give 0.6–1.5)
SENSOR_SCALE = 0.35
#: one sighting of a landmark per this many seconds tried (the range error persists ~10 s)
EVERY_S = (1.0, 3.0)
#: the iterated update's budget tried (``update_iterations``, docs/estimator.md)
ITERATIONS = 10
SPEED_WINDOW_S = 2.0  #: windows of the speed-scale measurement
SPEED_MIN_M = 0.1  #: … that count: the commanded displacement at least this
SPEED_MAX_TURN = 0.2  #: … and the truth's heading change at most this, rad
PATH_WINDOW_S = 4.0  #: windows of the path-length comparison
PATH_STEPS = (5, 10, 25)  #: its truth path measured between every k-th sample


def heading_errors(run: MrclamRun, truth: TruthTrack) -> dict[float, np.ndarray]:
    """Per window length T: truth heading change − commanded one, windows half overlapping."""
    odo = [m for m in run.events(truth=False) if isinstance(m, Odometry)]
    stamps = np.array([m.stamp for m in odo])
    turned = np.cumsum([m.w * m.dt for m in odo])  #: through each step's end (its stamp)
    poses = [truth.pose_at(s) for s in stamps]
    step = float(np.median([m.dt for m in odo]))
    out: dict[float, np.ndarray] = {}
    for T in WINDOWS_S:
        n = max(1, round(T / step))
        errs = []
        for i in range(0, len(odo) - n, max(1, n // 2)):
            a, b = poses[i], poses[i + n]
            if a is not None and b is not None:
                errs.append(float(wrap_angle(b[2] - a[2] - (turned[i + n] - turned[i]))))
        out[T] = np.array(errs)
    return out


def speed_ratio(run: MrclamRun) -> float:
    """Median over SPEED_WINDOW_S windows (truth turning < SPEED_MAX_TURN) of the truth's
    displacement over the one the commanded (v, ω) integrate to from the same heading."""
    odo = run.odometry
    t, v, w = odo[:, 0], odo[:, 1], odo[:, 2]
    ratios = []
    for a in np.arange(t[0], t[-1] - SPEED_WINDOW_S, SPEED_WINDOW_S):
        p_a, p_b = run.pose_at(a), run.pose_at(a + SPEED_WINDOW_S)
        if p_a is None or p_b is None or abs(float(wrap_angle(p_b[2] - p_a[2]))) > SPEED_MAX_TURN:
            continue
        i0 = max(int(np.searchsorted(t, a, side="right")) - 1, 0)
        i1 = int(np.searchsorted(t, a + SPEED_WINDOW_S, side="left"))
        dt = np.diff(np.clip(t[i0:i1 + 1], a, a + SPEED_WINDOW_S))
        heading = np.concatenate([[0.0], np.cumsum(w[i0:i0 + dt.size] * dt)])[:-1]
        step = v[i0:i0 + dt.size] * dt
        commanded = math.hypot(float(step @ np.cos(heading)), float(step @ np.sin(heading)))
        if commanded > SPEED_MIN_M:
            ratios.append(math.hypot(p_b[0] - p_a[0], p_b[1] - p_a[1]) / commanded)
    return float(np.median(ratios))


def path_ratio(run: MrclamRun, every: int) -> float:
    """Median over PATH_WINDOW_S windows of the truth's path length (between every
    ``every``-th sample) over the commanded distance Σ v·dt: what the spacing does to it."""
    odo, gt = run.odometry, run.groundtruth
    dt = np.diff(odo[:, 0])
    ratios = []
    for a in np.arange(max(odo[0, 0], gt[0, 0]), min(odo[-1, 0], gt[-1, 0]) - PATH_WINDOW_S,
                       PATH_WINDOW_S):
        steps = (odo[:-1, 0] >= a) & (odo[:-1, 0] < a + PATH_WINDOW_S)
        commanded = float(np.sum(odo[:-1][steps, 1] * dt[steps]))
        path = gt[(gt[:, 0] >= a) & (gt[:, 0] <= a + PATH_WINDOW_S), 1:3][::every]
        if commanded > 0.15 and len(path) > 1:
            ratios.append(float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
                          / commanded)
    return float(np.median(ratios))


def range_errors(run: MrclamRun, truth: TruthTrack) -> np.ndarray:
    """Rows (stamp, landmark id, range, bearing, range − true range) of every sighting of a
    landmark with truth, gross errors left out."""
    where = dict(zip(truth.landmark_ids.tolist(), truth.landmarks.tolist(), strict=True))
    rows = []
    for m in run.events(truth=False):
        pose = truth.pose_at(m.stamp) if isinstance(m, Observations) else None
        if pose is None or not isinstance(m, Observations):
            continue
        for lid, r, b in zip(m.ids, m.ranges, m.bearings, strict=True):
            if lid in where:
                true_r = math.hypot(where[lid][0] - pose[0], where[lid][1] - pose[1])
                rows.append((m.stamp, lid, r, b, r - true_r))
    table = np.array(rows)
    return table[np.abs(table[:, 4]) < GROSS_M]


def changing_sd(table: np.ndarray, errors: np.ndarray) -> float:
    """sd of the error's change between consecutive sightings of one landmark, / √2."""
    diffs = []
    for lid in np.unique(table[:, 1]):
        mine = table[:, 1] == lid
        close = np.diff(table[mine, 0]) < CONSECUTIVE_S
        diffs.append(np.diff(errors[mine])[close])
    return float(np.concatenate(diffs).std() / math.sqrt(2))


def correlation_by_gap(table: np.ndarray) -> list[float]:
    """Correlation of the range errors of two sightings of one landmark, for pairs whose
    time apart falls in each bucket of :data:`GAPS_S` (upper bounds, s)."""
    e = table[:, 4] - table[:, 4].mean()
    products: list[list[float]] = [[] for _ in GAPS_S]
    for lid in np.unique(table[:, 1]):
        stamps, errs = table[table[:, 1] == lid, 0], e[table[:, 1] == lid]
        for i in range(stamps.size):
            gaps = stamps[i + 1:] - stamps[i]
            bucket = np.searchsorted(GAPS_S, gaps)
            for b in range(len(GAPS_S)):
                products[b].extend((errs[i] * errs[i + 1:][bucket == b]).tolist())
    return [float(np.mean(p) / e.var()) if p else math.nan for p in products]


def design(r: np.ndarray, b: np.ndarray, terms: tuple[str, ...]) -> np.ndarray:
    """The calibration's columns for sightings at ranges ``r`` and bearings ``b``."""
    return np.column_stack([TERMS[t](r, b) for t in terms])


def fit_calibration(tables: list[np.ndarray], terms: tuple[str, ...]) -> np.ndarray:
    """Least-squares coefficients of ``terms`` for the range error of ``tables``."""
    both = np.concatenate(tables)
    coef, *_ = np.linalg.lstsq(design(both[:, 2], both[:, 3], terms), both[:, 4], rcond=None)
    return coef


def left_sd(tables: list[np.ndarray], terms: tuple[str, ...], coef: np.ndarray) -> float:
    """The range error's sd on ``tables`` once calibrated: the range σ that goes with it."""
    both = np.concatenate(tables)
    return float((both[:, 4] - design(both[:, 2], both[:, 3], terms) @ coef).std())


def report_errors(runs: dict[int, MrclamRun]) -> dict[int, np.ndarray]:
    """Print parts 1–3; the range tables by robot."""
    tables = {}
    print(f"odometry: truth − commanded heading change over T s (windows {WINDOWS_S} s)")
    for k, run in runs.items():
        truth = TruthTrack.from_mrclam(run)
        errs = heading_errors(run, truth)
        rates = "  ".join(f"{np.var(errs[T]) / T:.4f}" for T in WINDOWS_S)
        bias = float(np.mean(errs[4.0]) / 4.0)
        print(f"  robot {k}: turn-rate bias {bias:+.4f} rad/s; variance per s {rates} rad²/s;"
              f" truth / commanded displacement {speed_ratio(run):.4f} (path length, "
              "truth samples every " + ", ".join(f"{k}th {path_ratio(run, k):.4f}"
                                                 for k in PATH_STEPS) + ")")
        tables[k] = range_errors(run, truth)
    print("range: error against the truth; the part that changes between consecutive "
          f"sightings (< {CONSECUTIVE_S:g} s apart) of one landmark")
    for k, t in tables.items():
        print(f"  robot {k}: {t.shape[0]} sightings, sd {t[:, 4].std():.3f} m, "
              f"changing {changing_sd(t, t[:, 4]):.3f} m, mean {t[:, 4].mean():+.3f} m, "
              f"median measured/true {np.median(t[:, 2] / (t[:, 2] - t[:, 4])):.4f}")
    print(f"range: correlation of two sightings' errors by time apart (≤ {GAPS_S} s)")
    for k, t in tables.items():
        print(f"  robot {k}: " + "  ".join(f"{c:+.2f}" for c in correlation_by_gap(t)))
    for name, terms in CALIBRATIONS.items():
        print(f"range calibration {name}, fitted on the other four robots, sd left:")
        for k, t in tables.items():
            coef = fit_calibration([tables[j] for j in tables if j != k], terms)
            left = t[:, 4] - design(t[:, 2], t[:, 3], terms) @ coef
            print(f"  robot {k}: {t[:, 4].std():.3f} → {left.std():.3f} m "
                  f"(mean {left.mean():+.3f}, changing {changing_sd(t, left):.3f})")
    return tables


def _inputs(run: MrclamRun, turn_bias: float, calibration: tuple[tuple[str, ...], np.ndarray]
            | None, speed: float = 1.0, every_s: float = 0.0) -> Iterator[Odometry | Observations]:
    last: dict[int, float] = {}  #: landmark → stamp of its last sighting let through
    for m in run.events(truth=False):
        if isinstance(m, Odometry):
            yield replace(m, w=m.w + turn_bias, v=m.v * speed)
            continue
        if not isinstance(m, Observations):
            continue  # no truth was asked for
        if every_s:  # one sighting of a landmark per every_s seconds
            keep = [i for i, lid in enumerate(m.ids) if m.stamp - last.get(lid, -math.inf)
                    >= every_s]
            last.update((m.ids[i], m.stamp) for i in keep)
            rows = np.array(keep, dtype=int)
            m = replace(m, ids=np.asarray(m.ids)[rows], ranges=np.asarray(m.ranges)[rows],
                        bearings=np.asarray(m.bearings)[rows])
            if not keep:
                continue
        if calibration is not None:
            terms, coef = calibration
            r, b = np.asarray(m.ranges, float), np.asarray(m.bearings, float)
            yield replace(m, ranges=r - design(r, b, terms) @ coef)
        else:
            yield m


def evaluate(robot: int, variant: str, turn_bias: float,
             calibration: tuple[tuple[str, ...], np.ndarray] | None,
             sigma_range: float | None, sensor_scale: float = 1.0,
             iterations: int = 1, speed: float = 1.0, every_s: float = 0.0) -> str:
    """One offline run of ``robot`` with its left-out profile (with ``sigma_range`` its
    range σ, the range-dependent terms off; every sensor σ × ``sensor_scale``; the
    iterated update with ``iterations``); a table row."""
    run = load_mrclam(DATA, robot)
    settings = left_out_profile(robot, OC_FOLDS)
    if sigma_range is not None:
        settings = replace(settings, sigma_range=sigma_range, sigma_range_per_m=0.0,
                           sigma_range_off_axis=0.0)
    settings = replace(settings, update_iterations=iterations,
                       **{key: getattr(settings, key) * sensor_scale for key in SENSOR_KEYS})
    est = Estimator(replace(settings, robot=run.robot))
    scorer = Scorer(TruthTrack.from_mrclam(run), robot=run.robot)
    for m in _inputs(run, turn_bias, calibration, speed, every_s):
        try:
            rep = est.apply(m)
        except EstimationError:
            continue
        if rep is not None:
            scorer.add_innovations(rep.innovations, rep.innovation_covariances)
        scorer.add(m.stamp, est.pose, est.pose_covariance)
    e = scorer.finish(est.landmark_ids, est.landmarks, est.diagnostics())
    nis = e.nis if e.nis is not None else np.zeros(0)
    outside = sum(nis_windows_out(nis))
    mapped = np.asarray(e.landmarks)
    _, map_scale = similarity_fit(mapped, mapped + e.landmark_errors)
    return (f"  robot {robot}  {variant:<28} NEES {e.nees_mean:6.2f}  NIS mean "
            f"{e.nis_mean:4.2f} median {float(np.median(nis)):4.2f} (1.39)  windows outside "
            f"{outside:4.0%}  map {e.landmark_rmse_rigid:.3f} m (its scale "
            f"{1 / map_scale:.4f})")


def report_filter(runs: dict[int, MrclamRun], tables: dict[int, np.ndarray]) -> None:
    """Print part 4 (two processes)."""
    jobs: list[tuple] = []
    speeds = {k: speed_ratio(run) for k, run in runs.items()}
    paths = {k: path_ratio(run, 10) for k, run in runs.items()}
    for k, run in runs.items():
        bias = float(np.mean(heading_errors(run, TruthTrack.from_mrclam(run))[4.0]) / 4.0)
        speed = float(np.median([s for j, s in speeds.items() if j != k]))
        path = float(np.median([s for j, s in paths.items() if j != k]))
        jobs += [(k, "left-out profile", 0.0, None, None, 1.0, 1),
                 (k, f"speeds × {speed:.3f} (the others')", 0.0, None, None, 1.0, 1, speed),
                 (k, f"speeds × {path:.3f} (path, 10th)", 0.0, None, None, 1.0, 1, path),
                 *((k, f"a landmark once per {t:g} s", 0.0, None, None, 1.0, 1, 1.0, t)
                   for t in EVERY_S),
                 (k, f"sensor σ × {SENSOR_SCALE}", 0.0, None, None, SENSOR_SCALE, 1),
                 (k, "turn-rate bias removed", bias, None, None, 1.0, 1),
                 (k, f"iterated update (K = {ITERATIONS})", 0.0, None, None, 1.0,
                  ITERATIONS)]
        for name, terms in CALIBRATIONS.items():
            others = [tables[j] for j in tables if j != k]
            coef = fit_calibration(others, terms)
            jobs.append((k, "ranges calibrated, " + name.split()[0], 0.0, (terms, coef),
                         left_sd(others, terms, coef), 1.0, 1))
    print(f"the filter, each robot with its left-out profile (NIS windows of "
          f"{NIS_WINDOW}, band [{NIS_LO:.2f}, {NIS_HI:.2f}]; map: "
          "landmark RMSE after a rigid fit)")
    with ProcessPoolExecutor(2) as pool:
        for row in pool.map(_evaluate_job, jobs):
            print(row, flush=True)


def _evaluate_job(job: tuple) -> str:
    """:func:`evaluate` of one job's arguments (the later ones may be left at their default)."""
    return evaluate(*job)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--evaluate", action="store_true",
                        help="also run the estimator with the corrections (≈ 2 min)")
    args = parser.parse_args(argv)
    runs = {k: load_mrclam(DATA, k) for k in ROBOTS}
    tables = report_errors(runs)
    if args.evaluate:
        report_filter(runs, tables)
    return 0


if __name__ == "__main__":
    sys.exit(main())
