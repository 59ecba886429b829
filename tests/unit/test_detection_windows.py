"""WindowedDetector: between full frames it looks only around the last markers, and finds
exactly what OpenCV finds over the whole image (the oracle: MarkerDetector on every frame).

Rendered frames of the synthetic overhead camera (noise, blur) with the arena's marker
board and the robot driving the paper world, and of the large world's camera 30 m up.
"""
from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.errors import ConfigError
from slamlens.common.messages import Truth
from slamlens.services.registration import assemble
from slamlens.services.registration.markers import MarkerDetector, WindowedDetector
from slamlens.services.registration.settings import RegistrationSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

PAPER = RegistrationSettings(source="synthetic")
LARGE = RegistrationSettings(source="synthetic", arena=(-1.5, -1.5, 39.5, 24.5),
                             camera_height=30.0, marker_size=1.0)


def _camera(settings: RegistrationSettings):  # noqa: ANN202 - a SyntheticCamera
    calib = assemble.calibration_for(settings)
    return assemble.synthetic_sources(settings, calib, assemble.board_for(settings))[0].camera


def _truths(world: str, count: int, every: int) -> list[Truth]:
    truths = []
    for e in Simulator(load_world(world), seed=3).events():
        if isinstance(e, Truth):
            truths.append(e)
            if len(truths) >= count * every:
                break
    return truths[::every]


@pytest.mark.parametrize("settings,world", [(PAPER, "paper"), (LARGE, "large")],
                         ids=["paper", "large"])
def test_windows_find_what_the_whole_image_finds(settings: RegistrationSettings,
                                                 world: str) -> None:
    camera = _camera(settings)
    full, windowed = MarkerDetector(), WindowedDetector(MarkerDetector(), full_every=15)
    frames = seen = 0
    for k, truth in enumerate(_truths(world, 60, 3)):
        image = camera.render(robot_pose=truth.pose, landmarks_xy=truth.landmarks,
                              frame_index=k)
        want = full.detect(image)
        assert windowed.detect(image) == want, f"frame {k}"
        frames += 1
        seen += bool(want)  # the robot may pass under a post: no marker that frame
    assert seen >= frames - 3
    assert windowed.full_frames + windowed.window_frames == frames
    # a full frame every 15th, and after a frame without markers; windows otherwise
    assert windowed.window_frames >= frames * 13 // 15 - 2 * (frames - seen) - windowed.fallbacks
    assert windowed.fallbacks <= 2


def test_a_marker_gone_or_new_is_decided_over_the_whole_image() -> None:
    camera = _camera(PAPER)
    truth = _truths("paper", 1, 1)[0]
    with_robot = camera.render(robot_pose=truth.pose, landmarks_xy=truth.landmarks)
    without = camera.render(robot_pose=None, landmarks_xy=truth.landmarks)
    full, windowed = MarkerDetector(), WindowedDetector(MarkerDetector(), full_every=10)
    assert windowed.detect(with_robot) == full.detect(with_robot)
    assert windowed.detect(with_robot) == full.detect(with_robot)  # a window frame
    assert windowed.window_frames == 1
    # the robot leaves the picture: its window finds nothing, the whole image decides
    assert windowed.detect(without) == full.detect(without)
    assert windowed.fallbacks == 1 and windowed.full_frames == 2
    assert windowed.detect(without) == full.detect(without)  # after a fallback: whole
    assert windowed.full_frames == 3
    # it comes back: the board's windows do not see it, the next full frame does
    seen = []
    for _ in range(10):
        seen.append(windowed.detect(with_robot) == full.detect(with_robot))
    assert seen[-1] and not all(seen), seen  # found within full_every frames, not before
    assert seen.index(True) <= 9


def test_full_every_is_checked() -> None:
    with pytest.raises(ConfigError):
        WindowedDetector(MarkerDetector(), full_every=0)
    once = WindowedDetector(MarkerDetector(), full_every=1)  # every frame whole
    image = _camera(PAPER).render(robot_pose=np.array([0.5, 0.5, 0.0]))
    for _ in range(3):
        once.detect(image)
    assert once.full_frames == 3 and once.window_frames == 0


def test_a_marker_faster_than_its_window_costs_a_window_at_most_now_and_then() -> None:
    """The robot jumps across the arena every frame (a fast driver, or a camera far behind):
    every answer is still the whole image's, and after each lost window the next 1, 2, 4, …
    frames are detected whole, so only a few window detections are wasted."""
    camera = _camera(PAPER)
    here = camera.render(robot_pose=np.array([0.2, 0.3, 0.0]))
    there = camera.render(robot_pose=np.array([1.6, 1.5, 2.0]))
    full, windowed = MarkerDetector(), WindowedDetector(MarkerDetector(), full_every=15)
    for k in range(60):
        image = here if k % 2 == 0 else there
        assert windowed.detect(image) == full.detect(image), k
    # lost at frames 1, 3, 6, 11, 20, 36, 52: 7, against 59 without the backoff
    assert 3 <= windowed.fallbacks <= 8, windowed.fallbacks
    assert windowed.full_frames >= 60 - 8 - windowed.fallbacks


def test_a_head_mounted_walk_finds_each_marker_as_the_whole_image_does() -> None:
    """The AR page's test walk (a head-mounted camera circling the arena, every other frame
    as the page sends them), windowed as a moving camera is: every marker a window finds is
    the whole image's, bit for bit; what the windows miss is only a marker new in view, and
    it is found within ``full_every`` frames."""
    from slamlens.services.harness.ar_video import render_walk

    settings = RegistrationSettings(source="synthetic", mode="head-mounted")
    video = render_walk(40, arc_deg=60.0)
    full = MarkerDetector()
    windowed = assemble.detector_for(settings, moving=True)
    assert isinstance(windowed, WindowedDetector)
    assert windowed.full_every == settings.detect_full_every_moving == 3
    missing_for = {}  # marker id → frames in a row the windows missed it
    found = want_total = 0
    for k, image in enumerate(video.frames[::2]):
        want = {d.marker_id: d for d in full.detect(image)}
        got = {d.marker_id: d for d in windowed.detect(image)}
        assert set(got) <= set(want), f"frame {k}: {set(got) - set(want)} not in the image"
        for marker_id, d in got.items():
            assert d == want[marker_id], f"frame {k} marker {marker_id}"
        for marker_id in want:
            missing_for[marker_id] = 0 if marker_id in got else missing_for.get(marker_id, 0) + 1
            assert missing_for[marker_id] < windowed.full_every, (k, marker_id)
        found += len(got)
        want_total += len(want)
    assert want_total >= 2 * len(video.frames[::2])  # the board is in view
    assert windowed.window_frames >= len(video.frames[::2]) // 2
    assert found >= 0.9 * want_total


def test_a_frame_of_another_size_is_detected_whole() -> None:
    camera = _camera(PAPER)
    image = camera.render(robot_pose=np.array([0.5, 0.5, 0.0]))
    windowed = WindowedDetector(MarkerDetector(), full_every=10)
    windowed.detect(image)
    windowed.detect(image)
    assert (windowed.full_frames, windowed.window_frames) == (1, 1)
    half = image[::2, ::2].copy()
    assert windowed.detect(half) == MarkerDetector().detect(half)
    assert windowed.full_frames == 2
