"""Small tags: recall and corner accuracy of OpenCV's detector and AprilTag's own (the C
library through pupil-apriltags), with and without the project's edge refinement.

Frames: 1280×720, an overhead camera 3 m up (hfov 84°) over a textured floor, 24 AprilTag
36h11 markers per frame lying flat at random places and headings, 15–20 px a side (a
ceiling camera over a large arena), blur σ 0.7 px and noise σ 2 grey levels
(services/harness/marker_render.py: an independent renderer; its corners are the truth). Also
the shared real photo (13 tags of ~28 px; the C library's 12 detections of it are its
reference). Configurations are timed round robin on each frame; the script prints, per
configuration, markers found of those placed (recall), wrong ids, the corner error against
the truth (median and p95 px), and median ms per frame.

    .venv/bin/python benchmarks/bench_small_tags.py [--frames 8] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.geometry import make_T, rot_z  # noqa: E402
from slamlens.services.harness.marker_render import (  # noqa: E402
    PlacedMarker,
    render,
    true_corners,
)
from slamlens.services.registration.apriltag3 import (  # noqa: E402
    AprilTagDetector,
    AprilTagTuning,
)
from slamlens.services.registration.calibration import synthetic_calibration  # noqa: E402
from slamlens.services.registration.markers import (  # noqa: E402
    DetectorTuning,
    MarkerDetector,
)

CALIB = synthetic_calibration(1280, 720, hfov_deg=84.0)
HEIGHT_M = 3.0
N_MARKERS = 24
PHOTO = REPO / "tests" / "fixtures" / "fiducials" / "apriltag" / "33369213973_9d9bb4cc96_c.jpg"
PHOTO_REFERENCE = PHOTO.with_suffix(".txt")

NONE, EDGES = DetectorTuning(corner_refinement="none"), DetectorTuning()
CONFIGS = {
    "opencv + edges (the default before)": MarkerDetector(params=EDGES),
    "opencv, no refinement": MarkerDetector(params=NONE),
    "apriltag3, its own refinement": AprilTagDetector(params=NONE),
    "apriltag3 + edges": AprilTagDetector(params=EDGES),
    "apriltag3 decimate 2 + edges": AprilTagDetector(
        params=EDGES, library=AprilTagTuning(quad_decimate=2.0)),
}


def floor(rng: np.random.Generator) -> np.ndarray:
    h, w = CALIB.height, CALIB.width
    ys, xs = np.mgrid[0:h, 0:w]
    tile_px = 0.5 * CALIB.fx / HEIGHT_M
    tiles = ((xs // tile_px).astype(int) + (ys // tile_px).astype(int)) % 2
    image = 105.0 + 20.0 * tiles + rng.normal(0.0, 6.0, (h, w))
    image = cv2.GaussianBlur(image, (0, 0), 1.2) + 25.0 * (xs / w - 0.5)
    return np.clip(image, 0, 255).astype(np.uint8)


def make_frame(seed: int) -> tuple[np.ndarray, list[PlacedMarker]]:
    rng = np.random.default_rng(1000 + seed)
    R = np.diag([1.0, -1.0, -1.0])  # looking straight down
    half_w = HEIGHT_M * (CALIB.width / 2) / CALIB.fx * 0.9
    half_h = HEIGHT_M * (CALIB.height / 2) / CALIB.fy * 0.9
    placed: list[PlacedMarker] = []
    while len(placed) < N_MARKERS:
        x, y = rng.uniform(-half_w, half_w), rng.uniform(-half_h, half_h)
        if any(np.hypot(x - p.T_camera_from_marker[0, 3], -y - p.T_camera_from_marker[1, 3])
               < 0.2 for p in placed):
            continue
        side_px = float(rng.uniform(15.0, 20.0))
        z = float(rng.uniform(0.0, 0.2))
        size = side_px * (HEIGHT_M - z) / CALIB.fx
        T_wm = make_T(rot_z(rng.uniform(-math.pi, math.pi)), [x, y, z])
        placed.append(PlacedMarker(len(placed), make_T(R, [0.0, 0.0, HEIGHT_M]) @ T_wm, size))
    gray = render(CALIB, placed, background=floor(rng), blur_sigma_px=0.7, noise_sigma=2.0,
                  seed=seed)
    return gray, placed


def photo_reference() -> np.ndarray:
    """The C library's corners of the photo, in OpenCV's order and pixels."""
    rows = []
    for line in PHOTO_REFERENCE.read_text().splitlines():
        values = line.replace("(", " ").replace(")", " ").replace(",", " ").split()
        rows.append(np.array(values[1:], float).reshape(4, 2)[[1, 0, 3, 2]] - 0.5)
    return np.array(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    frames = [make_frame(seed) for seed in range(args.frames)]
    found = {name: 0 for name in CONFIGS}
    wrong = {name: 0 for name in CONFIGS}
    errors: dict[str, list[float]] = {name: [] for name in CONFIGS}
    times: dict[str, list[float]] = {name: [] for name in CONFIGS}
    for gray, placed in frames:
        truth = {p.marker_id: true_corners(p, CALIB.K) for p in placed}
        for name, detector in CONFIGS.items():
            for det in detector.detect(gray):
                if det.marker_id not in truth:
                    wrong[name] += 1
                    continue
                err = np.linalg.norm(det.corners_px - truth[det.marker_id], axis=1)
                if err.max() > 3.0:
                    wrong[name] += 1
                    continue
                found[name] += 1
                errors[name].extend(err.tolist())
        for _ in range(args.repeats):
            for name, detector in CONFIGS.items():
                t0 = time.perf_counter()
                detector.detect(gray)
                times[name].append((time.perf_counter() - t0) * 1e3)
    total = N_MARKERS * args.frames
    print(f"{args.frames} frames 1280x720, {N_MARKERS} AprilTag 36h11 tags of 15-20 px each "
          f"({total} placed), blur 0.7, noise 2")
    print(f"{'configuration':38s} {'found':>9s} {'wrong':>5s} {'median px':>9s} "
          f"{'p95 px':>6s} {'ms':>6s}")
    for name in CONFIGS:
        e = np.array(errors[name]) if errors[name] else np.array([math.nan])
        print(f"{name:38s} {found[name]:4d}/{total:<4d} {wrong[name]:5d} "
              f"{np.median(e):9.3f} {np.percentile(e, 95):6.3f} "
              f"{statistics.median(times[name]):6.1f}")
    photo = cv2.imread(str(PHOTO), cv2.IMREAD_GRAYSCALE)
    reference = photo_reference()
    print(f"\nreal photo {PHOTO.name}: the C library's {len(reference)} tags as reference")
    for name, detector in CONFIGS.items():
        dets = detector.detect(photo)
        matched = []
        for ref in reference:
            best = min((float(np.abs(d.corners_px - ref).max()) for d in dets), default=99.0)
            if best < 3.0:
                matched.append(best)
        print(f"{name:38s} found {len(dets):2d}, {len(matched):2d} of the library's "
              f"{len(reference)}; corner max {max(matched):.2f} / median "
              f"{statistics.median(matched):.2f} px from them")


if __name__ == "__main__":
    main()
