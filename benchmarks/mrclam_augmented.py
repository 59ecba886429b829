"""States the shipped estimator does not have, tried on MRCLAM dataset 6 with a dense
OC-EKF — the experiments behind docs/consistency.md, "Why the NIS is low on real data".

The filter is services/harness/dense_ekf.py's dense textbook EKF with OC (the same models,
OC's Jacobians at FEJ's points, the gate, new landmarks after a batch's updates): with no
extra state it gives the shipped estimator's figures (``--check`` prints both; the tests
hold the two equal on a real run). It can carry, beside robot and map:

* **a range bias per landmark** (``bias``): the range error that persists from one sighting
  of a landmark to the next (docs/consistency.md) as a first-order Gauss-Markov state b_i —
  z_r = |ℓ_i − p| + b_i + white, b_i(t + Δ) = φ b_i(t) + w with φ = exp(−Δ/τ) and
  var w = σ_b²(1 − φ²); new landmarks start with b_i = 0, var σ_b²; the white range variance
  is the profile's times ``white``²;
* **a range scale for the robot's camera** (``scale``): z_r = (1 + ε)|ℓ − p|, ε a constant
  with prior N(0, σ_ε²) — the maps' shape errors follow each camera's median range ratio
  (1.012, 1.010, 0.995, 1.020, 1.002 on robots 1–5);
* **a bearing offset and a bearing scale for the camera** (``offset``, ``bearing scale``):
  z_φ = (1 + s)·φ + δ, constants with priors N(0, σ²) — robot 4's camera has δ = −1.30°
  and s = +3.85 % against the truth, the others' |δ| ≤ 0.14°, |s| ≤ 1.8 %
  (benchmarks/mrclam_camera.py); alone and with the range scale;
* and, without either, the motion σ scaled back (×0.44 ≈ 1/c: the profile's σ before the
  scale that brings the pose NEES to 3).

None is in the global rotation or translation, so OC's null space N is unchanged (their
rows of N are 0) and the published marginal of robot and map would keep every covariance
theorem. Each robot runs with its left-out profile (benchmarks/profiles/oc/without-robotK.toml);
printed: pose NEES, map shape (landmark RMSE after a rigid fit), NIS mean / median and the
share of the monitor's 50-innovation NIS windows outside their band, the final ε, δ, s; and,
for the runs without an extra state, where S comes from (median |ν|, √S and √R).

Run: ``.venv/bin/python benchmarks/mrclam_augmented.py [--check]`` (≈ 1 min on 2 cores;
``--check`` ≈ 2 min).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from slamlens.services.harness.dense_ekf import DenseEkf, Extra
from slamlens.services.harness.mrclam_pipeline import (
    DATA,
    OC_FOLDS,
    left_out_profile,
    nis_windows_out,
)
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.scoring import (
    Evaluation,
    Scorer,
    TruthTrack,
    evaluate,
    similarity_fit,
)

ROBOTS = (1, 2, 3, 4, 5)


def run(robot: int, extra: Extra) -> tuple[Evaluation, str, np.ndarray]:
    """The dense filter over one robot with its left-out profile; (scores, the final
    camera states in words, the applied sightings' (ν_r², ν_φ², S_rr, S_φφ, R_rr, R_φφ))."""
    data = load_mrclam(DATA, robot)
    ekf = DenseEkf(left_out_profile(robot, OC_FOLDS), extra)
    scorer = Scorer(TruthTrack.from_mrclam(data), robot=data.robot)
    for m in data.events(truth=False):
        for nu, S in ekf.apply(m):
            scorer.add_innovations(nu[None], S[None])
        scorer.add(m.stamp, ekf.x[:3].copy(), ekf.P[:3, :3].copy())
    ids, landmarks = ekf.landmarks()
    offset, bscale = ekf.bearing_camera()
    camera = ((f"ε {ekf.scale - 1.0:+.4f}" if extra.scale_sd else "")
              + (f" δ {math.degrees(offset):+.2f}°" if extra.offset_sd else "")
              + (f" s {bscale:+.4f}" if extra.bearing_scale_sd else ""))
    return (scorer.finish(ids, landmarks, {"gated": ekf.gated}), camera.strip(),
            np.array(ekf.parts))


def row(what: str, robot: int, ev: Evaluation, camera: str) -> str:
    below, above = nis_windows_out(ev.nis)
    return (f"{what:<48} robot{robot}  NEES {ev.nees_mean:6.2f}  map {ev.landmark_rmse_rigid:.3f} m"
            f"  NIS {ev.nis_mean:.2f} / {float(np.median(ev.nis)):.2f}"
            f"  windows out {below + above:4.0%} ({below:.0%} below)  {camera}")


def where_s_comes_from(robot: int, parts: np.ndarray) -> str:
    """Median innovation against median S and R, range and bearing, as σ (the NIS is low
    where the innovations are smaller than S; which part of S makes it large)."""
    nu_r, nu_b, s_r, s_b, r_r, r_b = np.sqrt(np.median(parts, axis=0)).tolist()
    return (f"{'':<48} robot{robot}  range: |ν| {nu_r:.3f} m, √S {s_r:.3f}, √R {r_r:.3f};"
            f"  bearing: |ν| {math.degrees(nu_b):.2f}°, √S {math.degrees(s_b):.2f}°,"
            f" √R {math.degrees(r_b):.2f}°  (medians)")


def _job(args: tuple[int, Extra]) -> str:
    robot, extra = args
    ev, camera, parts = run(robot, extra)
    line = row(extra.label(), robot, ev, camera)
    if extra != Extra(motion=extra.motion):
        return line
    rmse, scale = similarity_fit(ev.landmarks, ev.landmarks + ev.landmark_errors)
    return (f"{line}\n{where_s_comes_from(robot, parts)}\n{'':<48} robot{robot}  map after a "
            f"similarity fit: scale {scale:.3f}, RMSE {rmse:.3f} m")


def _shipped(robot: int) -> str:
    return row("the shipped Estimator (reference)", robot,
               evaluate(load_mrclam(DATA, robot), left_out_profile(robot, OC_FOLDS)), "")


EXTRAS = (Extra(), Extra(motion=0.44),
          Extra(bias_sd=0.12, bias_tau=5.0, white=0.35),
          Extra(bias_sd=0.12, bias_tau=20.0, white=0.35),
          Extra(bias_sd=0.08, bias_tau=5.0, white=0.25),
          Extra(scale_sd=0.01), Extra(scale_sd=0.02),
          Extra(offset_sd=0.03), Extra(bearing_scale_sd=0.03),
          Extra(offset_sd=0.03, bearing_scale_sd=0.03, scale_sd=0.02))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="also run the shipped Estimator on each robot (the reference)")
    args = parser.parse_args(argv)
    jobs = [(robot, extra) for extra in EXTRAS for robot in ROBOTS]
    with ProcessPoolExecutor(2) as pool:
        if args.check:
            for line in pool.map(_shipped, ROBOTS):
                print(line, flush=True)
        for line in pool.map(_job, jobs):
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
