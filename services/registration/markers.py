"""Fiducial marker detection: OpenCV's ArUco/AprilTag detector plus sub-pixel edge refinement.

Corners come out in OpenCV's order (top-left, top-right, bottom-right, bottom-left of the
marker image, clockwise on screen) and OpenCV's pixel convention (pixel centres at integer
coordinates). The default corner refinement, ``"edges"``, fits a straight line to each side of
the marker's black border (the gradient peak along the side's normal, sampled at ≥ 16 points)
and intersects neighbouring lines, iterated to a fixed point. It is the refinement that
AprilTag's C library uses (``refine_edges``), and on the real photos in tests/fixtures it is
the most accurate of OpenCV's choices as well (docs/registration_vision.md has the figures).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from slamlens.common.errors import ConfigError, GeometryError, SourceError

log = logging.getLogger(__name__)

DICTIONARIES: Mapping[str, int] = {
    "apriltag_16h5": cv2.aruco.DICT_APRILTAG_16h5,
    "apriltag_25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "apriltag_36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "apriltag_36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "aruco_original": cv2.aruco.DICT_ARUCO_ORIGINAL,
    "aruco_mip_36h12": cv2.aruco.DICT_ARUCO_MIP_36h12,
    **{
        f"aruco_{n}x{n}_{size}": getattr(cv2.aruco, f"DICT_{n}X{n}_{size}")
        for n in (4, 5, 6, 7) for size in (50, 100, 250, 1000)
    },
}
"""Dictionary names accepted on the command line and in settings → OpenCV constants."""

DEFAULT_DICTIONARY = "apriltag_36h11"
CORNER_REFINEMENTS = ("edges", "subpix", "apriltag", "contour", "none")
_CV_REFINEMENT = {
    "edges": cv2.aruco.CORNER_REFINE_NONE,  # OpenCV's raw contour corners, then ours
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
}


CUSTOM_SUFFIXES = (".yml", ".yaml")
#: pixels a detection window reaches beyond a marker and its motion margin: more than
#: OpenCV's largest adaptive-threshold window (23 px) and its border distance (3 px)
WINDOW_PAD_PX = 32


def is_custom(name: str) -> bool:
    """Whether a dictionary "name" is the path of a custom dictionary YAML (``FILE.yml``)."""
    return name.lower().endswith(CUSTOM_SUFFIXES)


def check_dictionary(name: str) -> None:
    """ConfigError unless ``name`` is a built-in dictionary or a readable custom one."""
    get_dictionary(name)


def get_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The OpenCV dictionary called ``name`` (see :data:`DICTIONARIES`), or the custom one
    in the OpenCV YAML file ``name`` (``*.yml`` / ``*.yaml``, :func:`load_custom_dictionary`)."""
    if is_custom(name):
        return _custom(str(Path(name).resolve()))
    try:
        return cv2.aruco.getPredefinedDictionary(DICTIONARIES[name])
    except KeyError:
        raise ConfigError(f"unknown marker dictionary {name!r}; choices: "
                          f"{', '.join(sorted(DICTIONARIES))}, or a custom dictionary "
                          "FILE.yml") from None


@lru_cache(maxsize=8)
def _custom(path: str) -> cv2.aruco.Dictionary:
    return load_custom_dictionary(path)


def load_custom_dictionary(path: str | Path) -> cv2.aruco.Dictionary:
    """A dictionary from a YAML like OpenCV's ``tutorial_dict.yml`` (nmarkers, markersize,
    marker_0 … as bit strings)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"custom dictionary {p} does not exist")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        raise ConfigError(f"custom dictionary {p} is not an OpenCV YAML file") from None
    try:
        dictionary = cv2.aruco.Dictionary()
        if not fs.isOpened() or not dictionary.readDictionary(fs.root()):
            raise ConfigError(f"custom dictionary {p}: needs nmarkers, markersize and marker_i")
    finally:
        fs.release()
    return dictionary


def marker_image(dictionary: str, marker_id: int, *, side_px: int,
                 border_bits: int = 1) -> np.ndarray:
    """The marker's black-bordered image (uint8, side_px²), as printed; no white margin."""
    return cv2.aruco.generateImageMarker(get_dictionary(dictionary), marker_id, side_px,
                                         borderBits=border_bits)


@dataclass(frozen=True)
class Detection:
    """One marker found in an image."""

    marker_id: int
    """The marker's id in its dictionary."""
    corners_px: np.ndarray
    """(4, 2) float64 pixels, OpenCV order: top-left, top-right, bottom-right, bottom-left of
    the marker image; read-only."""

    def __post_init__(self) -> None:
        corners = np.array(self.corners_px, dtype=np.float64).reshape(4, 2)
        corners.setflags(write=False)
        object.__setattr__(self, "corners_px", corners)
        object.__setattr__(self, "marker_id", int(self.marker_id))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Detection):
            return NotImplemented
        return self.marker_id == other.marker_id and np.array_equal(self.corners_px,
                                                                    other.corners_px)

    __hash__ = None  # type: ignore[assignment]

    @property
    def center_px(self) -> np.ndarray:
        return self.corners_px.mean(axis=0)

    @property
    def side_px(self) -> float:
        """Mean side length in pixels."""
        return float(np.mean(np.linalg.norm(
            self.corners_px - np.roll(self.corners_px, -1, axis=0), axis=1)))


def mean_detection(detections: Sequence[Detection]) -> Detection:
    """The corner-wise mean of one marker's detections in several frames of a still camera.

    A single small marker seen face-on constrains its tilt poorly (at 3 m a 0.2 m marker's
    tilt moves its corners by hundredths of a pixel per degree), so registration should
    average a few frames before solving the pose.
    """
    if not detections:
        raise GeometryError("mean_detection needs at least one detection")
    ids = {d.marker_id for d in detections}
    if len(ids) != 1:
        raise GeometryError(f"mean_detection needs one marker id, got {sorted(ids)}")
    return Detection(detections[0].marker_id,
                     np.mean([d.corners_px for d in detections], axis=0))


@dataclass(frozen=True)
class DetectorTuning:
    """Detector settings; the defaults keep OpenCV's candidate search (see the benchmark)."""

    corner_refinement: str = field(default="edges", metadata={"choices": CORNER_REFINEMENTS})
    """"edges" (line fit to the border, default), OpenCV's "subpix"/"apriltag"/"contour", or
    "none" (raw contour vertices, what OpenCV's own tests compare against)."""
    downscale: float = field(default=1.0, metadata={"min": 1.0})
    """Find candidates on the image shrunk by this factor, then refine corners at full
    resolution ("edges" recommended with it: the shrunk corners are ±downscale/2 px)."""
    min_marker_perimeter_rate: float = field(default=0.03, metadata={"min": 0.0})
    """Smallest marker perimeter as a fraction of the image's larger side (OpenCV default)."""
    adaptive_thresh_win_size_min: int = field(default=3, metadata={"min": 3})
    adaptive_thresh_win_size_max: int = field(default=23, metadata={"min": 3})
    adaptive_thresh_win_size_step: int = field(default=10, metadata={"min": 1})
    """OpenCV thresholds the image once per window size in min..max by step: fewer is faster."""
    edge_search_px: float = field(default=1.5, metadata={"min": 0.5})
    """How far each edge refinement step looks either side of the current side, pixels."""
    edge_max_iterations: int = field(default=20, metadata={"min": 1})
    edge_tolerance_px: float = field(default=0.01, metadata={"min": 0.0})


# --- "edges" refinement: a pure function over all markers at once -------------------------

_REMAP_MAX_ROWS = 30000  # cv2.remap wants map sides below SHRT_MAX


def _sample_lines(gray: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear intensities at float32 (…, L) coordinates, one row per sampled line."""
    shape = xs.shape
    xs2 = xs.reshape(-1, shape[-1])
    ys2 = ys.reshape(-1, shape[-1])
    out = np.empty(xs2.shape, np.float32)
    for r in range(0, xs2.shape[0], _REMAP_MAX_ROWS):
        # cv2.remap is bilinear to 1/32 px: far below the 0.25 px search step
        out[r:r + _REMAP_MAX_ROWS] = cv2.remap(gray, xs2[r:r + _REMAP_MAX_ROWS],
                                               ys2[r:r + _REMAP_MAX_ROWS], cv2.INTER_LINEAR,
                                               borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(shape)


def _refine_once(gray: np.ndarray, corners: np.ndarray, *, search_px: float,
                 step_px: float = 0.25, gradient_px: float = 1.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """One line-fit step for (m, 4, 2) corners; returns (new corners, ok per marker)."""
    start = corners
    end = np.roll(corners, -1, axis=1)
    side = end - start
    length = np.linalg.norm(side, axis=-1)  # (m, 4)
    along = side / np.maximum(length, 1e-9)[..., None]
    nx, ny = along[..., 1], -along[..., 0]  # outward normal for clockwise corners
    # ≥ 16 samples per side, one every 8 px on big markers (as AprilTag's refine_edges)
    n_samples = max(16, int(math.ceil(float(length.max()) / 8.0)))
    alpha = (1.0 + np.arange(n_samples)) / (n_samples + 1)  # skip the unreliable corners
    base = start[:, :, None, :] + alpha[None, None, :, None] * side[:, :, None, :]
    # one line of intensities per sample point along the normal; the gradient at offset t
    # is I(t + g) − I(t − g), i.e. a difference of samples 2k apart
    k = max(1, int(round(gradient_px / step_px)))
    offsets = np.arange(-search_px, search_px + 1e-9, step_px)
    line = np.arange(-k, len(offsets) + k) * step_px + offsets[0]
    xs = (base[..., 0, None] + line * nx[:, :, None, None]).astype(np.float32)
    ys = (base[..., 1, None] + line * ny[:, :, None, None]).astype(np.float32)
    values = _sample_lines(gray, xs, ys)
    gradient = (values[..., 2 * k:] - values[..., :-2 * k]).astype(np.float64)
    # dark inside, light outside: a backwards gradient belongs to another edge, drop it
    weight = np.where(gradient > 0.0, gradient * gradient, 0.0)
    total = weight.sum(axis=-1)
    valid = total > 0.0
    shift = (weight @ offsets) / np.where(valid, total, 1.0)
    normal = np.stack([nx, ny], axis=-1)
    points = base + shift[..., None] * normal[:, :, None, :]  # (m, 4, ns, 2)

    count = valid.sum(axis=-1)  # (m, 4)
    w = valid.astype(np.float64)
    denom = np.maximum(count, 1)[..., None]
    mean = (points * w[..., None]).sum(axis=2) / denom
    d = (points - mean[:, :, None, :]) * w[..., None]
    cxx = (d[..., 0] ** 2).sum(axis=-1)
    cyy = (d[..., 1] ** 2).sum(axis=-1)
    cxy = (d[..., 0] * d[..., 1]).sum(axis=-1)
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # principal axis of the samples
    direction = np.stack([np.cos(angle), np.sin(angle)], axis=-1)

    # corner i joins side i−1 (ending at it) and side i (starting at it)
    m1, d1 = np.roll(mean, 1, axis=1), np.roll(direction, 1, axis=1)
    m2, d2 = mean, direction
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    diff = m2 - m1
    s = (diff[..., 0] * d2[..., 1] - diff[..., 1] * d2[..., 0]) / np.where(
        np.abs(cross) > 1e-3, cross, 1.0)
    refined = m1 + s[..., None] * d1
    ok = np.all(count >= 3, axis=1) & np.all(np.abs(cross) > 1e-3, axis=1)
    ok &= np.all(np.isfinite(refined), axis=(1, 2))
    return np.where(ok[:, None, None], refined, corners), ok


def refine_corners_edges(gray: np.ndarray, corners: np.ndarray, *, search_px: float = 1.5,
                         max_iterations: int = 20, tolerance_px: float = 0.01) -> np.ndarray:
    """Refine (m, 4, 2) marker corners by fitting lines to the border edges.

    Each step moves every side to the gradient peak within ``search_px`` of it and
    re-intersects the sides; steps repeat until no corner moves more than
    ``tolerance_px``. A marker whose fit fails or wanders further than a quarter of its
    side (2 px at least) from where it started keeps its input corners.
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
    if corners.shape[0] == 0:
        return corners.copy()
    image = gray if gray.dtype == np.float32 else gray.astype(np.float32)
    current = corners.copy()
    active = np.ones(len(corners), dtype=bool)
    failed = np.zeros(len(corners), dtype=bool)
    for _ in range(max_iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        refined, ok = _refine_once(image, current[idx], search_px=search_px)
        moved = np.abs(refined - current[idx]).max(axis=(1, 2))
        current[idx] = refined
        failed[idx[~ok]] = True
        active[idx[(moved < tolerance_px) | ~ok]] = False
    side = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=-1).mean(axis=1)
    wandered = np.abs(current - corners).max(axis=(1, 2)) > np.maximum(2.0, 0.25 * side)
    keep = failed | wandered
    current[keep] = corners[keep]
    return current


# --- the detector ---------------------------------------------------------------------------

def to_gray(image: np.ndarray) -> np.ndarray:
    """uint8 gray from a gray, BGR or BGRA image; SourceError on anything else."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise SourceError(f"image: expected a uint8 numpy array, got "
                          f"{getattr(image, 'dtype', type(image).__name__)}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return np.ascontiguousarray(image[:, :, 0])
    raise SourceError(f"image: expected HxW, HxWx3 or HxWx4, got shape {image.shape}")


class MarkerDetector:
    """Finds markers of one dictionary; stateless between frames apart from its settings."""

    def __init__(self, dictionary: str = DEFAULT_DICTIONARY, *,
                 params: DetectorTuning | None = None,
                 custom_dictionary_path: str | Path | None = None) -> None:
        self.tuning = params or DetectorTuning()
        if self.tuning.corner_refinement not in CORNER_REFINEMENTS:
            raise ConfigError(f"corner_refinement {self.tuning.corner_refinement!r}; "
                              f"choices: {', '.join(CORNER_REFINEMENTS)}")
        if custom_dictionary_path is not None or is_custom(dictionary):
            path = custom_dictionary_path if custom_dictionary_path is not None else dictionary
            self.dictionary_name = f"custom:{path}"
            self.dictionary = load_custom_dictionary(path)
        else:
            self.dictionary_name = dictionary
            self.dictionary = get_dictionary(dictionary)
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, self._cv_parameters())
        self._window_detector: cv2.aruco.ArucoDetector | None = None
        self._window_rate = -1.0

    def _cv_parameters(self) -> cv2.aruco.DetectorParameters:
        t = self.tuning
        p = cv2.aruco.DetectorParameters()
        p.cornerRefinementMethod = _CV_REFINEMENT[t.corner_refinement]
        p.minMarkerPerimeterRate = t.min_marker_perimeter_rate
        p.adaptiveThreshWinSizeMin = t.adaptive_thresh_win_size_min
        p.adaptiveThreshWinSizeMax = max(t.adaptive_thresh_win_size_max,
                                         t.adaptive_thresh_win_size_min)
        p.adaptiveThreshWinSizeStep = t.adaptive_thresh_win_size_step
        return p

    def detect(self, image: np.ndarray) -> list[Detection]:
        """Markers in a BGR, BGRA or gray uint8 image, sorted by id then x then y."""
        gray = to_gray(image)
        scale = self.tuning.downscale
        if scale > 1.0:
            small = cv2.resize(gray, (max(1, round(gray.shape[1] / scale)),
                                      max(1, round(gray.shape[0] / scale))),
                               interpolation=cv2.INTER_AREA)
            corners, ids, _ = self._detector.detectMarkers(small)
        else:
            corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None or len(ids) == 0:
            return []
        found = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
        if scale > 1.0:
            sx = gray.shape[1] / small.shape[1]
            sy = gray.shape[0] / small.shape[0]
            # pixel centres sit at integers: scale about the −0.5 pixel edge, not about 0
            found = (found + 0.5) * np.array([sx, sy]) - 0.5
        return self.finish(gray, found, ids)

    def finish(self, gray: np.ndarray, found: np.ndarray, ids: np.ndarray) -> list[Detection]:
        """OpenCV's corners ``found`` (k, 4, 2, image pixels) of markers ``ids`` refined
        (the "edges" refinement) and sorted by id then x then y."""
        return finish_detections(gray, found, ids, self.tuning)

    def detect_window(self, gray: np.ndarray, box: tuple[int, int, int, int]
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """Unrefined corners (k, 4, 2, in the box's pixels) and ids of the markers in
        ``box`` (x0, y0, x1, y1) of ``gray``, accepting exactly the marker sizes the whole
        image would (:class:`WindowedDetector`); None if there are none."""
        x0, y0, x1, y1 = box
        crop = gray[y0:y1, x0:x1]
        # OpenCV's minimum perimeter is a rate of the input's larger side: scaled, the
        # window accepts the marker sizes the whole image does
        rate = self.tuning.min_marker_perimeter_rate * max(gray.shape) / max(crop.shape)
        if self._window_detector is None or rate != self._window_rate:
            params = self._cv_parameters()
            params.minMarkerPerimeterRate = rate
            params.maxMarkerPerimeterRate = max(params.maxMarkerPerimeterRate, rate)
            self._window_detector = cv2.aruco.ArucoDetector(self.dictionary, params)
            self._window_rate = rate
        corners, ids, _ = self._window_detector.detectMarkers(np.ascontiguousarray(crop))
        if ids is None or len(ids) == 0:
            return None
        return np.asarray(corners, np.float64).reshape(-1, 4, 2), np.ravel(ids)


def finish_detections(gray: np.ndarray, found: np.ndarray, ids: np.ndarray,
                      tuning: DetectorTuning) -> list[Detection]:
    """Corners ``found`` (k, 4, 2, OpenCV's order and pixels) of markers ``ids`` refined as
    ``tuning`` says (the "edges" refinement, or as they are) and sorted by id, x, y."""
    if tuning.corner_refinement == "edges":
        found = refine_corners_edges(gray, found, search_px=tuning.edge_search_px,
                                     max_iterations=tuning.edge_max_iterations,
                                     tolerance_px=tuning.edge_tolerance_px)
    detections = [Detection(int(i), c) for i, c in zip(np.ravel(ids), found, strict=True)]
    detections.sort(key=lambda d: (d.marker_id, *d.center_px))
    return detections


class AnyDetector(Protocol):
    """What :class:`WindowedDetector` needs of a detector (OpenCV's, or AprilTag's own in
    :mod:`~slamlens.services.registration.apriltag3`)."""

    tuning: DetectorTuning

    def detect(self, image: np.ndarray) -> list[Detection]: ...

    def finish(self, gray: np.ndarray, found: np.ndarray,
               ids: np.ndarray) -> list[Detection]: ...

    def detect_window(self, gray: np.ndarray, box: tuple[int, int, int, int]
                      ) -> tuple[np.ndarray, np.ndarray] | None: ...


class WindowedDetector:
    """A :class:`MarkerDetector` that, between full-frame detections, looks only where the
    markers were: the same detections for a fraction of the pixels.

    Every ``full_every``-th frame (and the first, and whenever the last frame found nothing)
    it detects over the whole image. In between it detects in a window around each marker
    of the last frame — the marker plus ``margin`` of its side on every side, for its motion
    between frames, plus :data:`WINDOW_PAD_PX` so that OpenCV's adaptive threshold sees the
    same neighbourhood as over the whole image — with the minimum perimeter scaled so that
    a window accepts exactly the sizes the whole image would. If a window loses a marker of
    the last frame, that frame is detected again over the whole image, so a marker is never
    missed for the window's sake, and the next 1, 2, 4, … (at most ``full_every``) frames
    are detected whole before windows are tried again (a marker faster than its window does
    not pay twice each frame); a marker newly in view is found at the next full frame, at
    most ``full_every`` frames later. docs/registration.md, "Detection windows".
    """

    def __init__(self, detector: AnyDetector, *, full_every: int = 15,
                 margin: float = 1.0) -> None:
        if full_every < 1:
            raise ConfigError(f"full_every {full_every}: at least 1 (1 = every frame whole)")
        self.detector = detector
        self.full_every = int(full_every)
        self.margin = float(margin)
        self.full_frames = 0  #: frames detected over the whole image
        self.window_frames = 0  #: frames detected in windows only
        self.fallbacks = 0  #: frames whose windows lost a marker: detected whole again
        self._last: list[Detection] = []
        self._shape: tuple[int, ...] = ()  #: the last frame's shape (a new size: whole)
        self._since_full = 0
        #: after a fallback, frames detected whole before windows are tried again (doubling
        #: while they keep failing: a marker moving faster than its window costs a wasted
        #: window detection at most every full_every-th frame)
        self._backoff = 0
        self._skip = 0

    def _windows(self, shape: tuple[int, ...]) -> list[tuple[int, int, int, int]]:
        """(x0, y0, x1, y1) around the last frame's markers, overlapping ones merged."""
        h, w = shape[:2]
        boxes = []
        for d in self._last:
            lo, hi = d.corners_px.min(axis=0), d.corners_px.max(axis=0)
            grow = self.margin * max(d.side_px, 1.0) + WINDOW_PAD_PX
            boxes.append([max(0, math.floor(lo[0] - grow)), max(0, math.floor(lo[1] - grow)),
                          min(w, math.ceil(hi[0] + grow) + 1),
                          min(h, math.ceil(hi[1] + grow) + 1)])
        merged: list[list[int]] = []
        for box in boxes:  # a handful of boxes: each absorbs every one it overlaps
            i = 0
            while i < len(merged):
                o = merged[i]
                if box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3]:
                    box = [min(box[0], o[0]), min(box[1], o[1]), max(box[2], o[2]),
                           max(box[3], o[3])]
                    del merged[i]
                    i = 0  # grown: it may overlap one it passed
                else:
                    i += 1
            merged.append(box)
        return [(a, b, c, d) for a, b, c, d in merged]

    def detect(self, image: np.ndarray) -> list[Detection]:
        """As :meth:`MarkerDetector.detect`: markers sorted by id then x then y."""
        tuning = self.detector.tuning
        if (not self._last or self._since_full + 1 >= self.full_every
                or tuning.downscale > 1.0 or self._skip > 0
                or image.shape[:2] != self._shape):
            self._skip = max(0, self._skip - 1)
            return self._full(image)
        gray = to_gray(image)
        corners_all, ids_all = [], []
        for box in self._windows(gray.shape):
            found = self.detector.detect_window(gray, box)
            if found is not None:
                corners_all.append(found[0] + np.array([box[0], box[1]], np.float64))
                ids_all.append(found[1])
        found_ids = sorted(int(i) for i in np.concatenate(ids_all)) if ids_all else []
        if found_ids != sorted(d.marker_id for d in self._last):
            self.fallbacks += 1  # a marker lost (or one more): the whole image decides
            self._backoff = min(max(1, 2 * self._backoff), self.full_every)
            self._skip = self._backoff
            return self._full(image, gray)
        self._backoff = 0
        detections = self.detector.finish(gray, np.concatenate(corners_all),
                                          np.concatenate(ids_all))
        self._last = detections
        self._since_full += 1
        self.window_frames += 1
        return detections

    def _full(self, image: np.ndarray, gray: np.ndarray | None = None) -> list[Detection]:
        detections = self.detector.detect(image if gray is None else gray)
        self._last = detections
        self._shape = image.shape[:2]
        self._since_full = 0
        self.full_frames += 1
        return detections
