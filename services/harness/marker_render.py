"""A small, independent marker renderer for tests and benchmarks (not the product's
synthetic camera): each marker's printed image is warped into an ideal pinhole view with
the homography of its four projected outer corners, supersampled then area-averaged so
edges are anti-aliased like a real camera's.

Pixel convention (OpenCV's): pixel centres at integer coordinates, so the marker texture's
outer edges are at −0.5 and n−0.5 in texture pixels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.markers import get_dictionary, marker_image
from slamlens.services.registration.pose import marker_object_points


@dataclass(frozen=True)
class PlacedMarker:
    marker_id: int
    T_camera_from_marker: np.ndarray
    size_m: float
    margin_cells: float = 1.0  # white quiet zone around the black border, in marker cells


def project_pinhole(points_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Ideal pinhole projection of (N, 3) camera-frame points."""
    p = np.asarray(points_camera, dtype=np.float64)
    return (p[:, :2] / p[:, 2:3]) @ K[:2, :2].T + K[:2, 2]


def true_corners(placed: PlacedMarker, K: np.ndarray) -> np.ndarray:
    """(4, 2) exact image corners of the marker's black border, Detection order."""
    obj = marker_object_points(placed.size_m)
    cam = obj @ placed.T_camera_from_marker[:3, :3].T + placed.T_camera_from_marker[:3, 3]
    return project_pinhole(cam, K)


def render(calib: CameraCalibration, markers: Sequence[PlacedMarker], *,
           dictionary: str = "apriltag_36h11", background: np.ndarray | int = 110,
           supersample: int = 3, texture_px: int = 480, blur_sigma_px: float = 0.0,
           noise_sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    """A gray uint8 image of ``markers`` seen by the distortion-free camera ``calib``."""
    if np.any(calib.dist != 0.0):
        raise ValueError("render draws an ideal pinhole; give a calibration without distortion")
    S = supersample
    w, h = calib.width * S, calib.height * S
    K = calib.K.copy()
    K[:2, :2] *= S
    K[:2, 2] = (K[:2, 2] + 0.5) * S - 0.5  # same pixel-centre convention at S× resolution
    canvas: np.ndarray  # float32 throughout
    if isinstance(background, np.ndarray):
        canvas = cv2.resize(background, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    else:
        canvas = np.full((h, w), float(background), np.float32)
    for placed in markers:
        image = marker_image(dictionary, placed.marker_id, side_px=texture_px)
        cells = _cells(dictionary)
        pad = int(round(placed.margin_cells * texture_px / cells))
        texture = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
        n = texture.shape[0]
        half = placed.size_m / 2.0 * (texture_px + 2 * pad) / texture_px
        obj = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
        T = placed.T_camera_from_marker
        dst = project_pinhole(obj @ T[:3, :3].T + T[:3, 3], K).astype(np.float32)
        src = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]],
                       np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        # premultiplied alpha: the warped texture and its coverage share the same weights
        warped = cv2.warpPerspective(texture.astype(np.float32), H, (w, h),
                                     flags=cv2.INTER_LINEAR, borderValue=0.0)
        cover = cv2.warpPerspective(np.ones_like(texture, np.float32), H, (w, h),
                                    flags=cv2.INTER_LINEAR, borderValue=0.0)
        canvas = canvas * (1.0 - cover) + warped
    out = cv2.resize(canvas, (calib.width, calib.height), interpolation=cv2.INTER_AREA)
    if blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        out = out + np.random.default_rng(seed).normal(0.0, noise_sigma, out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _cells(dictionary: str) -> int:
    """Marker side in cells, border included (6×6 data + 2 for 36h11)."""
    return int(get_dictionary(dictionary).markerSize) + 2


def look_at(camera_position: Sequence[float], target: Sequence[float],
            up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_from_camera for an OpenCV camera (z forward, x right, y down) at
    ``camera_position`` looking at ``target``."""
    c = np.asarray(camera_position, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking along "up": pick world y as image-down
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = c
    return T
