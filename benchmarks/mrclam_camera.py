"""Each MRCLAM dataset 6 robot's camera against the ground truth, and what calibrating it
does to the filter — the measurements behind docs/consistency.md, "Robot 4's camera".

1. **The camera.** Every sighting of a landmark while there is ground truth, through
   services/slam/camera_fit.py (what ``slamlens tune`` reports): its bearing error
   (measured − true, gross errors left out) regressed on (1, bearing b, turn rate ω) — an
   offset (the camera's yaw on the robot), a bearing scale (its field of view) and a
   latency (a camera reporting a picture δ s old sees the bearing of δ·ω ago) — and the
   range's median measured / true ratio (its scale).
2. ``--evaluate``: the estimator offline, each robot with the OC profile fitted on the
   other four (benchmarks/profiles/oc/without-robotK.toml), on its sightings as recorded;
   with the latency measured on the *other four* taken off every sighting's stamp; and
   with its *own* camera calibrated (range ÷ scale, bearing − offset − scale·b) from the
   truth of its first 120 s, and from its whole run (an oracle: a lab calibrating that
   camera against a reference). Pose NEES and the map's shape (landmark RMSE after a
   rigid fit).

Run: ``.venv/bin/python benchmarks/mrclam_camera.py [--evaluate]`` (≈ 15 s; ``--evaluate``
≈ 1 min on 2 cores).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Observations
from slamlens.services.harness.mrclam_pipeline import DATA, OC_FOLDS, left_out_profile
from slamlens.services.slam.camera_fit import CameraFit, fit_camera
from slamlens.services.slam.mrclam import MrclamRun, load_mrclam
from slamlens.services.slam.scoring import TruthTrack, evaluate

ROBOTS = (1, 2, 3, 4, 5)
RATE_HALF_S = 0.05  #: the truth's turn rate is its heading change over ±this, s
EARLY_S = 120.0  #: the short calibration: the run's first this many seconds
#: a camera with no error: the sightings as recorded
PERFECT = CameraFit(offset=0.0, scale=0.0, range_scale=1.0, sightings=0, latency=0.0)


def sightings(run: MrclamRun, until_s: float = math.inf) -> np.ndarray:
    """Rows (bearing, true turn rate, bearing error, range, true range) of the landmark
    sightings of ``run``'s first ``until_s`` seconds that have ground truth around them."""
    truth = TruthTrack.from_mrclam(run)
    where = dict(zip(truth.landmark_ids.tolist(), truth.landmarks.tolist(), strict=True))
    rows = []
    for m in run.events(0.0, until_s, truth=False):
        if not isinstance(m, Observations):
            continue
        poses = [truth.pose_at(m.stamp + d) for d in (-RATE_HALF_S, 0.0, RATE_HALF_S)]
        if any(p is None for p in poses):
            continue
        before, pose, after = poses
        rate = float(wrap_angle(after[2] - before[2])) / (2 * RATE_HALF_S)
        for lid, r, b in zip(m.ids, m.ranges, m.bearings, strict=True):
            if lid in where:
                dx, dy = where[lid][0] - pose[0], where[lid][1] - pose[1]
                error = float(wrap_angle(b - wrap_angle(math.atan2(dy, dx) - pose[2])))
                rows.append((b, rate, error, r, math.hypot(dx, dy)))
    return np.array(rows).reshape(-1, 5)


def camera_of(rows: np.ndarray) -> CameraFit:
    """:func:`fit_camera` of :func:`sightings` rows, with the latency column."""
    return fit_camera(rows[:, 0], rows[:, 2], rows[:, 3], rows[:, 3] - rows[:, 4],
                      rates=rows[:, 1])


def calibrated(run: MrclamRun, camera: CameraFit) -> MrclamRun:
    """``run`` with ``camera``'s errors taken off its sightings (stamps moved back by its
    latency, ranges ÷ its scale, bearings less offset and scale)."""
    m = run.measurements.copy()
    m[:, 0] -= camera.latency or 0.0
    m[:, 2] /= camera.range_scale
    m[:, 3] = (m[:, 3] - camera.offset) / (1.0 + camera.scale)
    order = np.argsort(m[:, 0], kind="stable")
    return replace(run, measurements=m[order])


def report_cameras(cameras: dict[int, CameraFit]) -> None:
    print("the cameras against the truth: bearing error = offset + scale·b + latency·ω; "
          "range scale = median measured / true")
    for k, c in cameras.items():
        print(f"  robot {k}: {c.sightings:5d} sightings  offset {math.degrees(c.offset):+.2f}°  "
              f"bearing scale {c.scale:+.2%}  latency {(c.latency or 0.0) * 1e3:4.0f} ms  "
              f"range scale {c.range_scale:.4f}")


def score(robot: int, variant: str, camera: CameraFit) -> str:
    """One offline run of ``robot`` with its left-out profile, ``camera`` taken off."""
    run = calibrated(load_mrclam(DATA, robot), camera)
    e = evaluate(run, left_out_profile(robot, OC_FOLDS))
    return (f"  robot {robot}  {variant:<44} NEES {e.nees_mean:5.2f}  "
            f"map {e.landmark_rmse_rigid:.3f} m")


def report_filter(runs: dict[int, MrclamRun], cameras: dict[int, CameraFit]) -> None:
    """Part 2 (two processes)."""
    jobs = []
    for k in cameras:
        others = float(np.mean([c.latency or 0.0 for j, c in cameras.items() if j != k]))
        early = camera_of(sightings(runs[k], EARLY_S))
        jobs += [(k, "as recorded", PERFECT),
                 (k, f"latency of the other four ({others * 1e3:.0f} ms) off",
                  replace(PERFECT, latency=others)),
                 (k, f"own camera from its first {EARLY_S:.0f} s",
                  replace(early, latency=0.0)),
                 (k, "own camera from its whole run (oracle)",
                  replace(cameras[k], latency=0.0))]
    print("the filter, each robot with its left-out profile (map: landmark RMSE after a "
          "rigid fit)")
    with ProcessPoolExecutor(2) as pool:
        for row in pool.map(score, *zip(*jobs, strict=True)):
            print(row, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--evaluate", action="store_true",
                        help="also run the estimator with the cameras calibrated (≈ 1 min)")
    args = parser.parse_args(argv)
    runs = {k: load_mrclam(DATA, k) for k in ROBOTS}
    cameras = {k: camera_of(sightings(run)) for k, run in runs.items()}
    report_cameras(cameras)
    if args.evaluate:
        report_filter(runs, cameras)
    return 0


if __name__ == "__main__":
    sys.exit(main())
