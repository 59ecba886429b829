"""AprilTag's own detector (the C library through pupil-apriltags) beside OpenCV's, and
``slamlens detect``.

Oracles: the C library's published detections of the real photo (its ``.txt``, converted to
OpenCV's order and pixels as docs/registration_vision.md says), and the corners of the
independent test renderer (services/harness/marker_render.py) for rendered 15-20 px tags.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import cv2
import numpy as np

from slamlens.services.harness.procs import REPO, slamlens_cmd
from slamlens.services.registration import apriltag3
from slamlens.services.registration.apriltag3 import AprilTagDetector
from slamlens.services.registration.markers import DetectorTuning, MarkerDetector

PHOTO = REPO / "tests" / "fixtures" / "fiducials" / "apriltag" / "33369213973_9d9bb4cc96_c.jpg"


def library_reference() -> np.ndarray:
    rows = []
    for line in PHOTO.with_suffix(".txt").read_text().splitlines():
        values = line.replace("(", " ").replace(")", " ").replace(",", " ").split()
        rows.append(np.array(values[1:], float).reshape(4, 2)[[1, 0, 3, 2]] - 0.5)
    return np.array(rows)


def nearest(dets, ref: np.ndarray) -> float:
    return min((float(np.abs(d.corners_px - ref).max()) for d in dets), default=np.inf)


def test_the_photo_gives_the_libraries_tags_in_opencv_conventions() -> None:
    photo = cv2.imread(str(PHOTO))
    reference = library_reference()
    raw = AprilTagDetector(params=DetectorTuning(corner_refinement="none")).detect(photo)
    edges = AprilTagDetector().detect(photo)
    assert len(raw) == len(edges) == len(reference) == 12
    # the library at quad_decimate 1 against its own published detections
    assert max(nearest(raw, ref) for ref in reference) < 0.7
    # with the edge refinement: as close as OpenCV's detector with it (0.54 px, the docs)
    assert max(nearest(edges, ref) for ref in reference) < 0.6
    assert all(d.marker_id == 0 for d in edges)


def test_small_tags_all_found_with_accurate_corners() -> None:
    import sys
    sys.path.insert(0, str(REPO / "benchmarks"))
    sys.path.insert(0, str(REPO / "tests" / "unit"))
    from bench_small_tags import CALIB, make_frame

    from slamlens.services.harness.marker_render import true_corners

    gray, placed = make_frame(0)
    truth = {p.marker_id: true_corners(p, CALIB.K) for p in placed}
    found = {d.marker_id: d for d in AprilTagDetector().detect(gray)}
    assert set(found) == set(truth)  # every 15-20 px tag, no false one
    errors = np.concatenate([np.linalg.norm(found[i].corners_px - truth[i], axis=1)
                             for i in truth])
    opencv = {d.marker_id: d for d in MarkerDetector().detect(gray)}
    opencv_errors = np.concatenate([np.linalg.norm(opencv[i].corners_px - truth[i], axis=1)
                                    for i in opencv if i in truth])
    # no worse than OpenCV's detector with the same refinement, on the tags both find
    assert np.median(errors) < 0.2 and np.median(errors) <= np.median(opencv_errors) + 0.02


def test_one_library_detector_per_thread_and_configuration() -> None:
    gray = cv2.imread(str(PHOTO), cv2.IMREAD_GRAYSCALE)
    made = len(apriltag3._MADE)
    seen: list[int] = []

    def work() -> None:
        for _ in range(50):  # many detector objects, few library detectors
            seen.append(len(AprilTagDetector().detect(gray)))

    threads = [threading.Thread(target=work) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    # at most one new library detector per thread (none if idle ones were there: the
    # pool's), none destroyed when its thread ended, and every detection the same
    assert len(apriltag3._MADE) - made <= 2 and apriltag3._MADE
    assert len(set(seen)) == 1 and len(seen) == 100


def test_detect_command_json(tmp_path: Path) -> None:
    import subprocess

    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((120, 160, 3), 200, np.uint8))
    out = subprocess.run([*slamlens_cmd("detect", str(PHOTO), str(blank), "--detector",
                                        "apriltag3", "--json")], capture_output=True,
                         text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    assert [line["image"] for line in lines] == [str(PHOTO), str(blank)]
    assert lines[1]["detections"] == []
    dets = lines[0]["detections"]
    assert len(dets) == 12 and all(set(d) == {"id", "corners"} for d in dets)
    assert all(len(d["corners"]) == 4 and all(len(c) == 2 for c in d["corners"]) for d in dets)
    reference = library_reference()
    for ref in reference:  # OpenCV's convention: within the refinement of the library's
        assert min(np.abs(np.array(d["corners"]) - ref).max() for d in dets) < 0.6
    bad = subprocess.run(slamlens_cmd("detect", str(tmp_path / "nope.png")),
                         capture_output=True, text=True, timeout=60, cwd=REPO)
    assert bad.returncode != 0 and "cannot read image" in bad.stderr
    assert "Traceback" not in bad.stderr
