"""The synthetic camera as ground truth: its pictures, and the registration recovered from them.

Oracles: the camera's own exact pose and intrinsics (world = map for the simulator), exact
polygon areas and centroids for the marker warp, and plain pixel statistics for the
imaging effects. Registration and tracking use the real detector and pose code.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from slamlens.common.geometry import T_from_pose2, invert_T, rotation_angle_deg, wrap_angle
from slamlens.common.messages import Truth
from slamlens.services.registration.calibration import synthetic_calibration
from slamlens.services.registration.markers import MarkerDetector
from slamlens.services.registration.synthetic import (
    WALL_BGR,
    ImagingSettings,
    SceneSettings,
    SyntheticCamera,
    arena_centre,
    fit_hfov_deg,
    look_at,
    orbit_pose,
    overhead_pose,
    robot_marker_corners_world,
    stereo_poses,
    warp_quad,
)
from slamlens.services.registration.tracking import Registrar, RegistrarSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

W, H = 1280, 720
MM, DEG = 5e-3, 0.5  # acceptance: registration within 5 mm and 0.5°
SCENE = SceneSettings()
OFFSET = SCENE.marker_offset_xyz
REALISTIC = ImagingSettings(noise_sigma=2.0, blur_kernel=3)


@pytest.fixture(scope="module")
def paper_truths() -> list[Truth]:
    sim = Simulator(load_world("paper"), seed=1)
    return [e for e in sim.events() if isinstance(e, Truth)]


def overhead_camera(*, imaging: ImagingSettings = REALISTIC, yaw_deg: float = 8.0,
                    scene: SceneSettings = SCENE) -> SyntheticCamera:
    hfov = fit_hfov_deg(W, H, arena_xy=scene.arena_xy, height_m=3.0)
    calib = synthetic_calibration(W, H, hfov_deg=hfov)
    T = overhead_pose(centre_xy=arena_centre(scene.arena_xy), height_m=3.0, yaw_deg=yaw_deg)
    return SyntheticCamera(calib.K, W, H, T_world_from_camera=T, scene=scene, imaging=imaging)


def calib_of(camera: SyntheticCamera):
    from slamlens.services.registration.calibration import CameraCalibration

    return CameraCalibration(K=camera.K, dist=np.zeros(5), width=W, height=H)


def pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    return (float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])),
            rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3]))


# --- geometry of the views -------------------------------------------------------------------


def test_overhead_view_sees_the_whole_arena_looking_straight_down() -> None:
    cam = overhead_camera()
    x0, y0, x1, y1 = SCENE.arena_xy
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)
    uv = cam.project(corners)
    assert np.all(uv >= 0) and np.all(uv[:, 0] < W) and np.all(uv[:, 1] < H)
    # optical axis = −z of the world, camera 3 m above the arena centre
    T = cam.T_world_from_camera
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.5, 0.5, 3.0])
    # the arena centre projects to the principal point
    np.testing.assert_allclose(cam.project(np.array([[0.5, 0.5, 0.0]]))[0], cam.K[:2, 2],
                               atol=1e-9)


def test_look_at_orbit_and_stereo_poses() -> None:
    T = look_at((3.0, 0.0, 2.0), (0.0, 0.0, 0.0))
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    z_c = T[:3, 2]
    np.testing.assert_allclose(z_c, np.array([-3.0, 0.0, -2.0]) / math.sqrt(13), atol=1e-12)
    assert T[2, 1] < 0  # image down points towards the world's down
    T_orbit = orbit_pose(15.0, centre_xy=(0.5, 0.5), radius_m=3.0, height_m=2.5, period_s=60.0)
    # a quarter period after the start on the −y side: on the +x side of the centre
    np.testing.assert_allclose(T_orbit[:3, 3], [3.5, 0.5, 2.5], atol=1e-9)
    left, right = stereo_poses(T_orbit, 0.065)
    np.testing.assert_allclose(np.linalg.norm(left[:3, 3] - right[:3, 3]), 0.065)
    np.testing.assert_allclose(invert_T(left)[:3, :3] @ (right[:3, 3] - left[:3, 3]),
                               [0.065, 0.0, 0.0], atol=1e-12)  # along the camera's own x


def test_sky_above_the_horizon_is_wall() -> None:
    cam = SyntheticCamera(np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]), 640,
                          480, T_world_from_camera=look_at((0, -5, 1.0), (0, 5, 1.0)),
                          imaging=ImagingSettings())
    image = cam.render(robot_pose=None)
    assert tuple(image[5, 320]) == WALL_BGR  # looking level: the top half is above the horizon
    assert tuple(image[470, 320]) != WALL_BGR


# --- the marker is where the projection says -------------------------------------------------


@pytest.mark.parametrize("angle_deg", [0.0, 23.0, 61.0])
def test_warp_quad_preserves_area_and_centroid_of_the_quad(angle_deg: float) -> None:
    """Oracle: a black square warped onto white darkens exactly its polygon's area, centred
    on its centroid (shoelace formula), whatever its sub-pixel position and rotation."""
    src = np.zeros((64, 64, 4), np.uint8)
    src[:, :, 3] = 255
    a = math.radians(angle_deg)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 13.7 @ R.T + [70.31, 52.77]
    image = np.full((120, 140, 3), 255, np.uint8)
    warp_quad(image, src, quad)
    dark = 1.0 - image[:, :, 0].astype(float) / 255.0
    x, y = quad[:, 0], quad[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert dark.sum() == pytest.approx(area, rel=5e-3)
    v, u = np.mgrid[0:120, 0:140]
    centroid = np.array([(dark * u).sum(), (dark * v).sum()]) / dark.sum()
    np.testing.assert_allclose(centroid, quad.mean(axis=0), atol=0.02)


def test_detected_marker_corners_match_the_projected_corners() -> None:
    cam = overhead_camera(imaging=ImagingSettings())
    detector = MarkerDetector(SCENE.dictionary)
    rng = np.random.default_rng(3)
    for k in range(6):
        pose = (rng.uniform(-0.8, 1.8), rng.uniform(-0.8, 1.8), rng.uniform(-math.pi, math.pi))
        image = cam.render(robot_pose=pose, frame_index=k)
        (det,) = [d for d in detector.detect(image) if d.marker_id == SCENE.marker_id]
        true = cam.project(robot_marker_corners_world(pose, size_m=SCENE.marker_size_m,
                                                      offset_xyz=OFFSET))
        np.testing.assert_allclose(det.corners_px, true, atol=0.1)


# --- registration and tracking against the synthetic truth ------------------------------------


def register(cam: SyntheticCamera, truth: Truth, *, frames: int = 5) -> Registrar:
    registrar = Registrar(RegistrarSettings(SCENE.marker_id, SCENE.marker_size_m, OFFSET),
                          calib_of(cam))
    detector = MarkerDetector(SCENE.dictionary)
    for k in range(frames):
        image = cam.render(robot_pose=truth.pose, landmarks_xy=truth.landmarks, frame_index=k)
        registrar.observe(truth.stamp, detector.detect(image), T_anchor_from_camera=np.eye(4))
    return registrar


@pytest.mark.parametrize("imaging", [
    REALISTIC,
    ImagingSettings(),
    ImagingSettings(noise_sigma=3.0, blur_kernel=5, gain=0.7, offset=15.0, gradient=0.4),
], ids=["realistic", "clean", "dim-gradient-blurred"])
def test_registration_recovers_the_true_camera_from_map(paper_truths: list[Truth],
                                                       imaging: ImagingSettings) -> None:
    start = paper_truths[0]
    np.testing.assert_allclose(start.pose, [0, 0, 0])  # the map frame is the start pose
    cam = overhead_camera(imaging=imaging)
    registrar = register(cam, start)
    assert registrar.registered and registrar.registrations == 1
    dt, dr = pose_error(registrar.T_anchor_from_map, cam.true_T_camera_from_world())
    assert dt < MM and dr < DEG, (dt, dr)
    assert registrar.reprojection_error_px < 0.5


def test_registration_of_a_robot_not_at_the_world_origin() -> None:
    """Map frame = wherever the robot starts: T_camera_from_map = T_camera_from_world ·
    T_world_from_start."""
    cam = overhead_camera()
    start = np.array([0.9, -0.4, 2.2])
    truth = Truth(robot="r", stamp=0.0, pose=start, landmark_ids=np.zeros(0, np.int64),
                  landmarks=np.zeros((0, 2)))
    registrar = register(cam, truth)
    expected = cam.true_T_camera_from_world() @ T_from_pose2(start)
    dt, dr = pose_error(registrar.T_anchor_from_map, expected)
    assert dt < MM and dr < DEG, (dt, dr)


def test_tracked_pose_follows_the_whole_simulated_run(paper_truths: list[Truth]) -> None:
    cam = overhead_camera()
    registrar = register(cam, paper_truths[0])
    detector = MarkerDetector(SCENE.dictionary)
    position, heading = [], []
    run = paper_truths[1::4]  # every 0.4 s of the three loops
    for k, truth in enumerate(run):
        image = cam.render(robot_pose=truth.pose, landmarks_xy=truth.landmarks,
                           frame_index=100 + k)
        result = registrar.observe(truth.stamp, detector.detect(image),
                                   T_anchor_from_camera=np.eye(4))
        assert result.tracked_pose is not None, f"marker lost at t = {truth.stamp}"
        position.append(np.linalg.norm(result.tracked_pose[:2] - truth.pose[:2]))
        heading.append(abs(wrap_angle(result.tracked_pose[2] - truth.pose[2])))
    assert len(run) > 130
    assert max(position) < 0.01, max(position)
    assert math.degrees(max(heading)) < 1.0


def test_moving_camera_registration_from_the_board_follows_the_camera(
        paper_truths: list[Truth]) -> None:
    """Head-mounted: camera pose from the world markers each frame; T_camera_from_map must
    follow the true moving camera (world = map)."""
    from slamlens.services.registration.board import camera_pose_from_board, default_board
    from slamlens.services.registration.synthetic import WorldMarker

    board = default_board()
    markers = [WorldMarker(m.marker_id, board.corners_in_world(m.marker_id))
               for m in board.markers]
    calib = synthetic_calibration(W, H, hfov_deg=75.0)
    cam = SyntheticCamera(calib.K, W, H, T_world_from_camera=np.eye(4), imaging=REALISTIC,
                          board=markers)
    registrar = Registrar(RegistrarSettings(SCENE.marker_id, SCENE.marker_size_m, OFFSET,
                                            moving_camera=True), calib)
    detector = MarkerDetector(SCENE.dictionary)
    start = paper_truths[0]
    errors = []
    for k in range(12):
        T_true = orbit_pose(2.0 * k, centre_xy=(0.5, 0.5))
        image = cam.render(robot_pose=start.pose, T_world_from_camera=T_true, frame_index=k)
        detections = detector.detect(image)
        found = camera_pose_from_board(detections, board, calib)
        assert found is not None
        result = registrar.observe(float(k), detections, T_anchor_from_camera=found[0])
        if k >= 5:
            assert result.status == "tracking" and result.T_camera_from_map is not None
            errors.append(pose_error(result.T_camera_from_map, invert_T(T_true)))
    assert max(e[0] for e in errors) < 0.02 and max(e[1] for e in errors) < DEG, errors


# --- determinism and imaging effects ---------------------------------------------------------


def test_frames_are_deterministic_for_a_seed() -> None:
    a, b = overhead_camera(), overhead_camera()
    pose = (0.3, 0.2, 0.5)
    np.testing.assert_array_equal(a.render(robot_pose=pose, frame_index=4),
                                  b.render(robot_pose=pose, frame_index=4))
    assert not np.array_equal(a.render(robot_pose=pose, frame_index=4),
                              a.render(robot_pose=pose, frame_index=5))  # fresh sensor noise
    other = overhead_camera(scene=SceneSettings(seed=1))
    assert not np.array_equal(a.render(robot_pose=pose, frame_index=4),
                              other.render(robot_pose=pose, frame_index=4))


def test_only_the_robot_changes_between_frames_of_a_still_scene() -> None:
    cam = overhead_camera(imaging=ImagingSettings())
    lms = np.array([[1.5, 1.5], [-0.5, 1.2]])
    first = cam.render(robot_pose=(0.0, 0.0, 0.0), landmarks_xy=lms)
    second = cam.render(robot_pose=(1.0, 1.0, 1.0), landmarks_xy=lms)
    changed = np.any(first != second, axis=2)
    ys, xs = np.nonzero(changed)
    robots = cam.project(np.array([[0.0, 0.0, 0.1], [1.0, 1.0, 0.1]]))
    radius_px = 0.4 / 2.8 * cam.K[0, 0]  # body radius + perspective lean, seen from 2.8 m
    near = np.min(np.hypot(xs[:, None] - robots[:, 0], ys[:, None] - robots[:, 1]), axis=1)
    assert changed.any() and np.all(near < radius_px)


def test_noise_blur_and_lighting_change_pixels_as_configured() -> None:
    pose = (0.2, 0.1, 0.3)
    clean = overhead_camera(imaging=ImagingSettings()).render(robot_pose=pose).astype(float)

    noisy = overhead_camera(imaging=ImagingSettings(noise_sigma=4.0)).render(robot_pose=pose)
    residual = noisy.astype(float) - clean
    assert residual.std() == pytest.approx(4.0, rel=0.05)
    assert abs(residual.mean()) < 0.1

    blurred = overhead_camera(imaging=ImagingSettings(blur_kernel=7)).render(robot_pose=pose)

    def sharpness(img: np.ndarray) -> float:
        return float(cv2.Laplacian(cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_BGR2GRAY),
                                   cv2.CV_64F).var())
    assert sharpness(blurred) < 0.5 * sharpness(clean)
    assert blurred.astype(float).mean() == pytest.approx(clean.mean(), rel=0.01)

    dim = overhead_camera(imaging=ImagingSettings(gain=0.6)).render(robot_pose=pose)
    assert dim.astype(float).mean() / clean.mean() == pytest.approx(0.6, rel=0.01)

    bright = overhead_camera(imaging=ImagingSettings(offset=20.0)).render(robot_pose=pose)
    unsaturated = clean < 230
    assert (bright.astype(float) - clean)[unsaturated].mean() == pytest.approx(20.0, abs=0.5)

    ramp = overhead_camera(imaging=ImagingSettings(gradient=0.5)).render(robot_pose=pose)
    ratio = ramp.astype(float) / np.maximum(clean, 1.0)
    left, right = ratio[:, :40].mean(), ratio[:, -40:].mean()
    assert left == pytest.approx(0.75 + 0.5 * 20 / W, abs=0.02)
    assert right == pytest.approx(1.25 - 0.5 * 20 / W, abs=0.02)


def test_stereo_frames_differ_by_the_baseline_parallax() -> None:
    left_T, right_T = stereo_poses(overhead_pose(centre_xy=(0.5, 0.5), height_m=3.0), 0.1)
    cam = overhead_camera(imaging=ImagingSettings())
    point = np.array([[0.0, 0.0, OFFSET[2]]])
    u_left = cam.project(point, T_world_from_camera=left_T)[0]
    u_right = cam.project(point, T_world_from_camera=right_T)[0]
    # disparity = f·B / depth, along image x only
    np.testing.assert_allclose(u_left - u_right, [cam.K[0, 0] * 0.1 / (3.0 - OFFSET[2]), 0.0],
                               atol=1e-9)
    assert not np.array_equal(cam.render(robot_pose=(0, 0, 0), T_world_from_camera=left_T),
                              cam.render(robot_pose=(0, 0, 0), T_world_from_camera=right_T))


def test_robot_marker_corners_follow_spec_orientation() -> None:
    """protocol.md: marker x = robot forward, marker y = robot left; TL corner = (−s/2, +s/2)."""
    corners = robot_marker_corners_world((1.0, 2.0, math.pi / 2), size_m=0.2,
                                         offset_xyz=(0.1, 0.0, 0.3))
    # robot faces +y: marker centre 0.1 m ahead, marker x → world +y, marker y → world −x
    np.testing.assert_allclose(corners.mean(axis=0), [1.0, 2.1, 0.3], atol=1e-12)
    np.testing.assert_allclose(corners[0], [1.0 - 0.1, 2.1 - 0.1, 0.3], atol=1e-12)  # TL
    np.testing.assert_allclose(corners[1], [1.0 - 0.1, 2.1 + 0.1, 0.3], atol=1e-12)  # TR


def test_deploy_calibration_file_is_the_default_synthetic_camera() -> None:
    from pathlib import Path

    from slamlens.services.registration.assemble import calibration_for
    from slamlens.services.registration.calibration import load_calibration
    from slamlens.services.registration.settings import RegistrationSettings

    path = Path(__file__).resolve().parents[2] / "deploy" / "calibration_synthetic_1280x720.yml"
    assert load_calibration(path) == calibration_for(RegistrationSettings())
