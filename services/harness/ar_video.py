"""The test video of the AR page (tests and benchmarks): the synthetic head-mounted camera
walking round the paper world, the robot standing at its map origin, as a Y4M file for
Chromium's fake camera.

Every frame carries its index as a code in its top-left corner (:func:`read_index`), so a
picture the page shows can be matched to the exact camera pose it was rendered from (the
truth the overlay is checked against).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slamlens.services.registration.board import default_board
from slamlens.services.registration.calibration import (
    CameraCalibration,
    save_calibration,
    synthetic_calibration,
)
from slamlens.services.registration.synthetic import (
    ImagingSettings,
    SceneSettings,
    SyntheticCamera,
    WorldMarker,
    orbit_pose,
)
from slamlens.services.slam.world import load_world

ARENA = (-1.0, -1.0, 2.0, 2.0)
CENTRE = (0.5, 0.5)
HFOV_DEG = 75.0  #: the synthetic head-mounted camera's (HEAD_MOUNTED_HFOV_DEG)
BITS = 10  #: frame index code: this many bits, then a parity bit
BLOCK = 16  #: px per bit


@dataclass(frozen=True)
class Video:
    frames: list[np.ndarray]  #: BGR
    poses: list[np.ndarray]  #: T_world_from_camera of each frame
    calib: CameraCalibration
    landmarks: np.ndarray  #: (n, 2) world = map frame (the robot starts at the origin)
    ids: np.ndarray


def write_index(image: np.ndarray, index: int) -> None:
    bits = [(index >> b) & 1 for b in range(BITS)]
    bits.append(sum(bits) % 2)
    image[:BLOCK + 4, :BLOCK * (len(bits) + 1)] = 128
    for i, bit in enumerate(bits):
        x = 2 + i * BLOCK
        image[2:2 + BLOCK, x:x + BLOCK] = 255 if bit else 0


def read_index(image: np.ndarray) -> int | None:
    """The frame index coded by :func:`write_index` (None if the code does not check)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    bits = []
    for i in range(BITS + 1):
        x = 2 + i * BLOCK
        level = float(gray[2 + 4:2 + BLOCK - 4, x + 4:x + BLOCK - 4].mean())
        if 70 < level < 185:
            return None
        bits.append(1 if level >= 128 else 0)
    if sum(bits[:BITS]) % 2 != bits[BITS]:
        return None
    return sum(bit << b for b, bit in enumerate(bits[:BITS]))


def render_walk(count: int = 60, *, width: int = 1280, height: int = 720,
                arc_deg: float = 90.0, noise: float = 2.0) -> Video:
    """``count`` frames of a walk along ``arc_deg`` of the orbit, robot at the origin."""
    calib = synthetic_calibration(width, height, hfov_deg=HFOV_DEG)
    world = load_world("paper")
    board = default_board(area_min_xy=ARENA[:2], area_max_xy=ARENA[2:])
    markers = tuple(WorldMarker(m.marker_id, board.corners_in_world(m.marker_id),
                                board.dictionary) for m in board.markers)
    period = 360.0 / arc_deg * count
    camera = SyntheticCamera(calib.K, width, height, T_world_from_camera=orbit_pose(
        0.0, centre_xy=CENTRE, period_s=period), scene=SceneSettings(arena_xy=ARENA),
        imaging=ImagingSettings(noise_sigma=noise, blur_kernel=3), board=markers)
    frames, poses = [], []
    for i in range(count):
        T = orbit_pose(float(i), centre_xy=CENTRE, period_s=period)
        image = camera.render(robot_pose=np.zeros(3), landmarks_xy=world.landmarks_xy,
                              T_world_from_camera=T, frame_index=i)
        write_index(image, i)
        frames.append(image)
        poses.append(T)
    return Video(frames, poses, calib, np.asarray(world.landmarks_xy, float),
                 np.asarray(world.landmark_ids))


def write_y4m(video: Video, path: Path, *, fps: int = 30) -> Path:
    """The frames as a YUV 4:2:0 Y4M file (header ``C420``), as Chromium's fake camera reads."""
    h, w = video.frames[0].shape[:2]
    with open(path, "wb") as f:
        f.write(f"YUV4MPEG2 W{w} H{h} F{fps}:1 Ip A1:1 C420\n".encode())
        for image in video.frames:
            f.write(b"FRAME\n")
            f.write(cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420).tobytes())
    return path


def write_calibration(video: Video, path: Path) -> Path:
    save_calibration(path, video.calib)
    return path


def truth_pixels(video: Video, index: int, points_world: np.ndarray,
                 calib: CameraCalibration | None = None) -> np.ndarray:
    """Where frame ``index``'s camera sees ``points_world`` (n, 3): cv2.projectPoints with
    the true pose (independent of the viewer's camera model)."""
    calib = calib or video.calib
    T_cw = np.linalg.inv(video.poses[index])
    rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
    uv, _ = cv2.projectPoints(np.asarray(points_world, float).reshape(-1, 1, 3), rvec,
                              T_cw[:3, 3], calib.K, calib.dist)
    return uv.reshape(-1, 2)
