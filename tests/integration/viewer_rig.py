"""The viewer service's integration rig: a scene (camera, landmarks, states,
registrations, frames), HTTP helpers, and the fixtures that start viewers and publish
to them (tests/integration/conftest.py hands the fixtures to every test there)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import CameraFrame, Registration, SlamState
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewerConfig
from slamlens.services.visualiser.web import WebServer
from tests.routes import put_until_seen

KEYS = Keys()
ROBOT, CAMERA = "robot1", "top"
WIDTH, HEIGHT, FOCAL = 800, 600, 600.0
CAMERA_CENTRE = np.array([1.5, 1.5, 3.0])  # 3 m above the middle of the arena
BACKGROUND_BGR = (120, 100, 80)
# two clusters of three features, 2.8 m apart
LANDMARKS = np.array([[0.5, 0.5], [0.9, 0.5], [0.7, 0.85],
                      [2.3, 2.3], [2.7, 2.3], [2.5, 2.65]])


def camera_pose() -> np.ndarray:
    """T_camera_from_map of a camera looking straight down (x right, y image-down)."""
    R = np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ CAMERA_CENTRE
    return T


K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])


def pixel_of(xy: np.ndarray) -> tuple[int, int]:
    """Hand-made pinhole projection of a floor point (the test's own oracle)."""
    p = camera_pose() @ np.array([xy[0], xy[1], 0.0, 1.0])
    u, v = FOCAL * p[0] / p[2] + WIDTH / 2, FOCAL * p[1] / p[2] + HEIGHT / 2
    return int(round(u)), int(round(v))


def make_state(seq: int, *, sigma_m: float = 0.05, landmarks: np.ndarray = LANDMARKS) -> SlamState:
    n = len(landmarks)
    P = np.eye(3 + 2 * n) * sigma_m ** 2  # P_d = 2σ² I: 2-sigma glyph semi-axis 0.14 m
    P[:3, :3] = np.diag([1e-4, 1e-4, 1e-4])
    return SlamState(robot=ROBOT, seq=seq, stamp=0.1 * seq, step="update",
                     pose=np.array([1.5, 0.2, 0.0]), landmark_ids=np.arange(10, 10 + n),
                     landmarks=landmarks, covariance=P)


def make_registration(camera: str = CAMERA) -> Registration:
    return Registration(camera=camera, robot=ROBOT, stamp=0.0, K=K, dist=np.zeros(5),
                        width=WIDTH, height=HEIGHT, T_camera_from_map=camera_pose(),
                        reprojection_error_px=0.3)


def make_frame(seq: int, camera: str = CAMERA) -> CameraFrame:
    image = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    image[:] = BACKGROUND_BGR
    ok, jpeg = cv2.imencode(".jpg", image)
    assert ok
    return CameraFrame(camera=camera, seq=seq, stamp=0.1 * seq, encoding="jpeg", width=WIDTH,
                       height=HEIGHT, data=jpeg.tobytes())


def red_pixels(image: np.ndarray, uv: tuple[int, int], half: int = 5) -> int:
    """Red-dominant pixels (the glyph colour and its shading) around ``uv``."""
    u, v = uv
    patch = image[v - half:v + half + 1, u - half:u + half + 1].astype(int)
    b, g, r = patch[..., 0], patch[..., 1], patch[..., 2]
    return int(np.sum((r > 100) & (r > 1.5 * g) & (r > 1.5 * b)))


def midpoint(i: int, j: int) -> tuple[int, int]:
    return pixel_of((LANDMARKS[i] + LANDMARKS[j]) / 2)


# ------------------------------------------------------------------------------ helpers
def http(url: str, *, data: dict | None = None, method: str | None = None,
         timeout: float = 10.0) -> tuple[int, dict[str, str], bytes]:
    body = None if data is None else json.dumps(data).encode()
    request = urllib.request.Request(url, data=body, method=method or (
        "POST" if data is not None else "GET"), headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def snapshot(url: str, client: str | None = None) -> tuple[np.ndarray, dict[str, str]]:
    status, headers, body = http(url + "/snapshot.png" + (f"?client={client}" if client else ""))
    assert status == 200, body
    assert headers["Content-Type"] == "image/png"
    assert body[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image, headers


def status_of(url: str) -> dict:
    status, _, body = http(url + "/api/status")
    assert status == 200
    return json.loads(body)


def received_by(service: ViewerService, key: str) -> int | None:
    """How many samples of ``key`` the viewer's subscription received (None: it does not
    subscribe to it), read from its intake's slots: what a test waits on to know that a
    route from its publisher to the viewer carries samples."""
    intake = service.intake
    for robot in intake.robots():
        if key == KEYS.state(robot.name):
            return robot.state_slot.count
        if key == KEYS.health(robot.name):
            return robot.health_queue.received_count
    for camera in intake.cameras():
        if key == KEYS.frame(camera.name):
            return camera.frame_slot.count
        for robot_name, slot in camera.registration_slots.items():
            if key == KEYS.registration(camera.name, robot_name):
                return slot.count
    return None


@pytest.fixture
def viewers() -> list[ViewerService]:
    """The viewer services a test started (the publisher waits until they receive)."""
    return []


@pytest.fixture
def start_viewer(make_client, tmp_path: Path, viewers: list[ViewerService]
                 ) -> Iterator[Callable[..., tuple[ViewerService, str]]]:
    started: list[tuple[ViewerService, WebServer]] = []

    def start(**config: object) -> tuple[ViewerService, str]:
        settings = {"robot": ROBOT, "recordings_dir": str(tmp_path / "recordings"), **config}
        service = ViewerService(make_client(), keys=KEYS, config=ViewerConfig(**settings))
        service.start()
        web = WebServer(service, host="127.0.0.1", port=0)
        url = web.start()
        started.append((service, web))
        viewers.append(service)
        return service, url

    yield start
    for service, web in started:
        web.stop()
        service.stop()


@pytest.fixture
def publisher(make_client, viewers: list[ViewerService]) -> Callable[[str, bytes], None]:
    """``put(key, payload)`` as the estimator, camera or monitor would.

    A new publisher first waits for its matching status; then its first sample is put
    until every viewer subscribing to the key received it: on a loaded machine a route
    can still drop samples for a few hundred ms after the publisher matched (zenoh 1.10,
    measured: up to 0.3 s). Once a sample went through, the route is there (reliable)."""
    bus = make_client()
    publishers: dict[str, object] = {}

    def put(key: str, payload: bytes) -> None:
        if key in publishers:
            publishers[key].put(payload)  # type: ignore[attr-defined]
            return
        pub = publishers[key] = bus.publisher(key)
        assert pub.wait_matched(), key  # type: ignore[attr-defined]
        subscribed = [v for v in viewers if received_by(v, key) is not None]
        before = [received_by(v, key) for v in subscribed]
        put_until_seen(lambda: pub.put(payload),  # type: ignore[attr-defined]
                       lambda: all(received_by(v, key) > n  # type: ignore[operator]
                                   for v, n in zip(subscribed, before, strict=True)),
                       what=f"the first sample on {key} at the viewer", timeout_s=15.0)

    return put
