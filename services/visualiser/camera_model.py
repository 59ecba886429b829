"""A pinhole camera with OpenCV distortion, placed by ``T_camera_from_map`` (docs/protocol.md).

``project`` is a vectorised equivalent of ``cv2.projectPoints`` for the rational /
thin-prism models (4, 5, 8 or 12 coefficients); a tilted sensor (14 coefficients with a
non-zero tilt) falls back to OpenCV itself. Points at or behind the near plane get NaN
pixels and their (non-positive) depth, so callers can cull them.

Polynomial distortion folds back far outside the calibrated field of view (a point well
off the image can land inside it). Beyond the radius where ``r·radial(r)`` stops
increasing the radial factor is held at its value there, so off-image geometry stays
off-image; inside the image the model is OpenCV's exactly.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from slamlens.common.errors import CalibrationError
from slamlens.common.geometry import make_T
from slamlens.common.messages import Registration

NEAR_M = 1e-3  #: points closer than this to the camera plane are not projected


def _frozen(array: Any, shape: tuple[int, ...] | None, name: str) -> np.ndarray:
    a = np.array(array, dtype=float)
    if shape is not None and a.shape != shape:
        raise CalibrationError(f"camera model {name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"camera model {name}: expected finite values")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics ``K``, OpenCV distortion ``dist``, image size and the camera's pose."""

    K: np.ndarray  #: 3x3 camera matrix, pixels
    #: OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, k4..k6[, s1..s4[, τx, τy]]]])
    dist: np.ndarray
    width: int  #: image width, pixels
    height: int  #: image height, pixels
    T_camera_from_map: np.ndarray  #: 4x4, map frame → camera frame, m

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _frozen(self.K, (3, 3), "K"))
        dist = _frozen(self.dist, None, "dist").reshape(-1)
        if dist.size not in (0, 4, 5, 8, 12, 14):
            raise CalibrationError(f"camera model dist: expected 0, 4, 5, 8, 12 or 14 "
                                   f"coefficients, got {dist.size}")
        dist.setflags(write=False)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "T_camera_from_map",
                           _frozen(self.T_camera_from_map, (4, 4), "T_camera_from_map"))
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"camera model size: expected positive width and height, "
                                   f"got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.K[2, 2] != 1.0 or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CalibrationError("camera model K: expected positive focal lengths and K[2,2]=1")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (self.width == other.width and self.height == other.height
                and np.array_equal(self.K, other.K) and np.array_equal(self.dist, other.dist)
                and np.array_equal(self.T_camera_from_map, other.T_camera_from_map))

    __hash__ = None  # type: ignore[assignment]

    # -- construction ---------------------------------------------------------------
    @classmethod
    def from_registration(cls, reg: Registration) -> CameraModel:
        """The camera a registration describes."""
        return cls(K=reg.K, dist=reg.dist, width=reg.width, height=reg.height,
                   T_camera_from_map=reg.T_camera_from_map)

    @classmethod
    def top_down(cls, *, bounds_xy: tuple[float, float, float, float], width: int = 1280,
                 height: int = 720, margin: float = 0.15) -> CameraModel:
        """A virtual camera looking straight down on the map: the map view.

        Image right is map +x and image up is map +y. The camera hangs above the centre of
        ``bounds_xy`` (xmin, ymin, xmax, ymax) at a height equal to the larger side of the
        padded bounds (a ~53° field of view: enough perspective for the cones and
        ellipsoids to read as 3D), and the focal length fits the bounds plus ``margin``
        (a fraction of each side) inside the image.
        """
        xmin, ymin, xmax, ymax = (float(b) for b in bounds_xy)
        if not all(math.isfinite(b) for b in (xmin, ymin, xmax, ymax)):
            raise CalibrationError(f"top-down view: bounds must be finite, got {bounds_xy}")
        cx_m, cy_m = (xmin + xmax) / 2, (ymin + ymax) / 2
        # An empty or degenerate map still gets a 1 m wide view.
        span_x = max(xmax - xmin, 1.0) * (1 + 2 * margin)
        span_y = max(ymax - ymin, 1.0) * (1 + 2 * margin)
        distance_m = max(span_x, span_y)
        f = min(width / span_x, height / span_y) * distance_m
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        # camera x = map x, camera y = −map y (image down), optical axis z = −map z.
        R = np.diag([1.0, -1.0, -1.0])
        centre = np.array([cx_m, cy_m, distance_m])
        return cls(K=K, dist=np.zeros(0), width=width, height=height,
                   T_camera_from_map=make_T(R, -R @ centre))

    def stereo_pair(self, baseline_m: float) -> tuple[CameraModel, CameraModel]:
        """Left and right cameras ``baseline_m`` apart along this camera's x axis (parallel)."""
        if not baseline_m > 0:
            raise CalibrationError(f"stereo baseline must be positive, got {baseline_m}")
        half = baseline_m / 2
        left = make_T(np.eye(3), np.array([half, 0.0, 0.0])) @ self.T_camera_from_map
        right = make_T(np.eye(3), np.array([-half, 0.0, 0.0])) @ self.T_camera_from_map
        return (CameraModel(K=self.K, dist=self.dist, width=self.width, height=self.height,
                            T_camera_from_map=left),
                CameraModel(K=self.K, dist=self.dist, width=self.width, height=self.height,
                            T_camera_from_map=right))

    def resized(self, width: int, height: int) -> CameraModel:
        """The same camera for an image scaled to ``width`` x ``height``."""
        if (width, height) == (self.width, self.height):
            return self
        S = np.diag([width / self.width, height / self.height, 1.0])
        return CameraModel(K=S @ self.K, dist=self.dist, width=width, height=height,
                           T_camera_from_map=self.T_camera_from_map)

    # -- geometry -------------------------------------------------------------------
    @property
    def centre_map(self) -> np.ndarray:
        """The camera centre in the map frame, m."""
        R, t = self.T_camera_from_map[:3, :3], self.T_camera_from_map[:3, 3]
        return -R.T @ t

    @property
    def P(self) -> np.ndarray:
        """3x4 projection matrix K·[R|t] of the undistorted pinhole."""
        return self.K @ self.T_camera_from_map[:3, :]

    @functools.cached_property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    @functools.cached_property
    def _r2_limit(self) -> float:
        """Squared normalised radius up to which the radial model is monotonic."""
        d = np.zeros(12)
        d[:min(12, self.dist.size)] = self.dist[:12]
        r = np.linspace(0.0, 4.0, 4001)  # up to ~76° off axis, far beyond any lens here
        r2 = r * r
        radial = (1 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))) / \
                 (1 + r2 * (d[5] + r2 * (d[6] + r2 * d[7])))
        rd = r * radial
        bad = np.flatnonzero((np.diff(rd) <= 0) | ~np.isfinite(rd[1:]) | (radial[1:] <= 0))
        return float(r2[bad[0]]) if bad.size else float(r2[-1])

    def distort_normalised(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion model to normalised image coordinates (N, 2)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if not self.has_distortion:
            return xy.copy()
        d = self.dist
        if d.size == 14 and np.any(d[12:] != 0):
            out = np.full_like(xy, np.nan)
            ok = np.all(np.isfinite(xy), axis=1)
            if ok.any():
                pts = np.column_stack([xy[ok], np.ones(int(ok.sum()))])
                proj, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), d)
                out[ok] = proj.reshape(-1, 2)
            return out
        c = np.zeros(12)
        c[:d.size] = d[:12]
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        rc = np.minimum(r2, self._r2_limit)  # hold the radial factor beyond the fold-back
        radial = (1 + rc * (k1 + rc * (k2 + rc * k3))) / (1 + rc * (k4 + rc * (k5 + rc * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
        return np.column_stack([xd, yd])

    def distort_pixels(self, uv_pinhole: np.ndarray) -> np.ndarray:
        """Map undistorted pinhole pixels (N, 2) to the distorted image's pixels."""
        uv = np.asarray(uv_pinhole, dtype=float).reshape(-1, 2)
        if not self.has_distortion:
            return uv.copy()
        K = self.K
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        xd = self.distort_normalised(np.column_stack([x, y]))
        return np.column_stack([K[0, 0] * xd[:, 0] + K[0, 1] * xd[:, 1] + K[0, 2],
                                K[1, 1] * xd[:, 1] + K[1, 2]])

    def to_camera(self, points_map: np.ndarray) -> np.ndarray:
        """Points (N, 3) from the map frame into the camera frame."""
        pts = np.asarray(points_map, dtype=float).reshape(-1, 3)
        T = self.T_camera_from_map
        return pts @ T[:3, :3].T + T[:3, 3]

    def project(self, points_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and camera depths (N,) of map points (N, 3), with distortion.

        Points with depth ≤ ``NEAR_M`` (behind or on the camera plane) get NaN pixels.
        """
        pc = self.to_camera(points_map)
        depth = pc[:, 2]
        front = depth > NEAR_M
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / np.where(front, depth, np.nan)[:, None]
        xy = self.distort_normalised(xy) if self.has_distortion else xy
        K = self.K
        uv = np.column_stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2],
                              K[1, 1] * xy[:, 1] + K[1, 2]])
        uv[~front] = np.nan
        return uv, depth
