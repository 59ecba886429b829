"""The viewer with several robots on real Zenoh (loopback) with real OpenCV: each robot
through its own registration, every robot whose estimator is alive shown, and the page's
re-register button asking the registration service by a query (the scene and the fixtures:
tests/integration/viewer_rig.py).
"""

from __future__ import annotations

import dataclasses
import json

import msgpack
import numpy as np

from slamlens.common.messages import Registration, SlamState
from tests.integration.viewer_rig import (
    CAMERA,
    KEYS,
    ROBOT,
    camera_pose,
    http,
    make_frame,
    make_registration,
    make_state,
    midpoint,
    pixel_of,
    red_pixels,
    snapshot,
    status_of,
)
from tests.waiting import wait_until

# ------------------------------------------------------------------------------ several robots
R2_OFFSET = np.array([0.6, 0.9])  # robot r2's map origin in robot1's map frame
R2_LANDMARKS = np.array([[0.2, 0.2], [0.6, 0.2], [0.2, 1.7]])  # in r2's own map frame


def r2_state(seq: int, *, robot: str = "r2") -> SlamState:

    state = make_state(seq, landmarks=R2_LANDMARKS)
    return dataclasses.replace(state, robot=robot, pose=np.array([0.4, 0.1, 0.0]),
                               landmark_ids=np.arange(50, 53))


def r2_registration(robot: str = "r2") -> Registration:
    """Where r2's map frame sits in the camera: its own registration (its own frame)."""

    T_map1_from_map2 = np.eye(4)
    T_map1_from_map2[:2, 3] = R2_OFFSET
    return dataclasses.replace(make_registration(), robot=robot,
                               T_camera_from_map=camera_pose() @ T_map1_from_map2)


def colour_pixels(image: np.ndarray, uv: tuple[int, int], bgr: tuple[int, int, int],
                  half: int = 6, tol: int = 40) -> int:
    u, v = uv
    patch = image[v - half:v + half + 1, u - half:u + half + 1].astype(int)
    return int(np.sum(np.abs(patch - np.array(bgr)).max(axis=2) <= tol))


def test_one_viewer_shows_several_robots_each_through_its_own_registration(
        start_viewer, publisher) -> None:
    from slamlens.services.visualiser.legend import ROBOT_COLOURS

    _, url = start_viewer(camera=CAMERA, robot=f"{ROBOT},r2")
    publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    publisher(KEYS.registration(CAMERA, "r2"), r2_registration().to_bytes())
    publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    publisher(KEYS.state(ROBOT), make_state(4).to_bytes())
    publisher(KEYS.state("r2"), r2_state(6).to_bytes())
    wait_until(lambda: all(r["state"] and r["registration"] == {CAMERA: "current"}
                           for r in status_of(url)["robots"])
               and len(status_of(url)["robots"]) == 2)
    status = status_of(url)
    assert [r["name"] for r in status["robots"]] == [ROBOT, "r2"]
    assert status["robots"][0]["colour"] != status["robots"][1]["colour"]

    image, headers = snapshot(url)
    assert headers["X-State-Seq"] == "4"  # the first robot's
    for i, j in [(0, 1), (1, 4)]:  # robot1's pairs where robot1's registration puts them
        assert red_pixels(image, midpoint(i, j)) >= 40
    for i, j in [(0, 1), (1, 2)]:  # r2's pairs, in r2's frame, where r2's registration puts them
        assert red_pixels(image, pixel_of((R2_LANDMARKS[i] + R2_LANDMARKS[j]) / 2
                                          + R2_OFFSET)) >= 40
    # each robot's cone in its own colour: robot1 green, r2 the first other colour
    assert colour_pixels(image, pixel_of(np.array([1.5, 0.2])), (28, 140, 28), tol=45) >= 5
    r2_pose = pixel_of(np.array([0.4, 0.1]) + R2_OFFSET)
    assert colour_pixels(image, r2_pose, tuple(int(0.6 * c) for c in ROBOT_COLOURS[0]),
                         tol=45) >= 5

    # features of both maps are clickable, each with its robot
    features = json.loads(http(url + "/api/features")[2])
    assert features["robot"] == [ROBOT] * 6 + ["r2"] * 3
    assert features["ids"][6:] == [50, 51, 52]
    u, v = features["uv"][6]
    assert abs(u - pixel_of(R2_LANDMARKS[0] + R2_OFFSET)[0]) <= 1.5
    # health and plots per robot; an unknown robot is a clear 400
    assert json.loads(http(url + "/api/health?robot=r2")[2])["robot"] == "r2"
    status_code, _, body = http(url + "/api/series?robot=nobody")
    assert status_code == 400 and "nobody" in json.loads(body)["error"]
    # selecting r2's feature 50 shows only its pairs; robot1 is drawn whole
    http(url + "/api/settings?client=sel", data={"selected_robot": "r2", "selected_feature": 50})
    selected, _ = snapshot(url, "sel")
    assert red_pixels(selected, pixel_of((R2_LANDMARKS[1] + R2_LANDMARKS[2]) / 2
                                         + R2_OFFSET)) == 0
    assert red_pixels(selected, pixel_of((R2_LANDMARKS[0] + R2_LANDMARKS[1]) / 2
                                         + R2_OFFSET)) >= 40
    assert red_pixels(selected, midpoint(0, 1)) >= 40


def test_all_robots_whose_estimator_is_alive_are_shown(start_viewer, make_client,
                                                       publisher) -> None:
    _, url = start_viewer(robot="all")
    assert status_of(url)["robots"] == []
    estimators = make_client()
    estimators.declare_alive(KEYS.estimator_alive("r7"))
    estimators.declare_alive(KEYS.estimator_alive("r8"))
    wait_until(lambda: [r["name"] for r in status_of(url)["robots"]] in (
        ["r7", "r8"], ["r8", "r7"]), timeout=15.0)
    publisher(KEYS.state("r8"), r2_state(3, robot="r8").to_bytes())
    wait_until(lambda: any(r["state"] for r in status_of(url)["robots"]))
    _, headers = snapshot(url)
    assert status_of(url)["discover"] is True


def test_the_reregister_button_asks_the_registration_service_by_a_query(start_viewer,
                                                                       make_client) -> None:
    """A viewer may publish nothing (docs/security.md): it asks by a Zenoh query carrying a
    CameraControl, which the registration service answers."""
    from slamlens.common.messages import CameraControl

    _, url = start_viewer(camera=CAMERA, reregister_timeout_s=1.0)
    status, _, body = http(url + "/api/reregister", data={})
    assert status == 200
    answer = json.loads(body)
    assert answer["answered"] is False and "no registration service" in (
        answer["cameras"][0]["detail"])

    camera_service = make_client()
    asked: list[CameraControl] = []

    def answer(key: str, payload: bytes | None, parameters: str) -> bytes:
        assert payload is not None
        request = CameraControl.from_bytes(payload)
        asked.append(request)
        return msgpack.packb({"schema": 1, "answer": f"accepted: re-registering camera "
                              f"{CAMERA} for robot {request.robot}"})

    camera_service.answer(KEYS.camera_control(CAMERA), answer)  # as the registration service
    status, _, body = http(url + f"/api/reregister?robot={ROBOT}", data={})
    assert status == 200, body
    answer_json = json.loads(body)
    assert answer_json["answered"] is True and answer_json["accepted"] is True
    assert answer_json["robot"] == ROBOT
    assert answer_json["cameras"] == [{
        "camera": CAMERA, "answered": True,
        "detail": f"accepted: re-registering camera {CAMERA} for robot {ROBOT}"}]
    assert [(a.command, a.robot) for a in asked] == [("reregister", ROBOT)]
    assert asked[0].requester and "web viewer" in asked[0].requester
    status, _, body = http(url + "/api/reregister?robot=stranger", data={})
    assert status == 400 and "stranger" in json.loads(body)["error"]
    _, map_url = start_viewer()
    status, _, body = http(map_url + "/api/reregister", data={})
    assert status == 400 and "no camera" in json.loads(body)["error"]
