"""Where robot 3's better map under the previous profile comes from — the measurement behind
docs/consistency.md, "Against the targets".

The previous profile (benchmarks/profiles/mrclam6_before.toml: standard EKF, fitted on
robots 1 and 3) draws robot 3's map at 0.053 m after a rigid fit; the shipped invariant EKF
with the profile fitted on the other four robots at 0.066 m. Each MRCLAM dataset 6 robot is
run offline (an Estimator fed the dataset, the same figures as the processes give) with:

1. ``before``           — the previous profile, as shipped before (standard EKF);
2. ``before, invariant`` — the same noise with the invariant EKF: the linearisation's part;
3. ``left out``          — the profile fitted on the other four robots (the shipped tune's
   folds, benchmarks/profiles/without-robotK.toml);
4. ``left out, off-axis 0.559`` — that profile with the previous profile's off-axis range
   term (range σ growing with range × bearing²), the term robot 3's map answers to most.

Each row: time-averaged pose NEES with its standard error over the run (batch means: the
run cut into 10 equal stretches, the sd of their means / √10 — the NEES along one run is
autocorrelated, so the samples' own spread would understate it), landmark RMSE after a
rigid fit, mean NIS.

Run: ``.venv/bin/python benchmarks/mrclam_off_axis.py [--robots 1,2,3,4,5] [--jobs 2]``
(≈ 20 runs of 25 s of a core).
"""

from __future__ import annotations

import argparse
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from slamlens.common.config import load_settings
from slamlens.services.harness.mrclam_pipeline import DATA, REPO, left_out_profile
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.scoring import Evaluation, evaluate
from slamlens.services.slam.settings import EstimatorSettings

BEFORE = REPO / "benchmarks" / "profiles" / "mrclam6_before.toml"
BATCHES = 10
VARIANTS = ("before", "before, invariant", "left out", "left out, off-axis 0.559")


def settings_of(robot: int, variant: str) -> EstimatorSettings:
    before = load_settings(EstimatorSettings, BEFORE)
    left_out = left_out_profile(robot)
    return {"before": before,
            "before, invariant": replace(before, linearisation="invariant"),
            "left out": left_out,
            "left out, off-axis 0.559": replace(
                left_out, sigma_range_off_axis=before.sigma_range_off_axis)}[variant]


def nees_standard_error(e: Evaluation) -> float:
    """Batch-means standard error of the time-averaged pose NEES (module docstring)."""
    x = e.nees[np.isfinite(e.nees)]
    means = x[:x.size // BATCHES * BATCHES].reshape(BATCHES, -1).mean(axis=1)
    return float(means.std(ddof=1) / math.sqrt(BATCHES))


def run_one(job: tuple[int, str]) -> tuple[int, str, float, dict[str, float]]:
    robot, variant = job
    settings = settings_of(robot, variant)
    e = evaluate(load_mrclam(DATA, robot, robot_name=f"robot{robot}"), settings)
    return robot, variant, settings.sigma_range_off_axis, {**e.summary(),
                                                          "nees_se": nees_standard_error(e)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    jobs = [(int(r), v) for r in args.robots.split(",") for v in VARIANTS]
    print(f"{'robot':>5} {'profile':<26} {'off-axis':>8} {'NEES':>7} {'± SE':>6} {'rigid m':>8} "
          f"{'NIS':>6}")
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        for robot, variant, off_axis, s in pool.map(run_one, jobs):
            print(f"{robot:>5} {variant:<26} {off_axis:>8.3f} {s['nees_mean']:>7.2f} "
                  f"{s['nees_se']:>6.2f} {s['landmark_rmse_rigid_m']:>8.3f} "
                  f"{s['nis_mean']:>6.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
