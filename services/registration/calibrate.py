"""The pure core of ``slamlens calibrate``: intrinsics from photos of a ChArUco board.

A ChArUco board is a chessboard whose white squares hold ArUco markers: the markers say
which chessboard corner is which, the chessboard corners (saddle points, refined with
cornerSubPix) give the accuracy. OpenCV ≥ 4.6 lays boards with an even number of rows out
differently from older versions; ``legacy_pattern`` selects the old layout (boards with an
odd number of rows, like the 5×7 tutorial board, are the same either way).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from slamlens.common.errors import CalibrationError, ConfigError
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.markers import get_dictionary, to_gray
from slamlens.services.registration.pose import T_from_rvec_tvec, reprojection_rms

log = logging.getLogger(__name__)

# fewer corners than this in one view constrain neither the pose nor the intrinsics well
MIN_CORNERS_PER_VIEW = 6


@dataclass(frozen=True)
class CharucoSpec:
    """A printed ChArUco board: squares across and down, their sizes, the dictionary."""

    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str = "aruco_6x6_250"
    legacy_pattern: bool = False

    def __post_init__(self) -> None:
        if self.squares_x < 2 or self.squares_y < 2:
            raise ConfigError(f"ChArUco board needs ≥ 2×2 squares, got "
                              f"{self.squares_x}×{self.squares_y}")
        if not 0.0 < self.marker_m < self.square_m:
            raise ConfigError(f"ChArUco marker size {self.marker_m} must be in (0, square size "
                              f"{self.square_m})")

    def board(self) -> cv2.aruco.CharucoBoard:
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m,
                                       self.marker_m, get_dictionary(self.dictionary))
        board.setLegacyPattern(self.legacy_pattern)
        return board


def detect_charuco(image: np.ndarray, spec: CharucoSpec, *,
                   board: cv2.aruco.CharucoBoard | None = None
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """(object points (n, 3) in the board frame, image points (n, 2)) of the chessboard
    corners found, or None if fewer than MIN_CORNERS_PER_VIEW are seen."""
    board = board if board is not None else spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _, _ = detector.detectBoard(to_gray(image))
    if ids is None or len(ids) < MIN_CORNERS_PER_VIEW:
        return None
    # ChArUco corners come as one (n, 1, 2) array; the stub only types the markers' overload
    obj, img = board.matchImagePoints(corners, ids)  # type: ignore[call-overload]
    return np.asarray(obj, np.float64).reshape(-1, 3), np.asarray(img, np.float64).reshape(-1, 2)


def calibrate_charuco(images: Sequence[np.ndarray], *, squares_x: int, squares_y: int,
                      square_m: float, marker_m: float, dictionary: str = "aruco_6x6_250",
                      legacy_pattern: bool = False, flags: int = 0
                      ) -> tuple[CameraCalibration, float]:
    """Calibrate one camera from photos of a ChArUco board: (calibration, RMS px).

    Views where the board is not found (or too little of it) are skipped with a log line;
    all images must have the same size. ``flags`` go to cv2.calibrateCamera (0: fx, fy,
    cx, cy and the 5-term distortion all free, as OpenCV's own calibration sample).
    """
    spec = CharucoSpec(squares_x, squares_y, square_m, marker_m, dictionary, legacy_pattern)
    board = spec.board()
    object_points: list[np.ndarray] = []
    image_points: list[np.ndarray] = []
    size: tuple[int, int] | None = None
    for k, image in enumerate(images):
        h, w = image.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise CalibrationError(f"image {k} is {w}x{h}, the first was {size[0]}x{size[1]}")
        found = detect_charuco(image, spec, board=board)
        if found is None:
            log.info("calibrate: image %d: board not found (or < %d corners), skipped",
                     k, MIN_CORNERS_PER_VIEW)
            continue
        object_points.append(found[0].astype(np.float32))
        image_points.append(found[1].astype(np.float32))
    if size is None or not object_points:
        raise CalibrationError(f"no usable view of the {squares_x}x{squares_y} ChArUco board "
                               f"in {len(images)} image(s)")
    rms, K, dist, _, _ = cv2.calibrateCamera(object_points, image_points, size, None, None,
                                             flags=flags)
    return CameraCalibration(K=K, dist=np.ravel(dist), width=size[0], height=size[1]), float(rms)


def charuco_board_pose(image: np.ndarray, *, board: CharucoSpec,
                       calib: CameraCalibration) -> tuple[np.ndarray, float] | None:
    """(T_camera_from_board, RMS reprojection px of the chessboard corners), or None if the
    board is not seen. The board frame is OpenCV's CharucoBoard frame: origin at an outer
    corner of the printed board, x along its rows, z out of the board (chessboard corner k
    at ``spec.board().getChessboardCorners()[k]``)."""
    found = detect_charuco(image, board)
    if found is None:
        return None
    obj, img = found
    # the corners are coplanar: IPPE gives the planar solution, LM polishes it
    ok, rvec, tvec = cv2.solvePnP(obj, img, calib.K, calib.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, calib.K, calib.dist, rvec, tvec)
    T = T_from_rvec_tvec(rvec, tvec)
    return T, reprojection_rms(obj, img, T_camera_from_object=T, calib=calib)
