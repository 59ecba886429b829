"""Camera calibration files, the synthetic pinhole, and `slamlens calibrate`'s core on real
photos of a ChArUco board (tests/fixtures/fiducials, see its PROVENANCE.md)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.errors import CalibrationError, ConfigError
from slamlens.services.registration.calibrate import (
    CharucoSpec,
    calibrate_charuco,
    charuco_board_pose,
)
from slamlens.services.registration.calibration import (
    CameraCalibration,
    load_calibration,
    save_calibration,
    synthetic_calibration,
)

ARUCO = Path(__file__).resolve().parents[1] / "fixtures" / "fiducials" / "opencv_aruco"
CHARUCO_YML = ARUCO / "tutorial_camera_charuco.yml"
BOARD = dict(squares_x=5, squares_y=7, square_m=0.04, marker_m=0.02, dictionary="aruco_6x6_250")


def _numbers_after(text: str, field: str) -> list[float]:
    """The `data: [...]` numbers of one matrix field, read with a regex (not with OpenCV)."""
    block = text.split(field + ":", 1)[1]
    data = block.split("data:", 1)[1].split("]", 1)[0]
    return [float(x) for x in re.findall(r"-?\d+\.?\d*(?:e[-+]?\d+)?", data.replace("[", ""))]


def test_load_reads_the_opencv_tutorial_file() -> None:
    text = CHARUCO_YML.read_text()
    calib = load_calibration(CHARUCO_YML)
    assert (calib.width, calib.height) == (640, 480)
    np.testing.assert_array_equal(calib.K.ravel(), _numbers_after(text, "camera_matrix"))
    np.testing.assert_array_equal(calib.dist, _numbers_after(text, "distortion_coefficients"))
    assert not calib.K.flags.writeable and not calib.dist.flags.writeable


def test_save_load_round_trip_and_opencv_reads_it(tmp_path: Path) -> None:
    calib = load_calibration(CHARUCO_YML)
    out = tmp_path / "sub" / "cam.yml"
    save_calibration(out, calib, rms=0.25)
    assert load_calibration(out) == calib
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)  # the independent reader
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), calib.K)
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(), calib.dist)
    assert fs.getNode("image_width").real() == 640 and fs.getNode("image_height").real() == 480
    assert fs.getNode("avg_reprojection_error").real() == pytest.approx(0.25)
    fs.release()


def test_missing_image_size_names_the_field_unless_given() -> None:
    old = ARUCO / "tutorial_camera_params.yml"
    with pytest.raises(CalibrationError, match="image_width"):
        load_calibration(old)
    calib = load_calibration(old, image_size=(640, 480))
    assert calib.fx == pytest.approx(628.158) and calib.cy == pytest.approx(260.908)


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ("image_width: 640\nimage_height: 480\n", "camera_matrix"),
        ("camera_matrix: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: d\n"
         "   data: [1., 0., 0., 1.]\nimage_width: 640\nimage_height: 480\n", "camera_matrix"),
        ("camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
         "   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]\n"
         "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 3\n   dt: d\n"
         "   data: [0., 0., 0.]\nimage_width: 640\nimage_height: 480\n",
         "distortion_coefficients"),
        ("camera_matrix: 5\nimage_width: 640\nimage_height: 480\n", "camera_matrix"),
        ("camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
         "   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]\n"
         "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
         "   data: [0., 0., 0., 0., 0.]\nimage_width: -3\nimage_height: 480\n", "image_width"),
    ],
)
def test_malformed_files_name_file_and_field(tmp_path: Path, body: str, field: str) -> None:
    path = tmp_path / "bad.yml"
    path.write_text("%YAML:1.0\n---\n" + body)
    with pytest.raises(CalibrationError, match=field) as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="does not exist"):
        load_calibration(tmp_path / "nope.yml")
    garbage = tmp_path / "garbage.yml"
    garbage.write_bytes(b"\x00\x01not yaml at all: [")
    with pytest.raises(CalibrationError, match="garbage.yml"):
        load_calibration(garbage)


def test_calibration_validates_and_compares_by_value() -> None:
    a = synthetic_calibration(1280, 720, hfov_deg=70.0)
    b = CameraCalibration(K=a.K.copy(), dist=a.dist.copy(), width=1280, height=720)
    assert a == b and a != synthetic_calibration(1280, 720, hfov_deg=71.0)
    with pytest.raises(CalibrationError, match="K"):
        CameraCalibration(K=np.eye(3) * -1, dist=np.zeros(5), width=10, height=10)
    with pytest.raises(CalibrationError, match="dist"):
        CameraCalibration(K=np.eye(3), dist=np.zeros(6), width=10, height=10)


def test_synthetic_pinhole_edges_of_the_field_of_view() -> None:
    calib = synthetic_calibration(1280, 720, hfov_deg=90.0)
    assert calib.hfov_deg() == pytest.approx(90.0)
    assert np.all(calib.dist == 0.0) and calib.fx == calib.fy
    # a ray at half the field of view lands on the outer edge of the last pixel column
    u = calib.fx * math.tan(math.radians(45.0)) + calib.cx
    assert u == pytest.approx(1280 - 0.5)
    assert calib.cy == pytest.approx((720 - 1) / 2) and calib.cx == pytest.approx(639.5)


def _tutorial_images() -> list[np.ndarray]:
    return [cv2.imread(str(ARUCO / f"img_0{i}.jpg")) for i in range(4)]


def test_calibrate_charuco_reproduces_opencvs_calibration(tmp_path: Path) -> None:
    reference = load_calibration(CHARUCO_YML)  # OpenCV calibrated it on these 4 images
    calib, rms = calibrate_charuco(_tutorial_images(), **BOARD)
    assert (calib.width, calib.height) == (640, 480)
    ours = np.array([calib.fx, calib.fy, calib.cx, calib.cy])
    theirs = np.array([reference.fx, reference.fy, reference.cx, reference.cy])
    np.testing.assert_allclose(ours, theirs, rtol=0.03)
    assert 0.0 < rms < 0.5
    out = tmp_path / "cam.yml"
    save_calibration(out, calib, rms=rms)
    assert load_calibration(out) == calib


def test_calibrate_skips_blank_views_and_rejects_bad_input() -> None:
    images = _tutorial_images()
    blank = np.full_like(images[0], 200)
    calib, _ = calibrate_charuco([blank, *images], **BOARD)
    assert calib.width == 640
    with pytest.raises(CalibrationError, match="no usable view"):
        calibrate_charuco([blank, blank], **BOARD)
    with pytest.raises(CalibrationError, match="first was 640x480"):
        calibrate_charuco([images[0], cv2.resize(images[1], (320, 240))], **BOARD)
    with pytest.raises(ConfigError, match="marker size"):
        CharucoSpec(5, 7, square_m=0.02, marker_m=0.04)
    with pytest.raises(ConfigError, match="unknown marker dictionary"):
        calibrate_charuco(images, **{**BOARD, "dictionary": "aruco_9x9"})


def test_charuco_board_pose_none_when_not_seen() -> None:
    calib = load_calibration(CHARUCO_YML)
    spec = CharucoSpec(**BOARD)
    assert charuco_board_pose(np.full((480, 640), 90, np.uint8), board=spec, calib=calib) is None
