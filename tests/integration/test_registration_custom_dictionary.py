"""``slamlens registration --dictionary FILE.yml``: a custom ArUco
dictionary from an OpenCV YAML file, on OpenCV's own photo of a board in that dictionary
(../shared/data/fiducials/opencv_aruco: tutorial_dict.yml, gboriginal.png, the tutorial's
camera parameters). The service registers on marker 0; the pose is checked against OpenCV's
own detection and solvePnP of the same marker, computed here."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import Registration
from slamlens.services.harness.procs import REPO, spawn, stop
from slamlens.services.registration.calibration import CameraCalibration, save_calibration
from slamlens.services.registration.markers import get_dictionary, is_custom

ARUCO = REPO.parent / "shared" / "data" / "fiducials" / "opencv_aruco"
DICT, PHOTO, CAMERA = (ARUCO / "tutorial_dict.yml", ARUCO / "gboriginal.png",
                       ARUCO / "tutorial_camera_params.yml")
SIZE = 0.04  # m; any size: the same one is used below
KEYS = Keys()


def tutorial_camera() -> tuple[np.ndarray, np.ndarray]:
    fs = cv2.FileStorage(str(CAMERA), cv2.FILE_STORAGE_READ)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    fs.release()
    return K, dist


def opencv_pose_of_marker_0() -> np.ndarray:
    """T_camera_from_marker of marker 0 by OpenCV alone (detection + IPPE square)."""
    K, dist = tutorial_camera()
    d = cv2.aruco.Dictionary()
    fs = cv2.FileStorage(str(DICT), cv2.FILE_STORAGE_READ)
    assert d.readDictionary(fs.root())
    fs.release()
    gray = cv2.cvtColor(cv2.imread(str(PHOTO)), cv2.COLOR_BGR2GRAY)
    corners, ids, _ = cv2.aruco.ArucoDetector(d).detectMarkers(gray)
    assert ids is not None and len(ids) == 35  # OpenCV's own test finds all 35
    c = corners[[int(i) for i in ids.ravel()].index(0)].reshape(4, 2).astype(np.float64)
    h = SIZE / 2
    obj = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, c, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    assert ok
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T


def test_the_core_reads_a_dictionary_file_wherever_a_name_is_taken() -> None:
    assert is_custom(str(DICT)) and not is_custom("aruco_6x6_250")
    d = get_dictionary(str(DICT))
    assert d.markerSize == 6 and d.bytesList.shape[0] == 35


def test_registration_service_registers_on_a_custom_dictionary_marker(tmp_path: Path,
                                                                       router_endpoint,
                                                                       make_client) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    shutil.copy(PHOTO, frames / "0000.png")
    K, dist = tutorial_camera()  # the tutorial's file has no image size: the photo's is 640×480
    calibration = tmp_path / "tutorial_camera.yml"
    save_calibration(calibration, CameraCalibration(K=K, dist=dist.ravel(), width=640,
                                                    height=480))
    client = make_client()
    registrations = client.channel(KEYS.registration("bench", "r4"))
    proc = spawn("registration", "--camera", "bench", "--robot", "r4", "--source",
                 str(frames), "--loop", "--fps", "10", "--calibration", str(calibration),
                 "--dictionary", str(DICT), "--marker-id", "0", "--marker-size", str(SIZE),
                 "--marker-offset", "0,0,0", "--connect", router_endpoint)
    try:
        proc.wait_for_line("registration ready: bench", timeout=60)
        deadline = time.monotonic() + 30
        sample = None
        while sample is None and time.monotonic() < deadline:
            sample = registrations.recv(timeout=0.5)
        assert sample is not None, "".join(proc.err[-20:])
        reg = Registration.from_bytes(sample.payload)
    finally:
        out, err = stop(proc)
    assert proc.returncode == 0, err
    assert reg.status == "registered" and reg.reprojection_error_px < 1.0
    expected = opencv_pose_of_marker_0()  # marker frame = robot frame = map frame here
    got = reg.T_camera_from_map
    K = reg.K
    # where the map origin (the marker's centre) lands in the image: within a pixel
    px = (K @ got[:3, 3])[:2] / got[2, 3]
    px_cv = (K @ expected[:3, 3])[:2] / expected[2, 3]
    assert np.linalg.norm(px - px_cv) < 1.0
    # depth from a 30-pixel marker: corners within a pixel (test_real_fiducials) ≈ 4 %
    assert got[2, 3] == pytest.approx(expected[2, 3], rel=0.05)
    R = got[:3, :3].T @ expected[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 3.0


def test_a_missing_dictionary_file_is_one_line(router_endpoint, tmp_path: Path) -> None:
    proc = spawn("registration", "--source", "synthetic", "--dictionary",
                 str(tmp_path / "none.yml"), "--connect", router_endpoint)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1 and err.startswith("slamlens: error:"), err
    assert "none.yml does not exist" in err and err.strip().count("\n") == 0
