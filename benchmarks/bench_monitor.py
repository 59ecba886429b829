"""Monitor.check per state at n = 15, 50, 100 landmarks, without and with truth.

States come from the real estimator (docs/estimator.md models) on a ring of n landmarks: all are
initialised from the start pose, then the robot alternates predict and an update of 5
landmarks, so half the states are predicts (map block untouched: the fast path) and half
are updates (every pair compared). Target: median ≤ 2 ms per state at n = 100 (a monitor
keeping up with 100 Hz states). A naive baseline is measured in the same run on the same
update states: the pair check as a per-pair loop of P_d (slamlens.common.geometry) and
numpy.linalg.eigvalsh of the difference; the ratio is naive / ours for that check. The
machine is shared: run it a few times, quote medians; set OPENBLAS_NUM_THREADS=1 (as the
monitor service should run) or see the latency of a multi-threaded Cholesky under load.

    .venv/bin/python benchmarks/bench_monitor.py [--states 200] [--quick] [--unobservable]
    .venv/bin/python benchmarks/bench_monitor.py --invariant   # invariant EKF vs OC states
    .venv/bin/python benchmarks/bench_monitor.py --nis-band    # measured vs textbook NIS band
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.geometry import relative_covariance  # noqa: E402
from slamlens.common.messages import SlamState, Truth  # noqa: E402
from slamlens.services.monitor import checks  # noqa: E402
from slamlens.services.monitor.monitor import Monitor  # noqa: E402
from slamlens.services.monitor.settings import MonitorSettings  # noqa: E402
from slamlens.services.monitor.stats import WindowTest  # noqa: E402
from slamlens.services.slam.estimator import Estimator  # noqa: E402
from slamlens.services.slam.settings import EstimatorSettings  # noqa: E402


def make_run(n: int, count: int, seed: int = 0, *,
             settings: EstimatorSettings | None = None) -> tuple[list[SlamState], list[Truth]]:
    """The init state and ``count`` + 1 more of the estimator among n landmarks on a ring."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(-0.45 * math.pi, 0.45 * math.pi, n)
    radii = rng.uniform(2.0, 4.0, n)
    ids = np.arange(1, n + 1)
    xy = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    est = Estimator(settings or EstimatorSettings(max_batch=0))
    pose = np.zeros(3)

    def measure(which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = xy[which] - pose[:2]
        r = np.hypot(d[:, 0], d[:, 1]) + rng.normal(0, 0.05, which.size)
        b = np.arctan2(d[:, 1], d[:, 0]) - pose[2] + rng.normal(0, 0.02, which.size)
        return r, (b + math.pi) % (2 * math.pi) - math.pi

    # the init state first: a monitor that did not see a landmark appear cannot place
    # FEJ's (and OC's) linearisation points, and would skip their unobservable check
    states: list[SlamState] = [est.to_state(seq=0, stamp=0.0, step="init")]
    r, b = measure(np.arange(n))
    est.observe(ids=ids, ranges=r, bearings=b, stamp=0.0)
    states.append(est.to_state(seq=1, stamp=0.0, step="update"))
    truths: list[Truth] = []
    dt, v, w = 0.1, 0.1, 0.05
    for k in range(1, count // 2 + 1):
        t = k * dt
        pose = pose + [v * dt * math.cos(pose[2]), v * dt * math.sin(pose[2]), w * dt]
        est.predict(v=v + rng.normal(0, 0.05), w=w + rng.normal(0, 0.05), dt=dt, stamp=t)
        states.append(est.to_state(seq=len(states), stamp=t, step="predict"))
        which = rng.choice(n, size=5, replace=False)
        r, b = measure(which)
        rep = est.observe(ids=ids[which], ranges=r, bearings=b, stamp=t)
        states.append(est.to_state(seq=len(states), stamp=t, step="update", report=rep))
        truths.append(Truth(robot="robot1", stamp=t, pose=pose, landmark_ids=ids,
                            landmarks=xy))
    return states, truths


def time_monitor(states: list[SlamState], truths: list[Truth] | None,
                 settings: MonitorSettings | None = None, *,
                 clock: Callable[[], int] = time.perf_counter_ns) -> list[float]:
    """Microseconds of check() (and add_truth() of the state's truth) per state."""
    monitor = Monitor(settings or MonitorSettings())
    by_stamp = {} if truths is None else {t.stamp: t for t in truths}
    out = []
    for s in states:
        t0 = clock()
        truth = by_stamp.pop(s.stamp, None)
        if truth is not None:
            monitor.add_truth(truth)
        health = monitor.check(s)
        out.append((clock() - t0) / 1e3)
        assert health.ok, health.violations  # the benchmark run must be a correct run
    return out[1:]  # the first state has nothing to compare with


def naive_pairs(prev: SlamState, cur: SlamState) -> int:
    """Per-pair loop: P_d of both states, eigvalsh of the difference."""
    grown = 0
    n = prev.n
    for i in range(n):
        for j in range(i + 1, n):
            D = relative_covariance(prev.covariance, i, j) - relative_covariance(
                cur.covariance, i, j)
            grown += np.linalg.eigvalsh(D)[0] < -1e-12
    return grown


def ours_pairs(prev: SlamState, cur: SlamState) -> int:
    pos_p, pos_c = checks.common_landmarks(prev.landmark_ids, cur.landmark_ids)
    return checks.pair_growth(checks.map_block(prev.covariance, pos_p),
                              checks.map_block(cur.covariance, pos_c),
                              rtol=1e-9, atol=1e-12).count


def timed(fn, *args) -> float:  # type: ignore[no-untyped-def]
    t0 = time.perf_counter_ns()
    fn(*args)
    return (time.perf_counter_ns() - t0) / 1e3


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


def alternated_times(variants: dict[str, tuple[list[SlamState], MonitorSettings]],
                     rounds: int) -> dict[str, list[float]]:
    """µs of ``check`` per state for each variant (its states, the monitor's settings),
    whole runs alternated ``rounds`` times, in CPU time of the checking thread (so that
    other work on the machine counts less)."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, (states, settings) in variants.items():
            times[name] += time_monitor(states, None, settings, clock=time.thread_time_ns)
    return times


def alternated(variants: dict[str, tuple[list[SlamState], MonitorSettings]],
               rounds: int) -> dict[str, float]:
    """The median of :func:`alternated_times` for each variant."""
    return {name: statistics.median(t)
            for name, t in alternated_times(variants, rounds).items()}


def unobservable_cost(sizes: tuple[int, ...], rounds: int) -> None:
    """What the unobservable-directions check adds to ``check`` (docs/monitor.md): the
    same FEJ states checked with it off and on (auto: FEJ says so, so it is a theorem),
    whole runs alternated ``rounds`` times; medians of the per-state times over all."""
    print("unobservable-directions check: check() per state, off against on (FEJ states; "
          "CPU time of the checking thread, so that other work on the machine counts less)")
    for n in sizes:
        count = 200 if n <= 100 else 12
        states, _ = make_run(n, count, settings=EstimatorSettings(max_batch=0,
                                                                  linearisation="fej"))
        med = alternated({mode: (states, MonitorSettings(check_unobservable=mode))
                          for mode in ("off", "auto")}, rounds)
        off, on = med["off"], med["auto"]
        print(f"  n = {n:>4}: off {off:>10.0f} µs, on {on:>10.0f} µs, added {on - off:>8.0f} µs "
              f"({100 * (on - off) / off:+.1f} %)", flush=True)


def invariant_cost(sizes: tuple[int, ...], rounds: int) -> None:
    """What checking the invariant EKF's states costs against OC's (docs/monitor.md, "The
    invariant EKF's growth theorems are in its own error"): each update compared in ξ,
    T⁻¹ P T⁻ᵀ of both states, with no help from the burst screen. The same run made by
    each filter, both with the unobservable check on (auto), whole runs alternated."""
    print("the invariant EKF's states against OC's: check() per state (CPU time of the "
          "checking thread)")
    for n in sizes:
        count = 200 if n <= 100 else 12
        med = alternated({lin: (make_run(n, count, settings=EstimatorSettings(
            max_batch=0, linearisation=lin))[0], MonitorSettings())
            for lin in ("oc", "invariant")}, rounds)
        oc, inv = med["oc"], med["invariant"]
        print(f"  n = {n:>4}: oc {oc:>10.0f} µs, invariant {inv:>10.0f} µs "
              f"(ratio {inv / oc:.2f})", flush=True)


def nis_band_cost(rounds: int) -> None:
    """What the NIS band that measures the innovations' dependence costs against the
    textbook band (docs/monitor.md, "Statistical tests"): the window test alone on 100 000
    χ²(2) samples, and ``check`` per state on the same run (n = 15) with either band, whole
    runs alternated; the mean per state too (a window completes every 20th state here, so
    the median state pays nothing)."""
    x = np.random.default_rng(1).chisquare(2, size=100_000)
    per: dict[str, list[float]] = {"white": [], "measured": []}
    for _ in range(rounds):
        for band in per:
            test = WindowTest(dof=2, window=50, alpha=1e-6, band=band, measure_after=200)
            t0 = time.perf_counter_ns()
            test.add(x)
            per[band].append((time.perf_counter_ns() - t0) / 1e3 / (x.size / 50))
    white, measured = (statistics.median(per[b]) for b in ("white", "measured"))
    print(f"NIS window test, per window of 50: textbook {white:.0f} µs, measured {measured:.0f} "
          f"µs (ratio {measured / white:.1f}; {(measured - white) / 50:.2f} µs more per "
          f"innovation)")
    states, _ = make_run(15, 400)
    times = alternated_times({band: (states, MonitorSettings(nis_dependence=band))
                              for band in ("white", "measured")}, rounds)
    for band, t in times.items():
        print(f"  check() at n = 15, {band:>8} band: median {statistics.median(t):.0f} µs, "
              f"mean {statistics.fmean(t):.0f} µs per state", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, default=200, help="states per size")
    parser.add_argument("--quick", action="store_true", help="fewer states, n = 15, 100")
    parser.add_argument("--unobservable", action="store_true",
                        help="only the cost of the unobservable-directions check "
                             "(n = 15, 100, 1000)")
    parser.add_argument("--invariant", action="store_true",
                        help="only the cost of checking the invariant EKF's states against "
                             "OC's (n = 15, 100, 1000)")
    parser.add_argument("--nis-band", action="store_true",
                        help="only the cost of the measured NIS band against the textbook one")
    args = parser.parse_args()
    if args.nis_band:
        nis_band_cost(rounds=2 if args.quick else 5)
        return
    if args.invariant:
        invariant_cost((15, 100) if args.quick else (15, 100, 1000),
                       rounds=2 if args.quick else 5)
        return
    if args.unobservable:
        unobservable_cost((15, 100) if args.quick else (15, 100, 1000),
                          rounds=2 if args.quick else 5)
        return
    sizes = (15, 100) if args.quick else (15, 50, 100)
    count = 40 if args.quick else args.states
    threads = os.environ.get("OPENBLAS_NUM_THREADS", "unset")
    print(f"OPENBLAS_NUM_THREADS={threads} (the PSD test is a LAPACK Cholesky: on a loaded "
          f"2-core machine multi-threaded OpenBLAS costs ~10× in latency; run the monitor "
          f"with 1)")
    print(f"{'n':>4} {'no truth µs':>20} {'with truth µs':>20} {'pairs ours µs':>14} "
          f"{'pairs naive µs':>15} {'naive/ours':>10}")
    print(f"{'':>4} {'median':>9} {'p95':>10} {'median':>9} {'p95':>10}")
    for n in sizes:
        states, truths = make_run(n, count)
        plain = time_monitor(states, None)
        truth = time_monitor(states, truths)
        updates = [(states[k - 1], states[k]) for k in range(2, len(states))
                   if states[k].step == "update"]
        ours = [timed(ours_pairs, a, b) for a, b in updates]
        sample = updates[: max(3, min(len(updates), 3000 // n))]
        naive = [timed(naive_pairs, a, b) for a, b in sample]
        assert all(naive_pairs(a, b) == ours_pairs(a, b) for a, b in sample[:2])
        ratio = statistics.median(naive) / statistics.median(ours)
        print(f"{n:>4} {statistics.median(plain):>9.0f} {pct(plain, 95):>10.0f} "
              f"{statistics.median(truth):>9.0f} {pct(truth, 95):>10.0f} "
              f"{statistics.median(ours):>14.0f} {statistics.median(naive):>15.0f} "
              f"{ratio:>9.0f}×")
    print("target: median ≤ 2000 µs per state at n = 100 (100 Hz states)")


if __name__ == "__main__":
    main()
