"""AprilTag's own detector: the AprilTag 3 C library (through ``pupil-apriltags``) beside
OpenCV's.

On small tags the C library finds markers OpenCV's ArUco detector does not (its quads come
from a segmentation of the gradient, not from thresholded contours): on a real photo with
15-20 px tags the project's OpenCV detector found 15 of the 25 the library found, so a
ceiling camera over a large arena missed robots. :class:`AprilTagDetector` runs the library
and hands its corners over in OpenCV's conventions (docs/registration_vision.md: its
``p[1], p[0], p[3], p[2]`` are OpenCV's top-left, top-right, bottom-right, bottom-left, and
its pixel centres sit at +0.5), then applies the project's edge refinement where it helps
(``DetectorTuning.corner_refinement``, "edges" by default; measured in
``benchmarks/bench_detection.py``).

The C library crashes when a ``Detector`` is destroyed while another thread detects (a
thread-local detector freed at its thread's end did, in the test suite), and has crashed at
interpreter exit after many were made and dropped: library detectors are never destroyed.
A process-wide pool keeps them per configuration; a detection borrows one for its call and
gives it back (:func:`_borrowed`), so there are only as many as detections ever ran at once.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from slamlens.common.errors import ConfigError
from slamlens.services.registration.markers import (
    Detection,
    DetectorTuning,
    MarkerDetector,
    finish_detections,
    to_gray,
)

#: the dictionaries the C library knows (slamlens name → its family)
FAMILIES = {"apriltag_16h5": "tag16h5", "apriltag_25h9": "tag25h9",
            "apriltag_36h11": "tag36h11"}
#: OpenCV's corner order from the library's p[0..3] (which wrap the other way round)
_TO_OPENCV = [1, 0, 3, 2]

#: idle library detectors per (family, tuning); never destroyed (module docstring)
_POOL: dict[tuple[str, Any], list[Any]] = {}
_POOL_LOCK = threading.Lock()
_MADE: list[Any] = []  #: every library detector made, kept alive for the process


@dataclass(frozen=True)
class AprilTagTuning:
    """The C library's own settings (its defaults but ``quad_decimate``)."""

    quad_decimate: float = 1.0
    """Find quads on the image shrunk by this factor; the library's default 2 misses
    small tags (one of the 13 on the shared photo)."""
    quad_sigma: float = 0.0
    refine_edges: bool = True
    decode_sharpening: float = 0.25


def available() -> bool:
    """Whether the C library's binding is installed."""
    try:
        import pupil_apriltags  # noqa: F401
    except ImportError:
        return False
    return True


@contextlib.contextmanager
def _borrowed(family: str, tuning: AprilTagTuning) -> Iterator[Any]:
    """An idle library detector for ``family`` and ``tuning`` (made if none is idle), for
    this caller alone until it is given back."""
    key = (family, tuning)
    with _POOL_LOCK:
        idle = _POOL.setdefault(key, [])
        detector = idle.pop() if idle else None
    if detector is None:
        from pupil_apriltags import Detector

        detector = Detector(
            families=family, nthreads=1, quad_decimate=tuning.quad_decimate,
            quad_sigma=tuning.quad_sigma, refine_edges=int(tuning.refine_edges),
            decode_sharpening=tuning.decode_sharpening)
        with _POOL_LOCK:
            _MADE.append(detector)
    try:
        yield detector
    finally:
        with _POOL_LOCK:
            _POOL[key].append(detector)


class AprilTagDetector:
    """Finds markers of one AprilTag dictionary with the C library (module docstring)."""

    def __init__(self, dictionary: str = "apriltag_36h11", *,
                 params: DetectorTuning | None = None,
                 library: AprilTagTuning | None = None) -> None:
        if dictionary not in FAMILIES:
            raise ConfigError(f"--detector apriltag3 reads {', '.join(sorted(FAMILIES))}, "
                              f"not {dictionary!r} (use --detector opencv)")
        if not available():
            raise ConfigError("--detector apriltag3 needs the pupil-apriltags package "
                              "(pip install pupil-apriltags)")
        self.dictionary_name = dictionary
        self.family = FAMILIES[dictionary]
        self.tuning = params or DetectorTuning()
        if self.tuning.corner_refinement not in ("edges", "none"):
            raise ConfigError(f"--detector apriltag3: corner refinement "
                              f"{self.tuning.corner_refinement!r}; choices: edges, none")
        self.library = library or AprilTagTuning()

    def raw(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The library's corners (k, 4, 2) in OpenCV's order and pixels, and the ids."""
        with _borrowed(self.family, self.library) as library:
            found = library.detect(np.ascontiguousarray(gray))
        if not found:
            return np.zeros((0, 4, 2)), np.zeros(0, np.int64)
        corners = np.array([d.corners for d in found], np.float64)[:, _TO_OPENCV] - 0.5
        return corners, np.array([d.tag_id for d in found], np.int64)

    def detect(self, image: np.ndarray) -> list[Detection]:
        """Markers in a BGR, BGRA or gray uint8 image, sorted by id then x then y."""
        gray = to_gray(image)
        corners, ids = self.raw(gray)
        if len(ids) == 0:
            return []
        return self.finish(gray, corners, ids)

    def finish(self, gray: np.ndarray, found: np.ndarray, ids: np.ndarray) -> list[Detection]:
        return finish_detections(gray, found, ids, self.tuning)

    def detect_window(self, gray: np.ndarray, box: tuple[int, int, int, int]
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """The library's markers in ``box`` (x0, y0, x1, y1) of ``gray``, in the box's
        pixels (it has no size limit relative to the image: the whole image's sizes)."""
        x0, y0, x1, y1 = box
        corners, ids = self.raw(gray[y0:y1, x0:x1])
        return None if len(ids) == 0 else (corners, ids)


def make_detector(detector: str, dictionary: str) -> MarkerDetector | AprilTagDetector:
    """The detector ``--detector`` names (``opencv`` or ``apriltag3``) for ``dictionary``."""
    if detector == "apriltag3":
        return AprilTagDetector(dictionary)
    if detector != "opencv":
        raise ConfigError(f"--detector {detector!r}; choices: opencv, apriltag3")
    return MarkerDetector(dictionary)
