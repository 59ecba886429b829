"""Camera intrinsics: the pinhole matrix K, lens distortion and the image size they hold for.

Files use OpenCV's FileStorage YAML, as OpenCV's calibration tools write it (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height``), so a calibration made with
OpenCV's samples, with ``slamlens calibrate`` or by hand loads the same way.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slamlens.common.errors import CalibrationError

# OpenCV's distortion models take 4, 5, 8, 12 or 14 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6
# [s1 s2 s3 s4 [τx τy]]]]); any other count is a malformed file.
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Intrinsics of one camera at one resolution (pixel centres at integer coordinates)."""

    K: np.ndarray
    """3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels; read-only."""
    dist: np.ndarray
    """(k,) OpenCV distortion coefficients, k in DISTORTION_LENGTHS; read-only."""
    width: int
    """Image width in pixels the intrinsics hold for."""
    height: int
    """Image height in pixels the intrinsics hold for."""

    def __post_init__(self) -> None:
        flat = np.array(self.K, dtype=np.float64).reshape(-1)
        if flat.size != 9 or not np.all(np.isfinite(flat)):
            raise CalibrationError(f"K: expected 3x3 finite matrix, got {np.shape(self.K)}")
        K = flat.reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], (0.0, 0.0, 1.0)):
            raise CalibrationError(f"K: expected fx, fy > 0 and last row [0 0 1], got {K.tolist()}")
        dist = np.array(self.dist, dtype=np.float64).reshape(-1)
        if dist.size not in DISTORTION_LENGTHS or not np.all(np.isfinite(dist)):
            raise CalibrationError(
                f"dist: expected {DISTORTION_LENGTHS} finite coefficients, got {dist.size}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"image size: expected positive, got {self.width}x{self.height}")
        K.setflags(write=False)
        dist.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraCalibration):
            return NotImplemented
        return (self.width == other.width and self.height == other.height
                and np.array_equal(self.K, other.K) and np.array_equal(self.dist, other.dist))

    __hash__ = None  # type: ignore[assignment]  # value equality over mutable-typed fields

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def hfov_deg(self) -> float:
        """Horizontal field of view of the undistorted pinhole, degrees."""
        return math.degrees(2.0 * math.atan2(self.width / 2.0, self.fx))


def _read_matrix(fs: cv2.FileStorage, path: Path, field: str) -> np.ndarray:
    node = fs.getNode(field)
    if node.empty() or node.isNone():
        raise CalibrationError(f"{path}: missing field {field!r}")
    if not node.isMap():
        raise CalibrationError(f"{path}: field {field!r} is not an !!opencv-matrix")
    matrix = node.mat()
    if matrix is None:
        raise CalibrationError(f"{path}: field {field!r} could not be read as a matrix")
    return np.asarray(matrix, dtype=np.float64)


def _read_int(fs: cv2.FileStorage, path: Path, field: str, fallback: int | None) -> int:
    node = fs.getNode(field)
    if node.empty() or node.isNone():
        if fallback is not None:
            return fallback
        raise CalibrationError(f"{path}: missing field {field!r}")
    if not node.isInt() and not node.isReal():
        raise CalibrationError(f"{path}: field {field!r} is not a number")
    value = node.real()
    if value != int(value) or value <= 0:
        raise CalibrationError(f"{path}: field {field!r} must be a positive integer, got {value}")
    return int(value)


def load_calibration(path: str | Path, *,
                     image_size: tuple[int, int] | None = None) -> CameraCalibration:
    """Read an OpenCV calibration YAML.

    ``image_size`` (width, height) is used only when the file has no ``image_width`` /
    ``image_height`` (older OpenCV samples omit them). Raises :class:`CalibrationError`
    naming the file and the field on any problem.
    """
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file does not exist")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV's parser raises either on a non-YAML file
        raise CalibrationError(f"{p}: not an OpenCV FileStorage YAML/XML file") from None
    if not fs.isOpened():
        raise CalibrationError(f"{p}: not an OpenCV FileStorage file")
    try:
        K = _read_matrix(fs, p, "camera_matrix")
        if K.shape != (3, 3):
            raise CalibrationError(f"{p}: field 'camera_matrix' must be 3x3, got {K.shape}")
        dist = _read_matrix(fs, p, "distortion_coefficients")
        if dist.ndim != 2 or min(dist.shape) != 1 or dist.size not in DISTORTION_LENGTHS:
            raise CalibrationError(f"{p}: field 'distortion_coefficients' must be a row or "
                                   f"column of {DISTORTION_LENGTHS} values, got {dist.shape}")
        width = _read_int(fs, p, "image_width", image_size[0] if image_size else None)
        height = _read_int(fs, p, "image_height", image_size[1] if image_size else None)
    finally:
        fs.release()
    try:
        return CameraCalibration(K=K, dist=dist.reshape(-1), width=width, height=height)
    except CalibrationError as exc:
        raise CalibrationError(f"{p}: {exc}") from None


def save_calibration(path: str | Path, calib: CameraCalibration, *,
                     rms: float | None = None) -> None:
    """Write ``calib`` in the format :func:`load_calibration` and OpenCV's tools read."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise CalibrationError(f"{p}: cannot open for writing")
    try:
        fs.write("calibration_time", time.strftime("%Y-%m-%d %H:%M:%S %Z"))
        fs.write("image_width", calib.width)
        fs.write("image_height", calib.height)
        fs.write("camera_matrix", np.asarray(calib.K, dtype=np.float64))
        fs.write("distortion_coefficients", np.asarray(calib.dist, dtype=np.float64).reshape(1, -1))
        if rms is not None:
            fs.write("avg_reprojection_error", float(rms))
    finally:
        fs.release()


def synthetic_calibration(width: int, height: int, *, hfov_deg: float = 60.0) -> CameraCalibration:
    """An ideal pinhole (no distortion, square pixels) with the given horizontal FOV.

    The principal point is the image centre in OpenCV's pixel convention, ((w−1)/2, (h−1)/2),
    so a symmetric scene renders symmetric pixels.
    """
    if not 0.0 < hfov_deg < 180.0:
        raise CalibrationError(f"hfov_deg: expected in (0, 180), got {hfov_deg}")
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraCalibration(K=K, dist=np.zeros(5), width=width, height=height)


def scaled_calibration(calib: CameraCalibration, width: int, height: int) -> CameraCalibration:
    """``calib`` for frames of the same camera and field of view at another resolution
    (the same aspect ratio): focal lengths scale with the size, the principal point about
    the image's edge (pixel centres at integers: x' = (x + 0.5)·s − 0.5); distortion,
    being in normalised coordinates, is unchanged."""
    sx, sy = width / calib.width, height / calib.height
    K = np.array(calib.K, dtype=np.float64)
    K[0, 0], K[0, 1], K[1, 1] = K[0, 0] * sx, K[0, 1] * sx, K[1, 1] * sy
    K[0, 2], K[1, 2] = (K[0, 2] + 0.5) * sx - 0.5, (K[1, 2] + 0.5) * sy - 0.5
    return CameraCalibration(K=K, dist=np.array(calib.dist), width=width, height=height)
