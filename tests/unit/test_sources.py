"""Frame sources: folders, video files, devices, the synthetic camera, and reconnecting."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.errors import ConfigError, SourceError
from slamlens.common.messages import Truth
from slamlens.services.registration.sources import (
    CaptureSource,
    FolderSource,
    ReconnectingSource,
    SourceEnded,
    SyntheticSource,
    open_capture,
    parse_source,
)
from slamlens.services.registration.synthetic import (
    ImagingSettings,
    SyntheticCamera,
    overhead_pose,
    robot_marker_corners_world,
)


def numbered_image(k: int, size: tuple[int, int] = (64, 48)) -> np.ndarray:
    image = np.zeros((size[1], size[0], 3), np.uint8)
    image[:, :] = (10 * k, 255 - 10 * k, 7 * k)
    return image


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    d = tmp_path / "frames"
    d.mkdir()
    for k in (3, 1, 2):  # written out of order: read back in name order
        cv2.imwrite(str(d / f"frame_{k:03d}.png"), numbered_image(k))
    (d / "notes.txt").write_text("not an image")
    return d


def test_folder_reads_images_in_name_order_then_ends(folder: Path) -> None:
    source = FolderSource(folder, clock=lambda: 42.0)
    seen = []
    for _ in range(3):
        frame = source.read()
        assert frame is not None
        stamp, image = frame
        assert stamp == 42.0 and image.shape == (48, 64, 3)
        seen.append(int(image[0, 0, 0]) // 10)
    assert seen == [1, 2, 3]
    with pytest.raises(SourceEnded, match="ended after 3 images"):
        source.read()


def test_folder_loops_when_asked(folder: Path) -> None:
    source = FolderSource(folder, loop=True)
    values = [int(source.read()[1][0, 0, 0]) // 10 for _ in range(7)]
    assert values == [1, 2, 3, 1, 2, 3, 1]


def test_folder_errors_name_the_problem(tmp_path: Path, folder: Path) -> None:
    with pytest.raises(SourceError, match="does not exist"):
        FolderSource(tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SourceError, match="holds no images"):
        FolderSource(empty)
    source = FolderSource(folder)
    source.read()
    shutil.rmtree(folder)
    with pytest.raises(SourceError, match="unreadable or gone") as info:
        source.read()
    assert not isinstance(info.value, SourceEnded)


def write_video(path: Path, frames: int) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    assert writer.isOpened()
    for k in range(frames):
        writer.write(numbered_image(k))
    writer.release()


def test_video_file_plays_once_or_loops(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    write_video(path, 4)
    source = CaptureSource(str(path))
    assert not source.live
    got = [source.read() for _ in range(4)]
    assert all(f is not None and f[1].shape == (48, 64, 3) for f in got)
    # JPEG-compressed, but the colour ramp is still recognisable frame by frame
    assert [round(int(f[1][24, 32, 0]) / 10) for f in got] == [0, 1, 2, 3]
    with pytest.raises(SourceEnded):
        source.read()
    source.close()
    looping = CaptureSource(str(path), loop=True)
    assert sum(looping.read() is not None for _ in range(9)) == 9
    looping.close()


def test_device_and_path_parsing(tmp_path: Path, folder: Path) -> None:
    assert parse_source("0") == 0 and parse_source("rtsp://cam/1") == "rtsp://cam/1"
    assert parse_source(str(folder)) == folder
    with pytest.raises(ConfigError, match="does not exist"):
        open_capture(str(tmp_path / "nope.avi"))
    assert isinstance(open_capture(str(folder))(), FolderSource)
    with pytest.raises(SourceError, match="cannot open device 97"):
        CaptureSource(97)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_vanished_folder_is_retried_with_capped_backoff_and_comes_back(
        folder: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    backup = tmp_path / "backup"
    shutil.copytree(folder, backup)
    clock = FakeClock()
    source = ReconnectingSource(lambda: FolderSource(folder, loop=True), name="camera test",
                                backoff_initial_s=0.5, backoff_max_s=2.0, clock=clock)
    assert source.read() is not None
    shutil.rmtree(folder)
    with caplog.at_level(logging.DEBUG, logger="slamlens.services.registration.sources"):
        retries = []
        for _ in range(60):
            before = source.failures
            assert source.read() is None  # never raises, never blocks
            if source.failures > before:
                retries.append(clock.now)
            clock.now += 0.25
    gaps = np.diff(retries)
    np.testing.assert_allclose(gaps[:3], [0.5, 1.0, 2.0])
    assert np.all(gaps[3:] == 2.0)  # capped
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "camera test lost" in warnings[0].getMessage()
    assert source.outages == 1 and source.failures == len(retries)
    shutil.copytree(backup, folder)
    clock.now += 2.0
    assert source.read() is not None
    assert source.reconnects == 1


def test_reconnecting_source_lets_the_end_of_a_file_through(folder: Path) -> None:
    source = ReconnectingSource(lambda: FolderSource(folder), name="folder")
    for _ in range(3):
        assert source.read() is not None
    with pytest.raises(SourceEnded):
        source.read()


def test_reconnecting_source_opens_lazily_after_a_failed_start() -> None:
    attempts = []

    def factory():
        attempts.append(1)
        raise SourceError("no camera yet")

    clock = FakeClock()
    source = ReconnectingSource(factory, name="late camera", clock=clock)
    assert source.read() is None and source.read() is None  # second is inside the back-off
    assert len(attempts) == 1


def test_synthetic_source_renders_the_latest_truth_at_its_stamp() -> None:
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    cam = SyntheticCamera(K, 640, 480, T_world_from_camera=overhead_pose(
        centre_xy=(0.0, 0.0), height_m=2.0), imaging=ImagingSettings())
    source = SyntheticSource(cam, clock=lambda: 99.0)
    stamp, empty = source.read()
    assert stamp == 99.0  # no truth yet: wall clock, no robot
    truth = Truth(robot="r", stamp=3.5, pose=np.array([0.1, -0.1, 0.4]),
                  landmark_ids=np.array([1]), landmarks=np.array([[0.5, 0.5]]))
    source.set_truth(truth)
    stamp, image = source.read()
    assert stamp == 3.5 and source.frame_index == 2
    centre = cam.project(robot_marker_corners_world(truth.pose, size_m=0.2,
                                                    offset_xyz=(0, 0, 0.2))).mean(axis=0)
    u, v = np.round(centre).astype(int)
    assert np.any(image[v - 20:v + 20, u - 20:u + 20] != empty[v - 20:v + 20, u - 20:u + 20])

    moving = SyntheticSource(cam, pose_at=lambda t: overhead_pose(centre_xy=(t, 0.0),
                                                                  height_m=2.0))
    moving.set_truth(truth)
    moving.read()
    np.testing.assert_allclose(moving.last_T_world_from_camera[:3, 3], [3.5, 0.0, 2.0])
