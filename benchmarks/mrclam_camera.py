"""Each MRCLAM dataset 6 robot's camera against the ground truth, and what calibrating it
does to the filter — the measurements behind docs/consistency.md, "Robot 4's camera".

1. **The camera.** Every sighting of a landmark while there is ground truth: its bearing
   error (measured − true, gross errors beyond 0.3 rad left out) regressed on
   (1, bearing b, turn rate ω) — an offset (the camera's yaw on the robot), a bearing
   scale (its field of view) and a latency (a camera reporting a picture δ s old sees
   the bearing of δ·ω ago) — and the range's median measured / true ratio (its scale).
2. ``--evaluate``: the estimator offline, each robot with the profile fitted on the
   other four (benchmarks/profiles/without-robotK.toml), on its sightings as recorded;
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
from dataclasses import dataclass, replace

import numpy as np

from slamlens.common.messages import Observations
from slamlens.services.harness.mrclam_pipeline import DATA, left_out_profile
from slamlens.services.slam.mrclam import MrclamRun, load_mrclam
from slamlens.services.slam.scoring import TruthTrack, evaluate

ROBOTS = (1, 2, 3, 4, 5)
GROSS_BEARING = 0.3  #: rad: bearing errors beyond this are misreads, left out
GROSS_RANGE = 0.5  #: m: range errors beyond this are misreads, left out of the scale
RATE_HALF_S = 0.05  #: the truth's turn rate is its heading change over ±this, s
EARLY_S = 120.0  #: the short calibration: the run's first this many seconds


@dataclass(frozen=True)
class Camera:
    """One camera's errors: bearing = true·(1 + scale) + offset + latency·ω (+ noise);
    range = true · range_scale (+ noise)."""

    offset: float = 0.0  #: rad
    scale: float = 0.0  #: bearing error per rad of bearing
    latency: float = 0.0  #: s
    range_scale: float = 1.0  #: median measured / true range
    sightings: int = 0


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


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
        rate = _wrap(after[2] - before[2]) / (2 * RATE_HALF_S)
        for lid, r, b in zip(m.ids, m.ranges, m.bearings, strict=True):
            if lid in where:
                dx, dy = where[lid][0] - pose[0], where[lid][1] - pose[1]
                error = _wrap(b - _wrap(math.atan2(dy, dx) - pose[2]))
                rows.append((b, rate, error, r, math.hypot(dx, dy)))
    return np.array(rows).reshape(-1, 5)


def fit_camera(rows: np.ndarray) -> Camera:
    """The camera's offset, bearing scale and latency (least squares on the bearing
    errors) and its range scale (median ratio), gross errors left out."""
    good = np.abs(rows[:, 2]) < GROSS_BEARING
    X = np.column_stack([np.ones(good.sum()), rows[good, 0], rows[good, 1]])
    (offset, scale, latency), *_ = np.linalg.lstsq(X, rows[good, 2], rcond=None)
    fair = np.abs(rows[:, 3] - rows[:, 4]) < GROSS_RANGE
    return Camera(float(offset), float(scale), float(latency),
                  float(np.median(rows[fair, 3] / rows[fair, 4])), int(good.sum()))


def calibrated(run: MrclamRun, camera: Camera) -> MrclamRun:
    """``run`` with ``camera``'s errors taken off its sightings (stamps moved back by its
    latency, ranges ÷ its scale, bearings less offset and scale)."""
    m = run.measurements.copy()
    m[:, 0] -= camera.latency
    m[:, 2] /= camera.range_scale
    m[:, 3] = (m[:, 3] - camera.offset) / (1.0 + camera.scale)
    order = np.argsort(m[:, 0], kind="stable")
    return replace(run, measurements=m[order])


def report_cameras(cameras: dict[int, Camera]) -> None:
    print("the cameras against the truth: bearing error = offset + scale·b + latency·ω; "
          "range scale = median measured / true")
    for k, c in cameras.items():
        print(f"  robot {k}: {c.sightings:5d} sightings  offset {math.degrees(c.offset):+.2f}°  "
              f"bearing scale {c.scale:+.2%}  latency {c.latency * 1e3:4.0f} ms  "
              f"range scale {c.range_scale:.4f}")


def score(robot: int, variant: str, camera: Camera) -> str:
    """One offline run of ``robot`` with its left-out profile, ``camera`` taken off."""
    run = calibrated(load_mrclam(DATA, robot), camera)
    e = evaluate(run, left_out_profile(robot))
    return (f"  robot {robot}  {variant:<44} NEES {e.nees_mean:5.2f}  "
            f"map {e.landmark_rmse_rigid:.3f} m")


def report_filter(cameras: dict[int, Camera]) -> None:
    """Part 2 (two processes)."""
    jobs = []
    for k in cameras:
        others = float(np.mean([c.latency for j, c in cameras.items() if j != k]))
        early = fit_camera(sightings(load_mrclam(DATA, k), EARLY_S))
        jobs += [(k, "as recorded", Camera()),
                 (k, f"latency of the other four ({others * 1e3:.0f} ms) off",
                  Camera(latency=others)),
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
    cameras = {k: fit_camera(sightings(load_mrclam(DATA, k))) for k in ROBOTS}
    report_cameras(cameras)
    if args.evaluate:
        report_filter(cameras)
    return 0


if __name__ == "__main__":
    sys.exit(main())
