"""A fixed board of world markers, and a moving (head-mounted) camera's pose from it.

The board lists markers of one dictionary and size, each with its pose in the world frame
(``T_world_from_marker``, marker frame as OpenCV defines it). A small TOML file describes one::

    dictionary = "apriltag_36h11"
    marker_size_m = 0.2
    [[markers]]
    id = 10
    position_m = [-1.0, -1.0, 0.0]   # marker centre in the world frame
    rpy_deg = [0.0, 0.0, 0.0]        # optional; R = Rz(yaw)·Ry(pitch)·Rx(roll); zero = flat,
                                     # face up, marker x along world x
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamlens.common.config import read_toml
from slamlens.common.errors import ConfigError
from slamlens.common.geometry import invert_T, make_T, transform_points
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.markers import (
    DEFAULT_DICTIONARY,
    DICTIONARIES,
    Detection,
    is_custom,
)
from slamlens.services.registration.pose import (
    PoseError,
    T_from_rvec_tvec,
    marker_object_points,
    marker_pose,
    reprojection_rms,
)

log = logging.getLogger(__name__)
#: a board pose of three markers or more fitting worse than this is checked for a marker
#: that does not fit the others (px RMS; a clean pose of a few markers fits to ~0.3 px)
OUTLIER_RMS_PX = 0.6


def rotation_from_rpy_deg(rpy_deg: Sequence[float]) -> np.ndarray:
    """R = Rz(yaw)·Ry(pitch)·Rx(roll), angles in degrees (ROS fixed-axis convention)."""
    roll, pitch, yaw = (math.radians(float(a)) for a in rpy_deg)
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch),
                              math.sin(pitch), math.cos(yaw), math.sin(yaw))
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


@dataclass(frozen=True, eq=False)
class BoardMarker:
    """One marker of the board."""

    marker_id: int
    T_world_from_marker: np.ndarray
    """4x4 rigid transform, read-only."""

    def __post_init__(self) -> None:
        T = np.array(self.T_world_from_marker, dtype=np.float64).reshape(4, 4)
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ConfigError(f"board marker {self.marker_id}: T_world_from_marker is not rigid")
        T.setflags(write=False)
        object.__setattr__(self, "T_world_from_marker", T)
        object.__setattr__(self, "marker_id", int(self.marker_id))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, BoardMarker):
            return NotImplemented
        return self.marker_id == other.marker_id and np.array_equal(
            self.T_world_from_marker, other.T_world_from_marker)

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class MarkerBoard:
    """Markers fixed in the world, all of one dictionary and one size."""

    dictionary: str
    marker_size_m: float
    markers: tuple[BoardMarker, ...]

    def __post_init__(self) -> None:
        if self.dictionary not in DICTIONARIES and not is_custom(self.dictionary):
            raise ConfigError(f"board dictionary {self.dictionary!r}; choices: "
                              f"{', '.join(sorted(DICTIONARIES))}, or a custom FILE.yml")
        if not self.marker_size_m > 0.0:
            raise ConfigError(f"board marker_size_m must be positive, got {self.marker_size_m}")
        ids = [m.marker_id for m in self.markers]
        if len(set(ids)) != len(ids):
            raise ConfigError(f"board marker ids repeat: {sorted(ids)}")
        object.__setattr__(self, "markers", tuple(self.markers))

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(m.marker_id for m in self.markers)

    def marker(self, marker_id: int) -> BoardMarker:
        for m in self.markers:
            if m.marker_id == marker_id:
                return m
        raise KeyError(marker_id)

    def corners_in_world(self, marker_id: int) -> np.ndarray:
        """(4, 3) corners of one marker in the world frame, in Detection order."""
        return transform_points(self.marker(marker_id).T_world_from_marker,
                                marker_object_points(self.marker_size_m))


def default_board(*, area_min_xy: Sequence[float] = (-1.0, -1.0),
                  area_max_xy: Sequence[float] = (2.0, 2.0), marker_size_m: float = 0.2,
                  first_id: int = 10, dictionary: str = DEFAULT_DICTIONARY) -> MarkerBoard:
    """Four markers flat on the floor, face up, centred on the arena's corners.

    The default area is the paper world's 3 m × 3 m arena; ids run first_id.. counter-
    clockwise from (min x, min y). Marker x is along world x.
    """
    (x0, y0), (x1, y1) = area_min_xy, area_max_xy
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    markers = tuple(BoardMarker(first_id + k, make_T(np.eye(3), np.array([x, y, 0.0])))
                    for k, (x, y) in enumerate(corners))
    return MarkerBoard(dictionary=dictionary, marker_size_m=marker_size_m, markers=markers)


def _number_list(path: str, key: str, value: Any, n: int) -> list[float]:
    if (not isinstance(value, list) or len(value) != n
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise ConfigError(f"{path}: {key} must be a list of {n} numbers, got {value!r}")
    return [float(v) for v in value]


def board_from_mapping(data: dict[str, Any], *, source: str = "board") -> MarkerBoard:
    """Validate a parsed TOML mapping into a board (unknown keys named)."""
    unknown = sorted(set(data) - {"dictionary", "marker_size_m", "markers"})
    if unknown:
        raise ConfigError(f"{source}: unknown board key(s) {', '.join(unknown)}")
    dictionary = data.get("dictionary", DEFAULT_DICTIONARY)
    size = data.get("marker_size_m")
    if not isinstance(size, (int, float)) or isinstance(size, bool):
        raise ConfigError(f"{source}: marker_size_m must be a number, got {size!r}")
    entries = data.get("markers")
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{source}: needs at least one [[markers]] table")
    markers = []
    for k, entry in enumerate(entries):
        where = f"markers[{k}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{source}: {where} must be a table")
        extra = sorted(set(entry) - {"id", "position_m", "rpy_deg"})
        if extra:
            raise ConfigError(f"{source}: {where}: unknown key(s) {', '.join(extra)}")
        marker_id = entry.get("id")
        if not isinstance(marker_id, int) or isinstance(marker_id, bool) or marker_id < 0:
            raise ConfigError(f"{source}: {where}.id must be a non-negative integer")
        position = _number_list(source, f"{where}.position_m", entry.get("position_m"), 3)
        rpy = _number_list(source, f"{where}.rpy_deg", entry.get("rpy_deg", [0, 0, 0]), 3)
        markers.append(BoardMarker(marker_id, make_T(rotation_from_rpy_deg(rpy),
                                                     np.array(position))))
    return MarkerBoard(dictionary=str(dictionary), marker_size_m=float(size),
                       markers=tuple(markers))


def load_board(path: str | Path) -> MarkerBoard:
    """A board from its TOML file (format in the module docstring)."""
    return board_from_mapping(read_toml(path, what="board file"), source=str(Path(path)))


def camera_pose_from_board(detections: Iterable[Detection], board: MarkerBoard,
                           calib: CameraCalibration
                           ) -> tuple[np.ndarray, float, int] | None:
    """(T_world_from_camera, RMS reprojection error px, markers used), or None if no board
    marker is in view or the solve fails.

    One marker: IPPE_SQUARE (exact for a square). Several: SQPNP, a globally optimal solver
    that needs no initial guess, over every visible corner, then Levenberg–Marquardt.
    A board id seen twice in one image is ambiguous and left out. With three markers or
    more and an RMS error over :data:`OUTLIER_RMS_PX`, the marker whose leaving out halves
    the error at least is left out (a corner hidden behind a post, a marker knocked).
    """
    by_id: dict[int, list[Detection]] = {}
    for det in detections:
        if det.marker_id in board.ids:
            by_id.setdefault(det.marker_id, []).append(det)
    used = [dets[0] for dets in by_id.values() if len(dets) == 1]
    for marker_id, dets in by_id.items():
        if len(dets) > 1:
            log.debug("board marker %d seen %d times; left out", marker_id, len(dets))
    if not used:
        return None
    found = _solve(used, board, calib)
    if found is not None and found[1] > OUTLIER_RMS_PX and len(used) >= 3:
        # one marker that does not fit the others (a corner hidden behind something,
        # a marker moved): without it the rest must agree much better to be believed
        trials = [_solve(used[:k] + used[k + 1:], board, calib) for k in range(len(used))]
        best = min((t for t in trials if t is not None), key=lambda t: t[1], default=None)
        if best is not None and best[1] < found[1] / 2:
            log.debug("board marker left out: RMS %.2f px without it, %.2f px with it",
                      best[1], found[1])
            found = best
    return found


def _solve(used: list[Detection], board: MarkerBoard, calib: CameraCalibration
           ) -> tuple[np.ndarray, float, int] | None:
    try:
        if len(used) == 1:
            det = used[0]
            T_camera_from_marker, rms = marker_pose(det, size_m=board.marker_size_m, calib=calib)
            T_world_from_marker = board.marker(det.marker_id).T_world_from_marker
            return T_world_from_marker @ invert_T(T_camera_from_marker), rms, 1
        obj = np.concatenate([board.corners_in_world(d.marker_id) for d in used])
        img = np.concatenate([d.corners_px for d in used])
        ok, rvec, tvec = cv2.solvePnP(obj, img, calib.K, calib.dist, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, calib.K, calib.dist, rvec, tvec)
    except (cv2.error, PoseError) as exc:
        log.debug("board pose failed: %s", exc)
        return None
    T_camera_from_world = T_from_rvec_tvec(rvec, tvec)
    if not np.all(np.isfinite(T_camera_from_world)):
        return None
    rms = reprojection_rms(obj, img, T_camera_from_object=T_camera_from_world, calib=calib)
    return invert_T(T_camera_from_world), rms, len(used)
