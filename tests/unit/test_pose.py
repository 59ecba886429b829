"""Marker detection, marker pose, the registration chain and the board pose, on views
rendered with known poses (services/harness/marker_render.py: the oracle is the pose we render
with), plus hand-computed transforms."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.errors import ConfigError, GeometryError, SourceError
from slamlens.common.geometry import T_from_pose2, invert_T, make_T, rot_z, rotation_angle_deg
from slamlens.services.harness.marker_render import PlacedMarker, look_at, render, true_corners
from slamlens.services.registration import markers
from slamlens.services.registration.board import (
    BoardMarker,
    MarkerBoard,
    camera_pose_from_board,
    default_board,
    load_board,
    rotation_from_rpy_deg,
)
from slamlens.services.registration.calibration import CameraCalibration, synthetic_calibration
from slamlens.services.registration.markers import (
    DICTIONARIES,
    Detection,
    DetectorTuning,
    MarkerDetector,
    mean_detection,
    refine_corners_edges,
)
from slamlens.services.registration.pose import (
    PoseError,
    T_camera_from_map,
    T_marker_from_map,
    marker_object_points,
    marker_pose,
    project_points,
    robot_pose_from_marker,
)

CALIB = synthetic_calibration(1280, 720, hfov_deg=60.0)
MM, DEG = 0.005, 0.5  # the acceptance bounds: 5 mm and 0.5°


def rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def facing_camera(*, distance: float, tilt_deg: float, yaw_deg: float,
                  offset_xy: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """T_camera_from_marker: the marker face towards the camera (marker z ≈ −camera z),
    turned by yaw about its normal and tilted by tilt about its x axis."""
    R = rot_x(math.pi) @ rot_z(math.radians(yaw_deg)) @ rot_x(math.radians(tilt_deg))
    return make_T(R, np.array([offset_xy[0], offset_xy[1], distance]))


def pose_error(T_estimate: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error degrees)."""
    return (float(np.linalg.norm(T_estimate[:3, 3] - T_true[:3, 3])),
            rotation_angle_deg(T_estimate[:3, :3].T @ T_true[:3, :3]))


# --- marker frame -----------------------------------------------------------------------------

def test_marker_object_points_follow_opencvs_square_layout() -> None:
    pts = marker_object_points(0.2)
    np.testing.assert_array_equal(pts, [[-0.1, 0.1, 0], [0.1, 0.1, 0], [0.1, -0.1, 0],
                                        [-0.1, -0.1, 0]])
    with pytest.raises(PoseError):
        marker_object_points(0.0)


def test_detection_order_is_top_left_first_of_the_marker_image() -> None:
    T = facing_camera(distance=1.0, tilt_deg=0.0, yaw_deg=0.0)
    placed = PlacedMarker(7, T, 0.15)
    (det,) = MarkerDetector().detect(render(CALIB, [placed]))
    assert det.marker_id == 7
    truth = true_corners(placed, CALIB.K)
    # marker upright in the picture: corner 0 top-left, 1 top-right, 2 bottom-right
    assert truth[0, 0] < truth[1, 0] and truth[0, 1] < truth[3, 1]
    np.testing.assert_allclose(det.corners_px, truth, atol=0.3)


# --- detection accuracy and marker pose on rendered views -------------------------------------

VIEWS = [  # distance m, tilt °, yaw °, lateral offset m
    (0.8, 0.0, 10.0, (0.05, -0.02)),
    (1.5, 35.0, -40.0, (0.2, 0.1)),
    (2.2, 50.0, 120.0, (-0.4, 0.2)),
    (3.0, 20.0, 200.0, (0.6, -0.3)),
]
FACE_ON_FAR = (3.0, 0.0, 45.0, (0.0, 0.0))  # one noisy frame is not enough: see below


@pytest.mark.parametrize(("distance", "tilt", "yaw", "offset", "noisy"),
                         [(*v, n) for v in VIEWS for n in (False, True)] + [(*FACE_ON_FAR, False)])
def test_marker_pose_recovers_the_rendered_pose(distance: float, tilt: float, yaw: float,
                                                offset: tuple[float, float], noisy: bool) -> None:
    T_true = facing_camera(distance=distance, tilt_deg=tilt, yaw_deg=yaw, offset_xy=offset)
    placed = PlacedMarker(3, T_true, 0.2)
    image = render(CALIB, [placed], blur_sigma_px=0.8 if noisy else 0.0,
                   noise_sigma=3.0 if noisy else 0.0, seed=int(distance * 10 + abs(yaw)))
    (det,) = MarkerDetector().detect(image)
    np.testing.assert_allclose(det.corners_px, true_corners(placed, CALIB.K), atol=0.3)
    T, rms = marker_pose(det, size_m=0.2, calib=CALIB)
    dt, dr = pose_error(T, T_true)
    assert dt < MM and dr < DEG, (dt, dr)
    assert rms < 0.3


def test_face_on_far_marker_pose_from_a_few_averaged_frames() -> None:
    """A 0.2 m marker face-on at 3 m: a 1° tilt moves its corners by ~0.1 px, so with image
    noise one frame's tilt is only good to ~1° (translation stays at mm). The corner-wise mean
    of 8 frames of the still camera brings it within the 0.5° bound."""
    distance, tilt, yaw, offset = FACE_ON_FAR
    for trial in range(3):
        T_true = facing_camera(distance=distance, tilt_deg=tilt, yaw_deg=yaw + 17 * trial,
                               offset_xy=offset)
        placed = PlacedMarker(3, T_true, 0.2)
        frames = [MarkerDetector().detect(render(CALIB, [placed], blur_sigma_px=0.8,
                                                 noise_sigma=3.0, seed=100 * trial + f))[0]
                  for f in range(8)]
        T, _ = marker_pose(mean_detection(frames), size_m=0.2, calib=CALIB)
        dt, dr = pose_error(T, T_true)
        assert dt < MM and dr < DEG, (trial, dt, dr)
    with pytest.raises(GeometryError, match="one marker id"):
        mean_detection([frames[0], Detection(4, frames[0].corners_px)])


def test_edges_refinement_beats_opencvs_on_rendered_views() -> None:
    errors: dict[str, list[float]] = {}
    for k, (distance, tilt, yaw, offset) in enumerate(VIEWS):
        placed = PlacedMarker(3, facing_camera(distance=distance, tilt_deg=tilt, yaw_deg=yaw,
                                               offset_xy=offset), 0.2)
        image = render(CALIB, [placed], blur_sigma_px=0.8, noise_sigma=3.0, seed=k)
        truth = true_corners(placed, CALIB.K)
        for refinement in ("edges", "subpix", "apriltag", "none"):
            (det,) = MarkerDetector(params=DetectorTuning(corner_refinement=refinement)).detect(
                image)
            errors.setdefault(refinement, []).extend(
                np.linalg.norm(det.corners_px - truth, axis=1))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errors.items()}
    assert rms["edges"] < 0.15, rms
    assert all(rms["edges"] < rms[k] for k in ("subpix", "apriltag", "none")), rms


def test_downscaled_search_keeps_full_resolution_accuracy() -> None:
    placed = [PlacedMarker(i, facing_camera(distance=2.5, tilt_deg=15.0, yaw_deg=30.0 * i,
                                            offset_xy=(-0.6 + 0.4 * i, 0.1)), 0.2)
              for i in range(4)]
    image = render(CALIB, placed, blur_sigma_px=0.7, noise_sigma=2.0)
    found = MarkerDetector(params=DetectorTuning(downscale=2.0)).detect(image)
    assert [d.marker_id for d in found] == [0, 1, 2, 3]
    for det, p in zip(found, placed, strict=True):
        np.testing.assert_allclose(det.corners_px, true_corners(p, CALIB.K), atol=0.3)


def test_edge_refinement_keeps_corners_it_cannot_improve(monkeypatch) -> None:
    corners = np.array([[[100.0, 100.0], [140.0, 100.0], [140.0, 140.0], [100.0, 140.0]]])
    blank = np.full((240, 320), 128, np.uint8)  # no edge anywhere: nothing to fit
    np.testing.assert_array_equal(refine_corners_edges(blank, corners), corners)
    # the remap is done in row chunks for many markers: chunking must not change results
    placed = PlacedMarker(5, facing_camera(distance=1.2, tilt_deg=30.0, yaw_deg=20.0), 0.15)
    image = render(CALIB, [placed], noise_sigma=2.0)
    whole = MarkerDetector().detect(image)
    monkeypatch.setattr(markers, "_REMAP_MAX_ROWS", 7)
    np.testing.assert_array_equal(MarkerDetector().detect(image)[0].corners_px,
                                  whole[0].corners_px)


def test_marker_pose_survives_ippes_nan_solution() -> None:
    """Raw integer corners of a marker face-up under an 84° camera for which OpenCV 5's
    IPPE_SQUARE returns one NaN solution (found by benchmarks/bench_detection.py)."""
    calib = synthetic_calibration(1280, 720, hfov_deg=84.0)
    det = Detection(2, [[954.0, 307.0], [968.0, 347.0], [928.0, 361.0], [914.0, 321.0]])
    T, rms = marker_pose(det, size_m=0.1664865858249546, calib=calib)
    assert np.all(np.isfinite(T)) and 2.5 < T[2, 3] < 3.0 and rms < 1.0
    assert T[2, 2] < 0.0  # the face, not the back, towards the camera


def test_marker_pose_rejects_bad_corners() -> None:
    nan = Detection(1, np.full((4, 2), np.nan))
    with pytest.raises(PoseError, match="non-finite"):
        marker_pose(nan, size_m=0.1, calib=CALIB)


# --- the registration chain, by hand ------------------------------------------------------

def test_T_marker_from_map_by_hand() -> None:
    T = T_marker_from_map((0.1, -0.05, 0.3))
    np.testing.assert_allclose(T, make_T(np.eye(3), [-0.1, 0.05, -0.3]), atol=1e-15)
    # robot at (1, 2) facing +y: the marker centre is at (1 + 0.05, 2 + 0.1, 0.3) in the map,
    # marker axes = robot axes = Rz(90°); the inverse is R = Rz(−90°), t = −Rᵀ·c
    T = T_marker_from_map((0.1, -0.05, 0.3), robot_pose_in_map=(1.0, 2.0, math.pi / 2))
    expected = np.array([[0.0, 1.0, 0.0, -2.1], [-1.0, 0.0, 0.0, 1.05],
                         [0.0, 0.0, 1.0, -0.3], [0.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(T, expected, atol=1e-12)


def overhead_T_camera_from_map(x: float, y: float, height: float) -> np.ndarray:
    """Camera at (x, y, height) looking straight down, image right = map +x, image down =
    map −y: R_map_from_camera = diag(1, −1, −1), so T_camera_from_map by hand is below."""
    return np.array([[1.0, 0.0, 0.0, -x], [0.0, -1.0, 0.0, y], [0.0, 0.0, -1.0, height],
                     [0.0, 0.0, 0.0, 1.0]])


def test_T_camera_from_map_composition_by_hand() -> None:
    expected = overhead_T_camera_from_map(0.5, 0.5, 3.0)
    # marker centre at (0.05, 0, 0.2) in the map → camera (−0.45, 0.5, 2.8); axes diag(1,−1,−1)
    T_camera_from_marker = make_T(np.diag([1.0, -1.0, -1.0]), [-0.45, 0.5, 2.8])
    np.testing.assert_allclose(T_camera_from_map(T_camera_from_marker, (0.05, 0.0, 0.2)),
                               expected, atol=1e-12)


def test_registration_end_to_end_on_an_overhead_view() -> None:
    offset = (0.05, 0.0, 0.25)
    T_cam_map = overhead_T_camera_from_map(0.5, 0.5, 3.0)
    T_cam_marker = T_cam_map @ invert_T(T_marker_from_map(offset))
    image = render(CALIB, [PlacedMarker(0, T_cam_marker, 0.2)], blur_sigma_px=0.6,
                   noise_sigma=2.0)
    (det,) = MarkerDetector().detect(image)
    T, _ = marker_pose(det, size_m=0.2, calib=CALIB)
    dt, dr = pose_error(T_camera_from_map(T, offset), T_cam_map)
    assert dt < MM and dr < DEG, (dt, dr)


def test_robot_pose_from_marker_inverts_the_chain() -> None:
    rng = np.random.default_rng(4)
    T_cam_map = overhead_T_camera_from_map(0.5, 0.5, 3.0) @ make_T(rot_z(0.3), [0.1, 0, 0])
    offset = (0.07, -0.03, 0.25)
    for _ in range(20):
        pose = np.array([rng.uniform(-1, 2), rng.uniform(-1, 2), rng.uniform(-math.pi, math.pi)])
        T_cam_marker = T_cam_map @ T_from_pose2(pose) @ invert_T(T_marker_from_map(offset))
        np.testing.assert_allclose(robot_pose_from_marker(T_cam_marker, T_cam_map, offset),
                                   pose, atol=1e-9)


def test_tracked_robot_pose_from_a_rendered_view() -> None:
    offset = (0.05, 0.0, 0.25)
    T_cam_map = overhead_T_camera_from_map(0.5, 0.5, 3.0)
    pose = np.array([1.1, 0.1, 2.5])
    T_cam_marker = T_cam_map @ T_from_pose2(pose) @ invert_T(T_marker_from_map(offset))
    image = render(CALIB, [PlacedMarker(0, T_cam_marker, 0.2)], blur_sigma_px=0.6,
                   noise_sigma=2.0, seed=9)
    (det,) = MarkerDetector().detect(image)
    T, _ = marker_pose(det, size_m=0.2, calib=CALIB)
    measured = robot_pose_from_marker(T, T_cam_map, offset)
    assert np.linalg.norm(measured[:2] - pose[:2]) < MM
    assert abs(math.degrees(measured[2] - pose[2])) < DEG


def brown_conrady(points_camera: np.ndarray, calib: CameraCalibration) -> np.ndarray:
    """OpenCV's 5-term distortion model written out (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = calib.dist
    x = points_camera[:, 0] / points_camera[:, 2]
    y = points_camera[:, 1] / points_camera[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([calib.fx * xd + calib.cx, calib.fy * yd + calib.cy])


def test_project_points_with_distortion_and_behind_the_camera() -> None:
    calib = CameraCalibration(K=CALIB.K, dist=np.array([0.1, -0.2, 0.001, -0.002, 0.05]),
                              width=1280, height=720)
    T_cam_map = overhead_T_camera_from_map(0.5, 0.5, 3.0)
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-1, 2, 30), rng.uniform(-1, 2, 30),
                              rng.uniform(0, 0.5, 30)])
    camera = points @ T_cam_map[:3, :3].T + T_cam_map[:3, 3]
    np.testing.assert_allclose(project_points(points, T_camera_from_map=T_cam_map, calib=calib),
                               brown_conrady(camera, calib), atol=1e-6)
    behind = project_points(np.array([[0.5, 0.5, 3.5], [0.5, 0.5, 1.0]]),
                            T_camera_from_map=T_cam_map, calib=calib)
    assert np.all(np.isnan(behind[0])) and np.all(np.isfinite(behind[1]))
    assert project_points(np.zeros((0, 3)), T_camera_from_map=T_cam_map, calib=calib).shape == (
        0, 2)


# --- the board of world markers (head-mounted camera) ---------------------------------------

WIDE = synthetic_calibration(1280, 720, hfov_deg=90.0)  # a head-mounted camera's lens


def _view_of_board(board: MarkerBoard, T_world_from_camera: np.ndarray, **kw) -> np.ndarray:
    T_camera_from_world = invert_T(T_world_from_camera)
    placed = [PlacedMarker(m.marker_id, T_camera_from_world @ m.T_world_from_marker,
                           board.marker_size_m) for m in board.markers]
    return render(WIDE, placed, **kw)


@pytest.mark.parametrize(("camera_at", "n_seen"), [
    ((0.5, -2.0, 2.0), 4), ((-2.0, 0.5, 1.8), 4), ((3.5, 3.0, 2.0), 3), ((0.5, 0.5, 3.5), 4)])
def test_camera_pose_from_board_recovers_the_rendered_camera(camera_at: tuple,
                                                             n_seen: int) -> None:
    board = default_board()
    up = (0.0, 1.0, 0.0) if camera_at[:2] == (0.5, 0.5) else (0.0, 0.0, 1.0)
    T_true = look_at(camera_at, (0.5, 0.5, 0.0), up=up)
    image = _view_of_board(board, T_true, blur_sigma_px=0.6, noise_sigma=2.0)
    result = camera_pose_from_board(MarkerDetector().detect(image), board, WIDE)
    assert result is not None
    T, rms, used = result
    assert used == n_seen and rms < 0.3
    dt, dr = pose_error(T, T_true)
    assert dt < MM and dr < DEG, (dt, dr)


def test_camera_pose_from_one_board_marker_and_from_none() -> None:
    board = default_board()
    T_true = look_at((-0.7, -0.9, 1.0), (-1.0, -1.0, 0.0))  # close over marker 10 only
    detections = MarkerDetector().detect(_view_of_board(board, T_true))
    assert [d.marker_id for d in detections] == [10]
    result = camera_pose_from_board(detections, board, WIDE)
    assert result is not None and result[2] == 1
    dt, dr = pose_error(result[0], T_true)
    assert dt < MM and dr < DEG, (dt, dr)
    assert camera_pose_from_board([], board, CALIB) is None
    stray = Detection(99, detections[0].corners_px)  # not a board id
    assert camera_pose_from_board([stray], board, CALIB) is None
    twice = [detections[0], Detection(10, detections[0].corners_px + 40.0)]
    assert camera_pose_from_board(twice, board, CALIB) is None  # ambiguous: left out


def test_board_from_toml(tmp_path: Path) -> None:
    path = tmp_path / "board.toml"
    path.write_text('dictionary = "aruco_4x4_50"\nmarker_size_m = 0.1\n'
                    "[[markers]]\nid = 3\nposition_m = [1.0, 2.0, 0.5]\n"
                    "rpy_deg = [90.0, 0.0, 0.0]\n"
                    "[[markers]]\nid = 4\nposition_m = [0.0, 0.0, 0.0]\n")
    board = load_board(path)
    assert board.ids == (3, 4) and board.dictionary == "aruco_4x4_50"
    # roll 90°: marker y (up its image) becomes world z, its face looks along world −y
    expected = np.array([[0.95, 2.0, 0.55], [1.05, 2.0, 0.55], [1.05, 2.0, 0.45],
                         [0.95, 2.0, 0.45]])
    np.testing.assert_allclose(board.corners_in_world(3), expected, atol=1e-12)
    np.testing.assert_allclose(rotation_from_rpy_deg((0, 0, 90)), rot_z(math.pi / 2), atol=1e-12)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("marker_size_m = 0.1\ncolour = 1\n[[markers]]\nid = 1\nposition_m = [0,0,0]\n",
         "colour"),
        ("marker_size_m = 0.1\n[[markers]]\nid = 1\nposition_m = [0,0]\n", "position_m"),
        ("marker_size_m = 0.1\n[[markers]]\nid = 1\nposition_m = [0,0,0]\nsize = 2\n", "size"),
        ("marker_size_m = 0.1\n[[markers]]\nid = 1\nposition_m = [0,0,0]\n"
         "[[markers]]\nid = 1\nposition_m = [1,0,0]\n", "repeat"),
        ('dictionary = "qr"\nmarker_size_m = 0.1\n[[markers]]\nid = 1\nposition_m = [0,0,0]\n',
         "apriltag_36h11"),
        ("marker_size_m = 0.1\n", "markers"),
        ("marker_size_m = [\n", "not valid TOML"),
    ],
)
def test_bad_board_files_name_the_problem(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "board.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_board(path)


def test_default_board_is_four_markers_on_the_arena_corners() -> None:
    board = default_board()
    assert board.ids == (10, 11, 12, 13) and board.dictionary == "apriltag_36h11"
    centres = [board.marker(i).T_world_from_marker[:3, 3] for i in board.ids]
    np.testing.assert_array_equal(centres, [[-1, -1, 0], [2, -1, 0], [2, 2, 0], [-1, 2, 0]])
    with pytest.raises(ConfigError, match="rigid"):
        BoardMarker(1, np.diag([2.0, 1.0, 1.0, 1.0]))


# --- detector configuration and bad input -------------------------------------------------

def test_dictionary_names_and_errors(tmp_path: Path) -> None:
    assert "apriltag_36h11" in DICTIONARIES and "aruco_6x6_250" in DICTIONARIES
    with pytest.raises(ConfigError, match="aruco_4x4_50.*apriltag_36h11|apriltag_36h11"):
        MarkerDetector("apriltag_99h1")
    with pytest.raises(ConfigError, match="does not exist"):
        MarkerDetector(custom_dictionary_path=str(tmp_path / "none.yml"))
    with pytest.raises(ConfigError, match="corner_refinement"):
        MarkerDetector(params=DetectorTuning(corner_refinement="magic"))


def test_detector_input_handling() -> None:
    detector = MarkerDetector()
    assert detector.detect(np.full((120, 160), 128, np.uint8)) == []
    assert detector.detect(np.full((120, 160, 3), 128, np.uint8)) == []
    assert detector.detect(np.full((120, 160, 4), 128, np.uint8)) == []
    with pytest.raises(SourceError, match="uint8"):
        detector.detect(np.zeros((120, 160), np.float32))
    with pytest.raises(SourceError, match="shape"):
        detector.detect(np.zeros((120, 160, 2), np.uint8))
