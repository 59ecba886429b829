"""The invariant EKF on real data, left out — the measurement behind docs/consistency.md,
"The invariant EKF".

Each MRCLAM dataset 6 robot is run with the dense right-invariant EKF
(services/harness/dense_inekf.py) and the noise of its left-out profile
(benchmarks/profiles/oc/without-robotK.toml, fitted on the other four robots with OC). The
profile's NEES scale was fitted for OC, so it is fitted again for this filter the way
``slamlens tune`` fits it: the motion σ multiplied by m until the pooled pose NEES of the
*other four* robots is within 2 % of 3 (a secant on ln m; at most 6 passes). Then the robot
left out is run with that m: time-averaged pose NEES, the share of 100-state windows in
the band, the map's shape (landmark RMSE after a rigid fit) and its rotation. With
``--simulated``, the paper world's Monte-Carlo (50 seeds, 3 and 15 loops) as well; with
``--large-seeds K``, the large world's (1000 landmarks, 2 loops, 880 s) over K seeds, with
where its mean NEES first stays out of the band for 50 events.

Run: ``.venv/bin/python benchmarks/mrclam_invariant.py [--simulated] [--large-seeds K]``
(≈ 1.5 min on 2 cores, and ≈ 1 min of a core per large-world seed).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from scipy import stats

from slamlens.common.messages import Truth
from slamlens.services.harness.dense_inekf import DenseInvariantEkf
from slamlens.services.harness.mrclam_pipeline import DATA, OC_FOLDS, left_out_profile
from slamlens.services.slam import consistency
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.scoring import POSE_DOF, Scorer, TruthTrack
from slamlens.services.slam.world import load_world

ROBOTS = (1, 2, 3, 4, 5)
TOLERANCE = 0.02  #: the pooled NEES within this share of 3 (tune's)
PASSES = 6
SEEDS = 50
LEAVES = 50  #: events in a row outside the band that count as leaving it


@dataclass(frozen=True)
class Scored:
    nees: np.ndarray  #: the finite pose NEES samples
    nees_mean: float
    windows: float  #: share of 100-state windows in the band
    rmse_rigid: float
    rotation_deg: float


def score_robot(profile_of: int, robot: int, motion: float) -> Scored:
    """``robot``'s run with the left-out profile of ``profile_of``, motion σ × ``motion``."""
    run = load_mrclam(DATA, robot)
    s = left_out_profile(profile_of, OC_FOLDS)
    ekf = DenseInvariantEkf(replace(s, sigma_v=s.sigma_v * motion, sigma_w=s.sigma_w * motion,
                                    robot=run.robot))
    scorer = Scorer(TruthTrack.from_mrclam(run), robot=run.robot)
    for m in run.events(truth=False):
        if isinstance(m, Truth):
            continue
        for nu, S in ekf.apply(m):
            scorer.add_innovations(nu[None], S[None])
        scorer.add(m.stamp, ekf.pose, ekf.pose_covariance)
    ids, landmarks = ekf.landmarks()
    e = scorer.finish(ids, landmarks, {"gated": ekf.gated})
    return Scored(e.nees[np.isfinite(e.nees)], e.nees_mean, e.window_fraction(),
                  e.landmark_rmse_rigid, e.map_rotation_deg)


def fit_motion(robot: int, pool: Executor) -> tuple[float, float, int]:
    """m for the fold leaving ``robot`` out: (m, the four's pooled NEES, passes)."""
    train = [k for k in ROBOTS if k != robot]
    history: list[tuple[float, float]] = []
    m, pooled = 1.0, math.nan
    for number in range(1, PASSES + 1):
        runs = list(pool.map(score_robot, [robot] * len(train), train, [m] * len(train)))
        pooled = float(np.concatenate([r.nees for r in runs]).mean())
        history.append((math.log(m), math.log(pooled)))
        if abs(pooled / POSE_DOF - 1) <= TOLERANCE or number == PASSES:
            return m, pooled, number
        slope = -1.0
        if len(history) >= 2:
            (l0, n0), (l1, n1) = history[-2:]
            if l1 != l0 and (n1 - n0) / (l1 - l0) < -0.25:
                slope = (n1 - n0) / (l1 - l0)
        m = math.exp(history[-1][0] + (math.log(POSE_DOF) - history[-1][1]) / slope)
    return m, pooled, PASSES


def simulated_nees(world_name: str, seed: int, loops: int | None) -> np.ndarray:
    """One seed of a simulated world: the pose NEES after each event (NaN while P_vv is
    singular), scored as the estimator's Monte-Carlo scores it."""
    world = load_world(world_name)
    return consistency.run(world, seed=seed, loops=loops,
                           make=partial(DenseInvariantEkf, capacity=world.n_landmarks)).nees


def report_simulated(pool: Executor, world: str, loops: int | None, seeds: int) -> None:
    runs = list(pool.map(simulated_nees, [world] * seeds, range(seeds), [loops] * seeds))
    length = min(len(r) for r in runs)
    stacked = np.array([r[:length] for r in runs])
    stacked = stacked[:, int(np.argmax(np.isfinite(stacked).any(axis=0))):]  # from the start
    length = stacked.shape[1]
    finite = np.all(np.isfinite(stacked), axis=1)
    mean = stacked.mean(axis=0)
    lo, hi = stats.chi2.ppf([0.025, 0.975], POSE_DOF * seeds) / seeds
    inside = (mean >= lo) & (mean <= hi)
    out = np.convolve(~inside, np.ones(LEAVES), "valid") == LEAVES
    leaves = f"event {int(np.argmax(out))} of {length}" if out.any() else "never"
    fifths = ", ".join(f"{float(np.mean(c)):.3g}" for c in np.array_split(mean, 5))
    print(f"{world} world, {loops or 'its'} loops, {seeds} seeds ({seeds - finite.sum()} "
          f"non-finite): time average {mean.mean():.3g}, {inside.mean():.1%} of events in "
          f"[{lo:.2f}, {hi:.2f}]; per fifth {fifths}; leaves the band ({LEAVES} events) at "
          f"{leaves}; median NEES per seed {np.median(np.median(stacked, axis=1)):.2f}",
          flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--simulated", action="store_true",
                        help="also the paper world's Monte-Carlo (50 seeds, 3 and 15 loops)")
    parser.add_argument("--large-seeds", type=int, default=0, metavar="K",
                        help="also the large world's, 2 loops, over K seeds")
    parser.add_argument("--no-mrclam", action="store_true", help="the simulations only")
    args = parser.parse_args(argv)
    with ProcessPoolExecutor(2) as pool:
        if args.simulated:
            for loops in (3, 15):
                report_simulated(pool, "paper", loops, SEEDS)
        if args.large_seeds:
            report_simulated(pool, "large", 2, args.large_seeds)
        if args.no_mrclam:
            return 0
        print("MRCLAM dataset 6, each robot left out: the invariant EKF with its left-out "
              "profile, the motion σ × m fitted on the other four")
        for robot in ROBOTS:
            m, pooled, passes = fit_motion(robot, pool)
            r = score_robot(robot, robot, m)
            print(f"  robot {robot}: m {m:.3f} (the four's pooled NEES {pooled:.2f}, {passes} "
                  f"passes)  NEES {r.nees_mean:5.2f}  windows in band {r.windows:4.0%}  map "
                  f"{r.rmse_rigid:.3f} m  rotation {r.rotation_deg:+.1f}°", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
