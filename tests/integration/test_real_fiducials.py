"""Marker detection and board pose on real photos, against other people's results.

Photos and licences: tests/fixtures/fiducials/PROVENANCE.md.

Pixel conventions matter at the 1 px level checked here:
- OpenCV's gold corners (test_aruco_tutorial.cpp) are the *raw contour vertices* of the
  default detector (no corner refinement), stored as integers. A contour vertex is the centre
  of the outermost dark pixel, so it sits about half a pixel inside the true border edge;
  sub-pixel corners therefore lie ~0.5 px outward of the gold (checked below) and can be up to
  1.5 px from an integer gold value per axis (0.5 rounding + 0.5 convention + our 0.5).
- The AprilTag C library puts pixel centres at +0.5 (it samples with truncation), OpenCV at
  integers: C-library x = OpenCV x + 0.5. Its corners wrap the other way round (see below).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.services.registration.calibrate import CharucoSpec, charuco_board_pose, detect_charuco
from slamlens.services.registration.calibration import load_calibration
from slamlens.services.registration.markers import DetectorTuning, MarkerDetector
from slamlens.services.registration.pose import T_from_rvec_tvec

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "fiducials"
ARUCO = FIXTURES / "opencv_aruco"
APRILTAG = FIXTURES / "apriltag" / "33369213973_9d9bb4cc96_c"

# Gold ids and corners from OpenCV's own test, modules/objdetect/test/test_aruco_tutorial.cpp
# (github.com/opencv/opencv, read at commit 2e81c5601492999d560f17d94d5c862f5e12cac4):
# TEST(CV_ArucoTutorial, can_find_singlemarkersoriginal / can_find_gboriginal /
# can_find_choriginal / can_find_chocclusion). Each row: x,y of the 4 corners in OpenCV order.
GOLD_SINGLE_IDS = [40, 98, 62, 23, 124, 203]
GOLD_SINGLE = [
    [359, 310, 404, 310, 410, 350, 362, 350], [427, 255, 469, 256, 477, 289, 434, 288],
    [233, 273, 190, 273, 196, 241, 237, 241], [298, 185, 334, 186, 335, 212, 297, 211],
    [425, 163, 430, 186, 394, 186, 390, 162], [195, 155, 230, 155, 227, 178, 190, 178],
]
GOLD_GB = [  # ids 0..34
    [252, 74, 286, 81, 274, 102, 238, 95], [295, 82, 330, 89, 319, 111, 282, 104],
    [338, 91, 375, 99, 365, 121, 327, 113], [383, 100, 421, 107, 412, 130, 374, 123],
    [429, 109, 468, 116, 461, 139, 421, 132], [235, 100, 270, 108, 257, 130, 220, 122],
    [279, 109, 316, 117, 304, 140, 266, 133], [324, 119, 362, 126, 352, 150, 313, 143],
    [371, 128, 410, 136, 400, 161, 360, 152], [418, 139, 459, 145, 451, 170, 410, 163],
    [216, 128, 253, 136, 239, 161, 200, 152], [262, 138, 300, 146, 287, 172, 248, 164],
    [309, 148, 349, 156, 337, 183, 296, 174], [358, 158, 398, 167, 388, 194, 346, 185],
    [407, 169, 449, 176, 440, 205, 397, 196], [196, 158, 235, 168, 218, 195, 179, 185],
    [243, 170, 283, 178, 269, 206, 228, 197], [293, 180, 334, 190, 321, 218, 279, 209],
    [343, 192, 385, 200, 374, 230, 330, 220], [395, 203, 438, 211, 429, 241, 384, 233],
    [174, 192, 215, 201, 197, 231, 156, 221], [223, 204, 265, 213, 249, 244, 207, 234],
    [275, 215, 317, 225, 303, 257, 259, 246], [327, 227, 371, 238, 359, 270, 313, 259],
    [381, 240, 426, 249, 416, 282, 369, 273], [151, 228, 193, 238, 173, 271, 130, 260],
    [202, 241, 245, 251, 228, 285, 183, 274], [255, 254, 300, 264, 284, 299, 238, 288],
    [310, 267, 355, 278, 342, 314, 295, 302], [366, 281, 413, 290, 402, 327, 353, 317],
    [125, 267, 168, 278, 147, 314, 102, 303], [178, 281, 223, 293, 204, 330, 157, 317],
    [233, 296, 280, 307, 263, 346, 214, 333], [291, 310, 338, 322, 323, 363, 274, 349],
    [349, 325, 399, 336, 386, 378, 335, 366],
]
GOLD_CH = [  # ids 0..16
    [268, 77, 290, 80, 286, 97, 263, 94], [360, 90, 382, 93, 379, 111, 357, 108],
    [211, 106, 233, 109, 228, 127, 205, 123], [306, 120, 328, 124, 325, 142, 302, 138],
    [402, 135, 425, 139, 423, 157, 400, 154], [247, 152, 271, 155, 267, 174, 242, 171],
    [347, 167, 371, 171, 369, 191, 344, 187], [185, 185, 209, 189, 203, 210, 178, 206],
    [288, 201, 313, 206, 309, 227, 284, 223], [393, 218, 418, 222, 416, 245, 391, 241],
    [223, 240, 250, 244, 244, 268, 217, 263], [333, 258, 359, 262, 356, 286, 329, 282],
    [152, 281, 179, 285, 171, 312, 143, 307], [267, 300, 294, 305, 289, 331, 261, 327],
    [383, 319, 410, 324, 408, 351, 380, 347], [194, 347, 223, 352, 216, 382, 186, 377],
    [315, 368, 345, 373, 341, 403, 310, 398],
]
GOLD_OCC_IDS = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 15]
GOLD_OCC = [
    [301, 57, 322, 62, 317, 79, 295, 73], [391, 80, 413, 85, 408, 103, 386, 97],
    [242, 79, 264, 85, 256, 102, 234, 96], [334, 103, 357, 109, 352, 126, 329, 121],
    [428, 129, 451, 134, 448, 152, 425, 146], [274, 128, 296, 134, 290, 153, 266, 147],
    [371, 154, 394, 160, 390, 180, 366, 174], [208, 155, 232, 161, 223, 181, 199, 175],
    [309, 182, 333, 188, 327, 209, 302, 203], [411, 210, 436, 216, 432, 238, 407, 231],
    [241, 212, 267, 219, 258, 242, 232, 235], [167, 244, 194, 252, 183, 277, 156, 269],
    [202, 314, 230, 322, 220, 349, 191, 341],
]


def _gold(ids: list[int], rows: list[list[int]]) -> dict[int, np.ndarray]:
    return {i: np.array(r, dtype=float).reshape(4, 2) for i, r in zip(ids, rows, strict=True)}


CASES = {
    "singlemarkersoriginal.jpg": (None, _gold(GOLD_SINGLE_IDS, GOLD_SINGLE)),
    "gboriginal.png": ("tutorial_dict.yml", _gold(list(range(35)), GOLD_GB)),
    "choriginal.jpg": (None, _gold(list(range(17)), GOLD_CH)),
    "chocclusion_original.jpg": (None, _gold(GOLD_OCC_IDS, GOLD_OCC)),
}


def _detector(custom: str | None, refinement: str = "edges") -> MarkerDetector:
    tuning = DetectorTuning(corner_refinement=refinement)
    if custom:
        return MarkerDetector(custom_dictionary_path=str(ARUCO / custom), params=tuning)
    return MarkerDetector("aruco_6x6_250", params=tuning)


@pytest.mark.parametrize("name", sorted(CASES))
def test_raw_corners_match_opencvs_gold_within_1px(name: str) -> None:
    """The exact check of OpenCV's test: default detector parameters, no refinement."""
    custom, gold = CASES[name]
    found = _detector(custom, "none").detect(cv2.imread(str(ARUCO / name)))
    assert sorted(d.marker_id for d in found) == sorted(gold)
    for det in found:
        np.testing.assert_allclose(det.corners_px, gold[det.marker_id], atol=1.0,
                                   err_msg=f"marker {det.marker_id}")


@pytest.mark.parametrize("name", sorted(CASES))
def test_refined_corners_find_every_marker_and_sit_on_the_border_edge(name: str) -> None:
    custom, gold = CASES[name]
    found = _detector(custom).detect(cv2.imread(str(ARUCO / name)))
    assert sorted(d.marker_id for d in found) == sorted(gold)
    outward = []
    for det in found:
        g = gold[det.marker_id]
        # integer gold: ≤ 0.5 rounding + 0.5 contour-vertex convention + 0.5 ours (docstring)
        np.testing.assert_allclose(det.corners_px, g, atol=1.5, err_msg=f"marker {det.marker_id}")
        diagonal = g - g.mean(axis=0)
        diagonal /= np.linalg.norm(diagonal, axis=1, keepdims=True)
        outward.extend(np.sum((det.corners_px - g) * diagonal, axis=1))
    # the refined corner lies on the edge, half a pixel outside the dark pixel's centre
    assert 0.3 < float(np.mean(outward)) < 0.9


def _charuco_truth(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Board pose from the ChArUco *chessboard* corners (an independent measurement from
    saddle points, not marker borders), with OpenCV's intrinsics for these photos."""
    calib = load_calibration(ARUCO / "tutorial_camera_charuco.yml")
    spec = CharucoSpec(5, 7, 0.04, 0.02, "aruco_6x6_250")
    obj, img = detect_charuco(image, spec)
    ok, rvec, tvec = cv2.solvePnP(obj, img, calib.K, calib.dist)
    assert ok
    return T_from_rvec_tvec(rvec, tvec), calib.K, calib.dist


@pytest.mark.parametrize("index", range(4))
def test_edge_refinement_is_the_most_accurate_against_the_chessboard(index: int) -> None:
    """Marker corners predicted from the chessboard-corner pose vs detected: our default
    refinement must be within 0.65 px RMS and better than each of OpenCV's choices."""
    image = cv2.imread(str(ARUCO / f"img_0{index}.jpg"))
    T, K, dist = _charuco_truth(image)
    board = CharucoSpec(5, 7, 0.04, 0.02, "aruco_6x6_250").board()
    board_ids = list(np.ravel(board.getIds()))
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    rms = {}
    for refinement in ("edges", "none", "subpix", "apriltag"):
        errors = []
        for det in _detector(None, refinement).detect(image):
            obj = np.asarray(board.getObjPoints()[board_ids.index(det.marker_id)], float)
            predicted, _ = cv2.projectPoints(obj, rvec, T[:3, 3], K, dist)
            errors.append(np.linalg.norm(predicted.reshape(4, 2) - det.corners_px, axis=1))
        assert len(errors) == 17
        rms[refinement] = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    assert rms["edges"] < 0.65, rms
    assert all(rms["edges"] < rms[other] for other in ("none", "subpix", "apriltag")), rms


def _c_library_detections() -> np.ndarray:
    rows = []
    for line in APRILTAG.with_suffix(".txt").read_text().splitlines():
        numbers = [float(x) for x in re.findall(r"-?\d+(?:\.\d+)?", line)]
        assert len(numbers) == 9 and numbers[0] == 0  # every tag in this photo is id 0
        rows.append(np.array(numbers[1:]).reshape(4, 2))
    return np.array(rows)


# The C library's p[0..3] are the tag-frame points (−1, 1), (1, 1), (1, −1), (−1, −1) of its
# homography, wrapping counter-clockwise on screen; OpenCV's TL, TR, BR, BL are its
# p[1], p[0], p[3], p[2] (apriltag.c, quad_decode_task; the same for all 12 tags below).
C_LIBRARY_FROM_OPENCV_ORDER = [1, 0, 3, 2]
C_LIBRARY_PIXEL_OFFSET = 0.5


def test_apriltag_photo_matches_the_c_library() -> None:
    reference = _c_library_detections()
    assert len(reference) == 12
    found = MarkerDetector("apriltag_36h11").detect(cv2.imread(str(APRILTAG.with_suffix(".jpg"))))
    assert all(d.marker_id == 0 for d in found)
    ours = np.array([d.corners_px[C_LIBRARY_FROM_OPENCV_ORDER] + C_LIBRARY_PIXEL_OFFSET
                     for d in found])
    matched = set()
    for ref in reference:
        distance = np.linalg.norm(ours.mean(axis=1) - ref.mean(axis=0), axis=1)
        k = int(np.argmin(distance))
        assert k not in matched
        matched.add(k)
        np.testing.assert_allclose(ours[k], ref, atol=1.0)
    # OpenCV also decodes one more tag (a cube's front face at about (370, 356)) that the C
    # library's decimated quad search misses; it must be a different physical tag, not a
    # duplicate of one of the twelve
    extra = [k for k in range(len(found)) if k not in matched]
    assert len(extra) <= 1
    for k in extra:
        side = found[k].side_px
        assert np.min(np.linalg.norm(reference.mean(axis=1) - ours[k].mean(axis=0), axis=1)) > side


@pytest.mark.parametrize("index", range(4))
def test_charuco_board_pose_reprojects_within_half_a_pixel(index: int) -> None:
    calib = load_calibration(ARUCO / "tutorial_camera_charuco.yml")
    image = cv2.imread(str(ARUCO / f"img_0{index}.jpg"))
    spec = CharucoSpec(5, 7, 0.04, 0.02, "aruco_6x6_250")
    result = charuco_board_pose(image, board=spec, calib=calib)
    assert result is not None
    T, rms = result
    assert rms < 0.5
    assert 0.2 < T[2, 3] < 1.0  # a hand-held A4 board, tens of centimetres away
    obj, _ = detect_charuco(image, spec)
    assert len(obj) >= 20  # of the 24 inner corners of a 5x7 board
    # 7 rows is odd: the pre-4.6 ("legacy") layout is the same board, same corners
    legacy = detect_charuco(image, CharucoSpec(5, 7, 0.04, 0.02, "aruco_6x6_250",
                                               legacy_pattern=True))
    assert legacy is not None
    np.testing.assert_array_equal(legacy[1], detect_charuco(image, spec)[1])
    # the transposed layout does not fit the markers' arrangement
    wrong = detect_charuco(image, CharucoSpec(7, 5, 0.04, 0.02, "aruco_6x6_250"))
    assert wrong is None or len(wrong[0]) < len(obj) // 2
