"""Marker pose and the registration chain camera ← marker ← robot ← map (docs/protocol.md).

Frames: the marker frame is OpenCV's (origin at the marker centre, x to the right of the
marker image, y up the image, z out of its face). By default the marker lies flat on the
robot, face up, with marker x = robot forward and marker y = robot left, so the rotation
robot ← marker is the identity and only the offset (marker centre in the robot frame)
remains. The map frame is the robot's pose when SLAM starts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from slamlens.common.errors import GeometryError
from slamlens.common.geometry import T_from_pose2, invert_T, make_T
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.markers import Detection


class PoseError(GeometryError):
    """A pose could not be computed from the given corners (degenerate or non-finite)."""


def marker_object_points(size_m: float) -> np.ndarray:
    """(4, 3) marker corners in the marker frame, in :class:`Detection` order.

    Top-left (−s/2, s/2), top-right (s/2, s/2), bottom-right (s/2, −s/2), bottom-left
    (−s/2, −s/2), z = 0: the layout SOLVEPNP_IPPE_SQUARE requires.
    """
    if not size_m > 0.0:
        raise PoseError(f"marker size must be positive, got {size_m}")
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def T_from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """4x4 transform from OpenCV's Rodrigues vector and translation."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return make_T(R, np.asarray(tvec, dtype=np.float64).reshape(3))


def rvec_tvec_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (rvec, tvec) for a 4x4 transform."""
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3], dtype=np.float64))
    return rvec.reshape(3, 1), np.asarray(T[:3, 3], dtype=np.float64).reshape(3, 1)


def reprojection_rms(object_points: np.ndarray, image_points: np.ndarray, *,
                     T_camera_from_object: np.ndarray, calib: CameraCalibration) -> float:
    """RMS pixel distance between ``image_points`` and the projected ``object_points``."""
    rvec, tvec = rvec_tvec_from_T(T_camera_from_object)
    projected, _ = cv2.projectPoints(np.asarray(object_points, dtype=np.float64).reshape(-1, 3),
                                     rvec, tvec, calib.K, calib.dist)
    residual = projected.reshape(-1, 2) - np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1))))


def marker_pose(det: Detection, *, size_m: float, calib: CameraCalibration,
                refine: bool = True) -> tuple[np.ndarray, float]:
    """T_camera_from_marker and the RMS reprojection error (px) of one detected marker.

    IPPE_SQUARE returns both poses of the planar ambiguity; the one with the smaller
    reprojection error wins, then Levenberg–Marquardt polishes it (``refine``). With
    ``refine`` the answer is also cross-checked against SQPNP + LM and the lower RMS wins:
    OpenCV 5.0's IPPE_SQUARE misses the true pose when the corners fit one (almost)
    exactly, as a noise-free face-on marker makes them (both of its solutions 20–30° off,
    and LM stays in that valley); SQPNP is globally optimal and costs tens of µs.
    """
    corners = np.asarray(det.corners_px, dtype=np.float64).reshape(4, 2)
    if not np.all(np.isfinite(corners)):
        raise PoseError(f"marker {det.marker_id}: non-finite corners")
    obj = marker_object_points(size_m)
    try:
        n, rvecs, tvecs, errors = cv2.solvePnPGeneric(
            obj, corners, calib.K, calib.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error as exc:
        raise PoseError(f"marker {det.marker_id}: solvePnP failed ({exc.err})") from None
    # IPPE can return a NaN rotation for one of its two solutions (seen with a rotation of
    # about 180° about an axis in the image plane): keep the finite ones only
    finite = [k for k in range(n) if np.all(np.isfinite(rvecs[k])) and np.all(np.isfinite(
        tvecs[k])) and np.isfinite(np.ravel(errors)[k])]
    if finite:
        best = min(finite, key=lambda k: float(np.ravel(errors)[k]))
        rvec, tvec = rvecs[best], tvecs[best]
    else:
        # SQPNP needs no initial guess and does not share IPPE's failure modes
        ok, rvec, tvec = cv2.solvePnP(obj, corners, calib.K, calib.dist,
                                      flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise PoseError(f"marker {det.marker_id}: no pose for corners {corners.tolist()}")
    if refine:
        # LM on all 4 corners removes IPPE's small algebraic bias (it fits a homography first)
        rvec, tvec = cv2.solvePnPRefineLM(obj, corners, calib.K, calib.dist, rvec.copy(),
                                          tvec.copy())
    T = T_from_rvec_tvec(rvec, tvec)
    if not np.all(np.isfinite(T)) or T[2, 3] <= 0.0:
        raise PoseError(f"marker {det.marker_id}: pose behind the camera or non-finite")
    rms = reprojection_rms(obj, corners, T_camera_from_object=T, calib=calib)
    if refine:
        try:
            ok, rvec2, tvec2 = cv2.solvePnP(obj, corners, calib.K, calib.dist,
                                            flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                rvec2, tvec2 = cv2.solvePnPRefineLM(obj, corners, calib.K, calib.dist, rvec2,
                                                    tvec2)
                T2 = T_from_rvec_tvec(rvec2, tvec2)
                if np.all(np.isfinite(T2)) and T2[2, 3] > 0.0:
                    rms2 = reprojection_rms(obj, corners, T_camera_from_object=T2, calib=calib)
                    if rms2 < rms:
                        return T2, rms2
        except cv2.error:  # keep IPPE's answer
            pass
    return T, rms


def _offset(marker_offset_xyz: Sequence[float]) -> np.ndarray:
    offset = np.asarray(marker_offset_xyz, dtype=np.float64).reshape(-1)
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise PoseError(f"marker offset must be 3 finite numbers, got {marker_offset_xyz!r}")
    return offset


def T_robot_from_marker(marker_offset_xyz: Sequence[float]) -> np.ndarray:
    """Marker flat on the robot, face up, axes aligned with the robot's (docs/protocol.md)."""
    return make_T(np.eye(3), _offset(marker_offset_xyz))


def T_marker_from_map(marker_offset_xyz: Sequence[float], *,
                      robot_pose_in_map: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """inverse(T_map_from_robot · T_robot_from_marker) for the robot at ``robot_pose_in_map``
    (x, y, θ); at registration time the robot is at the map origin."""
    T_map_from_robot = T_from_pose2(np.asarray(robot_pose_in_map, dtype=np.float64))
    return invert_T(T_map_from_robot @ T_robot_from_marker(marker_offset_xyz))


def T_camera_from_map(T_camera_from_marker: np.ndarray, marker_offset_xyz: Sequence[float], *,
                      robot_pose_in_map: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The registration: T_camera_from_marker · T_marker_from_map."""
    return np.asarray(T_camera_from_marker, dtype=np.float64) @ T_marker_from_map(
        marker_offset_xyz, robot_pose_in_map=robot_pose_in_map)


def robot_pose_from_marker(T_camera_from_marker: np.ndarray, T_camera_from_map: np.ndarray,
                           marker_offset_xyz: Sequence[float]) -> np.ndarray:
    """The camera-measured robot pose (x, y, θ) in the map frame.

    θ is the heading of the robot's x axis projected onto the map's x–y plane, so a marker
    seen slightly tilted still gives the planar heading.
    """
    T_map_from_marker = invert_T(np.asarray(T_camera_from_map, dtype=np.float64)) @ np.asarray(
        T_camera_from_marker, dtype=np.float64)
    T_map_from_robot = T_map_from_marker @ invert_T(T_robot_from_marker(marker_offset_xyz))
    heading = math.atan2(T_map_from_robot[1, 0], T_map_from_robot[0, 0])
    return np.array([T_map_from_robot[0, 3], T_map_from_robot[1, 3], heading])


def project_points(points_in_map: np.ndarray, *, T_camera_from_map: np.ndarray,
                   calib: CameraCalibration) -> np.ndarray:
    """(N, 2) pixels of (N, 3) map points through the camera, with its lens distortion.

    Points at or behind the camera plane (z ≤ 0 in the camera frame) come out as NaN:
    OpenCV would mirror them into the picture.
    """
    points = np.asarray(points_in_map, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        return np.zeros((0, 2))
    rvec, tvec = rvec_tvec_from_T(np.asarray(T_camera_from_map, dtype=np.float64))
    pixels, _ = cv2.projectPoints(points, rvec, tvec, calib.K, calib.dist)
    pixels = pixels.reshape(-1, 2)
    T = np.asarray(T_camera_from_map, dtype=np.float64)
    depth = points @ T[2, :3] + T[2, 3]
    pixels[depth <= 0.0] = np.nan
    return pixels
