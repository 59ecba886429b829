"""The viewer service and its web server on real Zenoh (loopback) with real OpenCV.

The test plays estimator, camera and monitor: it publishes (or serves) SlamState,
Registration, CameraFrame and Health, and reads the viewer's HTTP endpoints.
"""

from __future__ import annotations

import dataclasses
import json
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import CameraFrame, Health, Registration, SlamState, Violation
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


def wait_until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError("condition not met in time")


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


# ------------------------------------------------------------------------------ tests
def test_snapshot_is_the_camera_picture_with_red_glyphs_at_pair_midpoints(
        start_viewer, publisher) -> None:
    _, url = start_viewer(camera=CAMERA)
    publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    publisher(KEYS.state(ROBOT), make_state(7).to_bytes())
    wait_until(lambda: (s := status_of(url))["state"] is not None
               and s["cameras"][0]["frame"] is not None
               and s["cameras"][0]["registration"] is not None)

    image, headers = snapshot(url)
    assert image.shape == (HEIGHT, WIDTH, 3)  # the camera's size
    assert headers["X-State-Seq"] == "7"
    for i, j in [(0, 1), (3, 4), (1, 4), (2, 5)]:
        assert red_pixels(image, midpoint(i, j)) >= 40, (i, j)
    # away from every glyph the camera's own picture shows through
    corner = image[HEIGHT - 20, WIDTH - 20].astype(int)
    assert np.abs(corner - BACKGROUND_BGR).max() <= 8
    assert red_pixels(image, (WIDTH - 30, HEIGHT - 30)) == 0


def test_a_late_viewer_shows_the_current_picture_at_once(start_viewer, make_client) -> None:
    estimator = make_client()  # plays estimator and camera: answers `get`, publishes nothing
    state, registration = make_state(42), make_registration()
    estimator.serve_latest(KEYS.state(ROBOT), lambda: state.to_bytes())
    estimator.serve_latest(KEYS.registration(CAMERA, ROBOT), lambda: registration.to_bytes())
    probe = make_client()  # the router routes queries to both queryables: so will the viewer's
    wait_until(lambda: len(probe.get(KEYS.state(ROBOT), timeout=1.0)) == 1
               and len(probe.get(KEYS.registration(CAMERA, ROBOT), timeout=1.0)) == 1)

    _, url = start_viewer(camera=CAMERA)
    image, headers = snapshot(url)
    assert headers["X-State-Seq"] == "42"
    assert image.shape == (HEIGHT, WIDTH, 3)  # registered size, though no frame came yet
    assert red_pixels(image, midpoint(0, 1)) >= 40
    assert red_pixels(image, midpoint(1, 4)) >= 40


def test_the_estimators_input_counts_reach_the_status_the_page_shows(start_viewer,
                                                                     make_client) -> None:
    estimator = make_client()
    counts = {"gated": 0.0, "inputs.late": 2.0, "inputs.lost": 1.0, "inputs.duplicates": 5.0}
    state = dataclasses.replace(make_state(9), diagnostics=counts)
    estimator.serve_latest(KEYS.state(ROBOT), lambda: state.to_bytes())
    probe = make_client()
    wait_until(lambda: len(probe.get(KEYS.state(ROBOT), timeout=1.0)) == 1)
    _, url = start_viewer(camera=CAMERA)
    wait_until(lambda: (status_of(url).get("state") or {}).get("seq") == 9)
    assert status_of(url)["state"]["inputs"] == {"late": 2, "lost": 1, "duplicates": 5}


def test_malformed_states_are_counted_and_the_viewer_keeps_going(start_viewer,
                                                                  publisher) -> None:
    _, url = start_viewer()  # map view
    key = KEYS.state(ROBOT)
    publisher(key, make_state(1).to_bytes())
    wait_until(lambda: (status_of(url)["state"] or {}).get("seq") == 1)

    wrong_shape = make_state(2).to_dict()
    wrong_shape["covariance"]["shape"] = [5, 5]  # 25 entries announced, 225 sent
    nan_pose = make_state(3).to_dict()
    nan_pose["pose"]["data"] = np.array([np.nan, 0.0, 0.0]).tobytes()
    bad = [b"\x00garbage", msgpack.packb({"schema": 1, "robot": ROBOT}),
           msgpack.packb(wrong_shape, use_bin_type=True),
           msgpack.packb(nan_pose, use_bin_type=True)]
    for n, payload in enumerate(bad, start=1):
        publisher(key, payload)  # one by one: the viewer keeps only the latest
        wait_until(lambda n=n: status_of(url)["bad_messages"].get("state") == n)
    publisher(key, make_state(5).to_bytes())

    wait_until(lambda: (status_of(url)["state"] or {}).get("seq") == 5)
    status = status_of(url)
    assert status["bad_messages"] == {"state": len(bad)}
    image, headers = snapshot(url)
    assert headers["X-State-Seq"] == "5"
    assert image.shape == (720, 1280, 3)  # the map view


def test_two_clients_with_different_modes_get_different_pictures(start_viewer,
                                                                 publisher) -> None:
    _, url = start_viewer(camera=CAMERA)
    publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    publisher(KEYS.state(ROBOT), make_state(3).to_bytes())
    wait_until(lambda: status_of(url)["state"] is not None
               and status_of(url)["cameras"][0]["registration"] is not None)

    status, _, body = http(url + "/api/settings?client=tabB", data={"mode": "inter"})
    assert status == 200 and json.loads(body)["settings"]["mode"] == "inter"
    all_pairs, _ = snapshot(url, "tabA")
    inter, _ = snapshot(url, "tabB")
    intra = [(0, 1), (3, 4)]  # pairs inside one cluster
    for i, j in intra:
        assert red_pixels(all_pairs[:, :], midpoint(i, j)) >= 40
        assert red_pixels(inter, midpoint(i, j)) == 0
    assert red_pixels(inter, midpoint(1, 4)) >= 40  # inter-cluster pairs stay
    # each tab kept its own settings
    assert json.loads(http(url + "/api/settings?client=tabA")[2])["settings"]["mode"] == "all"
    assert json.loads(http(url + "/api/settings?client=tabB")[2])["settings"]["mode"] == "inter"
    # the default snapshot (no client) is all pairs (docs/cli.md)
    default, _ = snapshot(url)
    assert red_pixels(default, midpoint(0, 1)) >= 40
    # tab A and the default snapshot have equal settings: they share one rendering
    assert status_of(url)["views_active"] == 2


def test_mjpeg_stream_follows_the_state_and_tags_each_frame(start_viewer, publisher) -> None:
    _, url = start_viewer()
    key = KEYS.state(ROBOT)
    publisher(key, make_state(1).to_bytes())
    response = urllib.request.urlopen(url + "/stream.mjpg?client=mj", timeout=10)
    assert response.headers["Content-Type"].startswith("multipart/x-mixed-replace")
    seqs: list[int] = []
    next_seq = 2
    while len(seqs) < 4 or seqs[-1] < 4:
        headers: dict[str, str] = {}
        line = response.readline().strip()
        while not line:
            line = response.readline().strip()
        assert line == b"--slamlensframe"
        while (line := response.readline().strip()):
            name, _, value = line.decode().partition(":")
            headers[name.strip().lower()] = value.strip()
        jpeg = response.read(int(headers["content-length"]))
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (720, 1280, 3)
        if headers["x-state-seq"]:
            seqs.append(int(headers["x-state-seq"]))
        if next_seq <= 4 and seqs and seqs[-1] == next_seq - 1:
            publisher(key, make_state(next_seq).to_bytes())
            next_seq += 1
    response.close()
    assert seqs == sorted(seqs) and seqs[-1] == 4


def test_bad_requests_get_a_clear_400_never_a_500(start_viewer) -> None:
    _, url = start_viewer()
    cases = [
        ("/api/settings?client=t1", {"mode": "sideways"}, "mode"),
        ("/api/settings?client=t1", {"scale": "big"}, "scale"),
        ("/api/settings?client=t1", {"scale": -1}, "scale"),
        ("/api/settings?client=t1", {"cluster_threshold_m": "nan"}, "cluster_threshold_m"),
        ("/api/settings?client=t1", {"selected_feature": "x"}, "selected_feature"),
        ("/api/settings?client=t1", {"no_such_setting": 1}, "no_such_setting"),
        ("/api/settings?client=t1", {"robot": {"a": 1}}, "robot"),
        ("/api/settings", {"mode": "all"}, "client"),
        ("/api/settings?client=../../etc", {"mode": "all"}, "client"),
    ]
    for path, data, word in cases:
        status, headers, body = http(url + path, data=data)
        assert status == 400, (path, data, body)
        assert headers["Content-Type"].startswith("application/json")
        assert word in json.loads(body)["error"], body
    for raw in (b"{not json", b"[1, 2]", b"\xff\xfe"):
        request = urllib.request.Request(url + "/api/settings?client=t1", data=raw,
                                         headers={"Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as error:
            urllib.request.urlopen(request, timeout=10)
        assert error.value.code == 400
        assert "JSON object" in json.loads(error.value.read())["error"]
    status, _, body = http(url + "/api/series?pairs=1-x")
    assert status == 400 and "pairs" in json.loads(body)["error"]
    status, _, body = http(url + "/snapshot.png?client=bad%20id")
    assert status == 400
    status, _, body = http(url + "/recordings/..%2Fsecrets")
    assert status in (400, 404)
    status, _, body = http(url + "/api/record/stop?client=nobody", data={})
    assert status == 404 and "not recording" in json.loads(body)["error"]
    # a bad change left the settings untouched
    assert json.loads(http(url + "/api/settings?client=t1")[2])["settings"]["mode"] == "all"


def test_health_and_series_endpoints_report_the_monitor(start_viewer, publisher) -> None:
    _, url = start_viewer(series_interval_s=0.0)
    for seq in range(1, 4):
        publisher(KEYS.state(ROBOT), make_state(seq, sigma_m=0.05 / seq).to_bytes())
        # the viewer keeps the newest state: wait for this one before the next
        wait_until(lambda s=seq: (status_of(url)["state"] or {}).get("seq") == s)
        health = Health(robot=ROBOT, seq=seq, stamp=0.1 * seq, ok=seq < 3,
                        suspects=np.array([12] if seq == 3 else [], dtype=np.int64),
                        violations=(Violation("pair", (10, 12), seq, 1e-3),) if seq == 3
                        else (),
                        statistics={"nees_pose": 2.0 + seq, "nees_pose_lo": 0.5,
                                    "nees_pose_hi": 9.0})
        publisher(KEYS.health(ROBOT), health.to_bytes())
        wait_until(lambda s=seq: (status_of(url)["health"] or {}).get("seq") == s)

    h = json.loads(http(url + "/api/health")[2])
    assert h["latest"]["ok"] is False and h["latest"]["suspects"] == [12]
    assert h["recent"][0]["kind"] == "pair" and h["recent"][0]["ids"] == [10, 12]

    series = json.loads(http(url + "/api/series?pairs=10-11,12-10")[2])
    assert [p["ids"] for p in series["pairs"]] == [[10, 11], [12, 10]]
    sizes = series["pairs"][0]["values"]
    assert len(sizes) == 3 and sizes == sorted(sizes, reverse=True)  # P_d shrank each step
    # size of P_d = 2σ² I is √(2σ²)
    assert sizes[0] == pytest.approx(np.sqrt(2) * 0.05, rel=1e-5)
    assert series["health"]["stats"]["nees_pose"] == [3.0, 4.0, 5.0]
    assert series["health"]["stats"]["nees_pose_hi"] == [9.0, 9.0, 9.0]
    # two clusters → one cluster pair with min ≤ mean ≤ max
    (cluster_pair,) = series["clusters"]
    low, mean, high = (cluster_pair[k][-1] for k in ("min", "mean", "max"))
    assert low <= mean * (1 + 1e-12) and mean <= high * (1 + 1e-12)
    assert mean == pytest.approx(np.sqrt(2) * 0.05 / 3, rel=1e-9)
    # automatic pairs: the monitor's flagged pair first
    auto = json.loads(http(url + "/api/series")[2])
    assert auto["pairs"][0]["ids"] == [10, 12]


def test_recording_writes_a_playable_video_that_can_be_downloaded(start_viewer,
                                                                 publisher) -> None:
    service, url = start_viewer(fps=20.0)
    publisher(KEYS.state(ROBOT), make_state(1).to_bytes())
    status, _, body = http(url + "/api/record/start?client=rec", data={})
    assert status == 200, body
    started = json.loads(body)
    for seq in range(2, 8):
        publisher(KEYS.state(ROBOT), make_state(seq).to_bytes())
        wait_until(lambda s=seq: (status_of(url)["state"] or {}).get("seq") == s)
    # the video is real time (fps frames a second): wait until it holds a few of them
    recorder = service.clients._recorders["rec"]
    wait_until(lambda: recorder.frames >= 5)
    status, _, body = http(url + "/api/record/stop?client=rec", data={})
    assert status == 200, body
    info = json.loads(body)
    assert info["file"] == started["file"] and info["frames"] >= 5

    path = Path(service.config.recordings_dir) / info["file"]
    capture = cv2.VideoCapture(str(path))
    ok, frame = capture.read()
    capture.release()
    assert ok and frame.shape == (720, 1280, 3)
    status, headers, body = http(url + info["url"])
    assert status == 200 and body == path.read_bytes()
    assert "attachment" in headers["Content-Disposition"]


def test_stereo_views_are_side_by_side(start_viewer, publisher) -> None:
    _, map_url = start_viewer(view="stereo")  # no camera: a stereo pair of the map view
    _, cam_url = start_viewer(view="stereo", camera=CAMERA)  # cameras top-left, top-right
    for eye in ("left", "right"):
        publisher(KEYS.registration(f"{CAMERA}-{eye}", ROBOT),
                  make_registration(f"{CAMERA}-{eye}").to_bytes())
    publisher(KEYS.state(ROBOT), make_state(9).to_bytes())
    wait_until(lambda: all(c["registration"] for c in status_of(cam_url)["cameras"])
               and status_of(cam_url)["state"] is not None)

    pair, _ = snapshot(map_url)
    assert pair.shape == (720, 2 * 1280, 3)
    pair, _ = snapshot(cam_url)
    assert pair.shape == (HEIGHT, 2 * WIDTH, 3)
    u, v = midpoint(1, 4)
    assert red_pixels(pair, (u, v)) >= 40  # left eye
    assert red_pixels(pair, (u + WIDTH, v)) >= 40  # right eye


def test_the_path_covers_states_received_before_any_view_was_drawn(start_viewer,
                                                                   publisher) -> None:
    """The path is remembered from every state taken in, not from the first render."""
    import dataclasses

    _, url = start_viewer(camera=CAMERA)
    publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    xs = np.linspace(1.2, 2.8, 17)
    for k, x in enumerate(xs):
        state = dataclasses.replace(make_state(k + 1), pose=np.array([x, 0.1, 0.0]))
        publisher(KEYS.state(ROBOT), state.to_bytes())
        # each one taken in before the next (the viewer keeps only the latest)
        wait_until(lambda s=k + 1: (status_of(url)["state"] or {}).get("seq") == s)
    image, _ = snapshot(url)  # the first picture drawn of this run
    green = (image[:, :, 1].astype(int) > 150) & (image[:, :, 0] < 110) & (image[:, :, 2] < 110)
    for x in (1.3, 1.7, 2.1):  # well behind the robot's final position at x = 2.8
        u, v = pixel_of(np.array([x, 0.1]))
        assert green[v - 4:v + 5, u - 4:u + 5].sum() >= 5, x


def test_several_viewers_attach_to_the_same_robot(start_viewer, publisher) -> None:
    """Two viewer services (as on two machines: each its own Zenoh session) see the same
    robot at once (a viewer joining late is tested above)."""
    _, url_a = start_viewer()
    _, url_b = start_viewer()
    def seq_of(url: str) -> int | None:
        return (status_of(url)["state"] or {}).get("seq")

    for seq in (1, 2, 3):  # (the first is put until both viewers received it)
        publisher(KEYS.state(ROBOT), make_state(seq).to_bytes())
        wait_until(lambda s=seq: seq_of(url_a) == s and seq_of(url_b) == s)
    for url in (url_a, url_b):
        _, headers = snapshot(url)
        assert headers["X-State-Seq"] == "3"


def test_a_new_map_is_never_drawn_with_the_old_maps_registration(start_viewer,
                                                                  publisher) -> None:
    """An estimator restarted without a checkpoint begins a new epoch (a new map frame):
    the viewer drops the old map (plots, path), says "map restarted", and shows the camera
    picture with a note — not a misplaced overlay — until a registration of the new epoch
    comes."""
    import dataclasses

    service, url = start_viewer(camera=CAMERA, series_interval_s=0.0)
    old, new = 1_000, 2_000
    publisher(KEYS.registration(CAMERA, ROBOT),
              dataclasses.replace(make_registration(), epoch=old).to_bytes())
    publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    for seq in (1, 2, 3):  # one by one: the viewer keeps only the latest
        publisher(KEYS.state(ROBOT), dataclasses.replace(make_state(seq), epoch=old).to_bytes())
        wait_until(lambda s=seq: (status_of(url)["state"] or {}).get("seq") == s)
    wait_until(lambda: status_of(url)["cameras"][0]["registration"] is not None)
    image, _ = snapshot(url)
    assert red_pixels(image, midpoint(0, 1)) >= 40
    assert len(json.loads(http(url + "/api/series?pairs=10-11")[2])["state"]["seq"]) == 3

    # the estimator restarts: a new epoch, seq from 0 again
    publisher(KEYS.state(ROBOT), dataclasses.replace(make_state(1), epoch=new).to_bytes())
    wait_until(lambda: (status_of(url)["state"] or {}).get("epoch") == new)
    status = status_of(url)
    (robot,) = status["robots"]
    assert robot["map_restarted"] and robot["restarts"] == 1
    assert robot["registration"] == {CAMERA: "stale"}
    image, _ = snapshot(url)
    assert red_pixels(image, midpoint(0, 1)) == 0  # no overlay in the old map's frame
    assert np.abs(image[HEIGHT // 2, WIDTH // 2].astype(int) - BACKGROUND_BGR).max() <= 8
    assert json.loads(http(url + "/api/series?pairs=10-11")[2])["state"]["seq"] == [1]
    assert len(service.renderer.path_xy) == 1  # the old map's path is gone

    # a registration without an epoch sent *before* the restart would be stale too; one
    # for the new epoch puts the overlay back
    publisher(KEYS.registration(CAMERA, ROBOT),
              dataclasses.replace(make_registration(), epoch=new).to_bytes())
    wait_until(lambda: status_of(url)["robots"][0]["registration"] == {CAMERA: "current"})
    image, _ = snapshot(url)
    assert red_pixels(image, midpoint(0, 1)) >= 40


def test_a_resumed_estimator_keeps_its_map(start_viewer, publisher) -> None:
    """The same epoch with a lower seq (an estimator resumed from its checkpoint replays a
    few states) is the same map: nothing is dropped."""
    import dataclasses

    service, url = start_viewer(series_interval_s=0.0)
    for seq in (1, 2, 3, 4, 2):
        publisher(KEYS.state(ROBOT), dataclasses.replace(make_state(seq), epoch=7).to_bytes())
        wait_until(lambda s=seq: (status_of(url)["state"] or {}).get("seq") == s)
    (robot,) = status_of(url)["robots"]
    assert robot["restarts"] == 0 and not robot["map_restarted"]
    assert json.loads(http(url + "/api/series?pairs=10-11")[2])["state"]["seq"] == [1, 2, 3, 4]


# ------------------------------------------------------------------------------ several robots
R2_OFFSET = np.array([0.6, 0.9])  # robot r2's map origin in robot1's map frame
R2_LANDMARKS = np.array([[0.2, 0.2], [0.6, 0.2], [0.2, 1.7]])  # in r2's own map frame


def r2_state(seq: int, *, robot: str = "r2") -> SlamState:
    import dataclasses

    state = make_state(seq, landmarks=R2_LANDMARKS)
    return dataclasses.replace(state, robot=robot, pose=np.array([0.4, 0.1, 0.0]),
                               landmark_ids=np.arange(50, 53))


def r2_registration(robot: str = "r2") -> Registration:
    """Where r2's map frame sits in the camera: its own registration (its own frame)."""
    import dataclasses

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


def test_each_state_is_drawn_on_layers_before_the_render_thread_takes_it_in(
        start_viewer, publisher) -> None:
    """Over a camera, ``viewer-layers`` draws each new state onto its layers,
    so the render thread only puts them over the frames: of five states it draws at most
    the first itself (before any picture, the eyes are not known yet)."""
    service, url = start_viewer(camera=CAMERA)
    service.histories.get(ROBOT).renderer.layers_from_n = 0  # (6 features: straight else)
    publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    for seq in range(1, 6):
        publisher(KEYS.state(ROBOT), make_state(seq).to_bytes())
        wait_until(lambda seq=seq: snapshot(url)[1]["X-State-Seq"] == str(seq))
    image, _ = snapshot(url)
    assert red_pixels(image, midpoint(0, 1)) >= 40  # drawn, over the camera's picture
    assert np.abs(image[HEIGHT - 20, WIDTH - 20].astype(int) - BACKGROUND_BGR).max() <= 8
    built = service.renderer.layers_built_on
    assert built["viewer-layers"] >= 4, built
    assert built["viewer-render"] <= 1, built
