"""CameraModel: pinhole by hand, distortion against cv2.projectPoints, views it builds."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slamlens.common.errors import CalibrationError
from slamlens.common.geometry import make_T, rot_z
from slamlens.common.messages import Registration
from slamlens.services.visualiser.camera_model import CameraModel

K = np.array([[800.0, 0.0, 640.0], [0.0, 780.0, 360.0], [0.0, 0.0, 1.0]])


def oblique_T(tilt_rad: float = 0.5, yaw_rad: float = 0.3, eye=(0.2, -2.0, 2.5)) -> np.ndarray:
    """T_camera_from_map of a camera above the floor, tilted, looking roughly at the origin."""
    Rx = np.array([[1, 0, 0], [0, np.cos(-tilt_rad), -np.sin(-tilt_rad)],
                   [0, np.sin(-tilt_rad), np.cos(-tilt_rad)]])
    R = Rx @ np.diag([1.0, -1.0, -1.0]) @ rot_z(yaw_rad).T
    return make_T(R, -R @ np.asarray(eye, dtype=float))


def test_pinhole_projection_matches_hand_computation() -> None:
    T = oblique_T()
    cam = CameraModel(K=K, dist=np.zeros(5), width=1280, height=720, T_camera_from_map=T)
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [-0.5, 1.0, 0.3]])
    uv, depth = cam.project(points)
    for p, (u, v), z in zip(points, uv, depth, strict=True):
        X, Y, Z = T[:3, :3] @ p + T[:3, 3]
        assert z == pytest.approx(Z)
        assert u == pytest.approx(800.0 * X / Z + 640.0, abs=1e-9)
        assert v == pytest.approx(780.0 * Y / Z + 360.0, abs=1e-9)


@pytest.mark.parametrize("dist", [
    [-0.28, 0.09, 0.001, -0.002],
    [-0.3, 0.1, 0.001, -0.002, -0.02],
    [0.1, -0.05, 0.001, 0.002, 0.01, 0.05, -0.01, 0.02],
    [0.05, -0.02, 0.001, 0.001, 0.003, 0.01, 0.0, 0.001, 0.002, -0.001, 0.001, 0.0005],
    [0.05, -0.02, 0.001, 0.001, 0.003, 0.01, 0.0, 0.001, 0.002, -0.001, 0.001, 0.0005,
     0.01, -0.02],
])
def test_distorted_projection_matches_opencv(dist: list[float]) -> None:
    rng = np.random.default_rng(len(dist))
    T = oblique_T()
    cam = CameraModel(K=K, dist=np.array(dist), width=1280, height=720, T_camera_from_map=T)
    points = np.column_stack([rng.uniform(-1.0, 1.5, 200), rng.uniform(-0.5, 1.5, 200),
                              rng.uniform(0.0, 0.4, 200)])
    uv, _ = cam.project(points)
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    expected, _ = cv2.projectPoints(points, rvec, T[:3, 3], K, np.array(dist))
    expected = expected.reshape(-1, 2)
    inside = ((expected[:, 0] > 0) & (expected[:, 0] < 1280) & (expected[:, 1] > 0)
              & (expected[:, 1] < 720))
    assert inside.sum() > 100
    np.testing.assert_allclose(uv[inside], expected[inside], atol=1e-6)
    # distort_pixels is the same map applied to undistorted pinhole pixels
    pinhole = CameraModel(K=K, dist=np.zeros(0), width=1280, height=720, T_camera_from_map=T)
    np.testing.assert_allclose(cam.distort_pixels(pinhole.project(points)[0])[inside],
                               expected[inside], atol=1e-6)


def test_points_behind_the_camera_are_flagged() -> None:
    cam = CameraModel(K=K, dist=np.array([-0.2, 0.05, 0, 0, 0]), width=1280, height=720,
                      T_camera_from_map=np.eye(4))
    uv, depth = cam.project(np.array([[0.1, 0.1, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 2.0]]))
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()
    assert depth[0] < 0 and depth[1] == 0 and depth[2] == 2.0


def test_barrel_distortion_does_not_fold_far_points_back_into_the_image() -> None:
    # k1 = −0.5: OpenCV's r·(1 + k1·r²) peaks at r = 0.82 and comes back towards the centre.
    cam = CameraModel(K=K, dist=np.array([-0.5, 0.0, 0.0, 0.0]), width=1280, height=720,
                      T_camera_from_map=np.eye(4))
    xs = np.linspace(0.0, 2.0, 201)
    uv, _ = cam.project(np.column_stack([xs, np.zeros_like(xs), np.ones_like(xs)]))
    assert np.all(np.diff(uv[:, 0]) >= 0)  # monotonic: farther out never lands further in
    rvec = np.zeros(3)
    folded, _ = cv2.projectPoints(np.array([[2.0, 0.0, 1.0]]), rvec, np.zeros(3), K,
                                  np.array([-0.5, 0.0, 0.0, 0.0]))
    assert folded[0, 0, 0] < 640  # OpenCV's polynomial folds it back inside …
    assert uv[-1, 0] > uv[80, 0]  # … ours keeps it beyond the fold


def test_top_down_view_puts_the_bounds_inside_the_image_the_right_way_up() -> None:
    bounds = (-1.0, -1.0, 2.0, 2.0)
    cam = CameraModel.top_down(bounds_xy=bounds, width=1280, height=720, margin=0.15)
    corners = np.array([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [2.0, 2.0, 0.0], [-1.0, 2.0, 0.0]])
    uv, depth = cam.project(corners)
    assert np.all(depth > 0)
    assert np.all((uv[:, 0] > 0) & (uv[:, 0] < 1280) & (uv[:, 1] > 0) & (uv[:, 1] < 720))
    # the margin is kept on the tight side (height): 15 % of the span above and below
    span_v = uv[:, 1].max() - uv[:, 1].min()
    assert uv[:, 1].min() == pytest.approx(720 * 0.15 / 1.3, rel=1e-6)
    assert span_v == pytest.approx(720 / 1.3, rel=1e-6)
    centre, _ = cam.project(np.array([[0.5, 0.5, 0.0]]))
    np.testing.assert_allclose(centre[0], [640.0, 360.0], atol=1e-9)
    # image right = map +x, image up = map +y
    east, _ = cam.project(np.array([[1.5, 0.5, 0.0]]))
    north, _ = cam.project(np.array([[0.5, 1.5, 0.0]]))
    assert east[0, 0] > 640 and east[0, 1] == pytest.approx(360)
    assert north[0, 1] < 360 and north[0, 0] == pytest.approx(640)
    # a higher point (a cone's base) is nearer the camera
    _, depth_high = cam.project(np.array([[0.5, 0.5, 0.2]]))
    assert depth_high[0] == pytest.approx(depth[0] - 0.2)


def test_top_down_of_an_empty_map_still_works() -> None:
    cam = CameraModel.top_down(bounds_xy=(0.0, 0.0, 0.0, 0.0), width=640, height=480)
    uv, depth = cam.project(np.array([[0.4, 0.4, 0.0]]))
    assert depth[0] > 0 and 0 < uv[0, 0] < 640 and 0 < uv[0, 1] < 480


def test_stereo_pair_disparity_is_f_b_over_z() -> None:
    cam = CameraModel.top_down(bounds_xy=(-1.0, -1.0, 2.0, 2.0))
    left, right = cam.stereo_pair(0.065)
    np.testing.assert_allclose(np.linalg.norm(left.centre_map - right.centre_map), 0.065)
    point = np.array([[0.3, 0.8, 0.0]])
    (ul, vl), (ur, vr) = left.project(point)[0][0], right.project(point)[0][0]
    depth = cam.project(point)[1][0]
    assert vl == pytest.approx(vr)
    assert ul - ur == pytest.approx(cam.K[0, 0] * 0.065 / depth)
    with pytest.raises(CalibrationError):
        cam.stereo_pair(0.0)


def test_from_registration_and_resized() -> None:
    reg = Registration(camera="c", robot="r", stamp=1.0, K=K, dist=np.array([0.1, 0, 0, 0, 0]),
                       width=1280, height=720, T_camera_from_map=oblique_T(),
                       reprojection_error_px=0.3)
    cam = CameraModel.from_registration(reg)
    assert cam == CameraModel(K=K, dist=reg.dist, width=1280, height=720,
                              T_camera_from_map=reg.T_camera_from_map)
    half = cam.resized(640, 360)
    p = np.array([[0.4, 0.6, 0.1]])
    np.testing.assert_allclose(half.project(p)[0], cam.project(p)[0] / 2, atol=1e-9)
    assert cam.resized(1280, 720) is cam
    assert not cam.K.flags.writeable


@pytest.mark.parametrize("kwargs", [
    {"K": np.eye(2)},
    {"dist": np.zeros(3)},
    {"T_camera_from_map": np.eye(3)},
    {"width": 0},
    {"K": np.array([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1.0]])},
])
def test_bad_camera_models_are_refused(kwargs: dict) -> None:
    args = {"K": K, "dist": np.zeros(5), "width": 1280, "height": 720,
            "T_camera_from_map": np.eye(4), **kwargs}
    with pytest.raises(CalibrationError):
        CameraModel(**args)
