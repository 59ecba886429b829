"""The viewer service and its web server on real Zenoh (loopback) with real OpenCV.

The test plays estimator, camera and monitor: it publishes (or serves) SlamState,
Registration, CameraFrame and Health, and reads the viewer's HTTP endpoints (the scene and
the fixtures: tests/integration/viewer_rig.py; several robots: test_viewer_robots.py).
"""

from __future__ import annotations

import dataclasses
import json
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest

from slamlens.common.messages import Health, Violation
from tests.integration.viewer_rig import (
    BACKGROUND_BGR,
    CAMERA,
    HEIGHT,
    KEYS,
    ROBOT,
    WIDTH,
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
