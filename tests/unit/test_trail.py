"""The robot's path drawn from picture to picture (services/visualiser/trail.py).

The oracle is the path drawn whole and straight onto the picture with one
``cv2.polylines`` call, as every picture drew it before: the trace, drawn a few points at
a time onto its layer and put over the picture, must give the same pixels to rounding,
over a camera frame and over a large state's under-layer, and must draw only what is new.
"""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.geometry import make_T
from slamlens.services.visualiser import draw, trail
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.trail import Trail
from tests.unit.test_viewer_layers import MAX_ROUNDING

COLOUR = (40, 200, 60)
WIDTH, HEIGHT = 640, 360


def camera(tilt: float = 0.0) -> CameraModel:
    cam = CameraModel.top_down(bounds_xy=(-1.0, -1.0, 2.0, 2.0), width=WIDTH, height=HEIGHT)
    if not tilt:
        return cam
    T = make_T(np.eye(3), np.zeros(3))
    T[:3, :3] = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)],
                          [0, np.sin(tilt), np.cos(tilt)]])
    return CameraModel(K=cam.K, dist=cam.dist, width=WIDTH, height=HEIGHT,
                       T_camera_from_map=T @ cam.T_camera_from_map)


def loop_path(points: int, seed: int = 0) -> np.ndarray:
    """A wobbly estimate of laps round a 1 m square (the paper's loop), overlapping itself."""
    t = np.linspace(0.0, 4.0 * points / 150.0, points)
    side = np.floor(t) % 4
    f = t % 1.0
    x = np.select([side == 0, side == 1, side == 2], [f, np.ones_like(f), 1 - f], 0 * f)
    y = np.select([side == 0, side == 1, side == 2], [0 * f, f, np.ones_like(f)], 1 - f)
    rng = np.random.default_rng(seed)
    return np.column_stack([x, y]) + rng.normal(0.0, 0.01, (points, 2))


def straight(img: np.ndarray, cam: CameraModel, xy: np.ndarray, thickness: int = 2) -> None:
    """The oracle: the whole path in one polylines call onto the picture."""
    draw.draw_polylines(img, draw.project_polyline(cam, np.column_stack(
        [xy, np.zeros(len(xy))])), colour=COLOUR, thickness=thickness)


def frame(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)


def assert_same_to_rounding(picture: np.ndarray, expected: np.ndarray,
                            background: np.ndarray) -> None:
    """The same pixels to OpenCV's rounding of anti-aliased edges on a layer (as
    tests/unit/test_viewer_layers.py holds layers: ≤ 12 levels where edges overlap), under
    a level on average over the pixels the path lit, and the same pixels lit."""
    diff = np.abs(picture.astype(int) - expected.astype(int)).max(axis=2)
    lit = (expected != background).any(axis=2)
    lit_here = (picture != background).any(axis=2)
    assert lit.sum() > 200
    assert diff.max() <= MAX_ROUNDING, diff.max()
    assert diff[lit].mean() < 1.0, diff[lit].mean()
    assert abs(int(lit_here.sum()) - int(lit.sum())) <= 0.02 * lit.sum()


def test_drawn_a_few_points_at_a_time_it_is_the_path_drawn_whole() -> None:
    xy = loop_path(600)
    path, cam = Trail(), camera()
    for k, point in enumerate(xy):
        path.track("r", k, tuple(point))
        if k % 37 == 36 or k == len(xy) - 1:
            picture, expected = frame(k), frame(k)
            path.draw(picture, cam, colour=COLOUR, thickness=2)
            straight(expected, cam, xy[:k + 1])
            assert_same_to_rounding(picture, expected, frame(k))


def test_over_a_layer_it_is_the_path_drawn_on_the_layer() -> None:
    xy = loop_path(300, seed=1)
    path, cam = Trail(), camera()
    for k, point in enumerate(xy):
        path.track("r", k, tuple(point))
    layer, expected_layer = draw.new_layer(HEIGHT, WIDTH), draw.new_layer(HEIGHT, WIDTH)
    path.draw(layer, cam, colour=COLOUR, thickness=2)
    straight(expected_layer, cam, xy)
    picture, expected = frame(5), frame(5)
    draw.Overlay(layer).put_over(picture)
    draw.Overlay(expected_layer).put_over(expected)
    assert_same_to_rounding(picture, expected, frame(5))


def test_only_the_new_segments_are_drawn(monkeypatch) -> None:
    drawn: list[int] = []
    real = trail._draw_segments

    def counting(trace, camera, xy, **kw):
        drawn.append(len(xy))
        real(trace, camera, xy, **kw)

    monkeypatch.setattr(trail, "_draw_segments", counting)
    xy = loop_path(500)
    path, cam = Trail(), camera()
    for k in range(400):
        path.track("r", k, tuple(xy[k]))
    path.draw(frame(0), cam, colour=COLOUR, thickness=2)
    assert drawn == [400]
    for k in range(400, 403):
        path.track("r", k, tuple(xy[k]))
    path.draw(frame(1), cam, colour=COLOUR, thickness=2)
    assert drawn[-1] == 4  # the last point drawn and the three new ones
    path.draw(frame(2), cam, colour=COLOUR, thickness=2)  # nothing new: nothing drawn
    assert len(drawn) == 2
    path.draw(frame(3), camera(tilt=0.2), colour=COLOUR, thickness=2)  # another view
    assert drawn[-1] == 403
    path.draw(frame(4), cam, colour=COLOUR, thickness=3)  # another width: another trace
    assert drawn[-1] == 403


@pytest.mark.parametrize("how", ["reset", "another robot", "seq went back", "thinned"])
def test_points_removed_start_the_trace_again(how: str, monkeypatch) -> None:
    monkeypatch.setattr(trail, "MAX_POINTS", 250)
    xy = loop_path(400, seed=2)
    path, cam = Trail(), camera()
    for k in range(200):
        path.track("r", k, tuple(xy[k]))
    path.draw(frame(0), cam, colour=COLOUR, thickness=2)
    robot, seq0 = "r", 200
    if how == "reset":
        path.reset()
        seq0 = 0
    elif how == "another robot":
        robot, seq0 = "r2", 0
    elif how == "seq went back":
        seq0 = 0
    for k in range(200, 400 if how == "thinned" else 260):
        path.track(robot, seq0 + k - 200, tuple(xy[k]))
    kept = path.points()
    if how == "thinned":
        assert len(kept) < 250 and np.allclose(kept[-1], xy[399])
    else:
        np.testing.assert_allclose(kept, xy[200:260])
    picture, expected = frame(9), frame(9)
    path.draw(picture, cam, colour=COLOUR, thickness=2)
    straight(expected, cam, kept)
    # the old path is gone from the picture: only what is kept now is drawn
    assert_same_to_rounding(picture, expected, frame(9))


def test_a_point_repeated_or_a_state_seen_twice_is_not_added() -> None:
    path = Trail()
    path.track("r", 1, (0.0, 0.0))
    path.track("r", 2, (0.0, 0.0))  # the robot stood still
    path.track("r", 2, (1.0, 0.0))  # the same state again
    path.track("r", 3, (0.5, 0.5))
    np.testing.assert_allclose(path.points(), [[0.0, 0.0], [0.5, 0.5]])


def test_a_segment_continued_is_drawn_as_opencv_draws_it_inside_one_polyline() -> None:
    """The trace's own segments (quadrilateral, end cap, a start cap only where a run
    starts) against ``cv2.polylines`` over the whole path, bit for bit, on random
    polylines of every width the viewer draws."""
    rng = np.random.default_rng(7)
    for _ in range(60):
        thickness = int(rng.integers(2, 7))
        points = rng.uniform(-40, 440, (int(rng.integers(3, 12)), 2))
        whole = draw.new_layer(400, 400)
        draw.draw_polylines(whole, [draw.fixed(points)], colour=COLOUR, thickness=thickness)
        trace = trail._Trace(0, 0, draw.new_layer(400, 400))
        cut = int(rng.integers(2, len(points)))
        trail._draw_segments(trace, _Pixels(), points[:cut], colour=COLOUR,
                             thickness=thickness)
        trace.drawn = cut
        trail._draw_segments(trace, _Pixels(), points[cut - 1:], colour=COLOUR,
                             thickness=thickness)
        assert np.array_equal(trace.layer, whole)


class _Pixels:
    """A camera that projects map (x, y) to the pixel (x, y)."""

    @staticmethod
    def project(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return points[:, :2].astype(float), points[:, 2]
