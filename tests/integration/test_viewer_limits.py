"""The viewer's resources stay bounded whatever clients ask.

A real viewer service and web server on loopback Zenoh; the clients are real HTTP
clients (urllib; MJPEG streams read on threads). Every wait is on an event: a state's seq
arriving in a stream, the viewer's own status saying a view was dropped.
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable, Iterator
from http.client import HTTPConnection
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState
from slamlens.services.harness.web_client import http, post_json
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewerConfig
from slamlens.services.visualiser.web import WebServer
from tests.routes import put_until_seen
from tests.waiting import wait_until

KEYS = Keys()
ROBOT = "robot1"
MAP_W, MAP_H = 320, 180
PICTURE_BYTES = MAP_W * MAP_H * 3  # the BGR picture a view holds (besides its JPEG)
LANDMARKS = np.array([[0.5, 0.5], [0.9, 0.5], [2.3, 2.3], [2.7, 2.3]])


def state(seq: int) -> SlamState:
    P = np.eye(3 + 2 * len(LANDMARKS)) * 0.05 ** 2
    return SlamState(robot=ROBOT, seq=seq, stamp=0.1 * seq, step="update",
                     pose=np.array([1.0 + 0.01 * seq, 1.0, 0.0]),
                     landmark_ids=np.arange(10, 10 + len(LANDMARKS)), landmarks=LANDMARKS,
                     covariance=P)


def status_of(url: str) -> dict[str, Any]:
    code, _, body = http(url + "/api/status")
    assert code == 200, body
    return json.loads(body)


def views(url: str) -> dict[str, Any]:
    return status_of(url)["views"]


class Stream(threading.Thread):
    """An MJPEG client: reads every part and notes the state seq it shows."""

    def __init__(self, url: str, client: str | None = None) -> None:
        super().__init__(daemon=True)
        host, port = url.removeprefix("http://").split(":")
        self.conn = HTTPConnection(host, int(port), timeout=30)
        self.conn.connect()
        self.sock = self.conn.sock  # http.client lets go of it once the response streams
        self.conn.request("GET", "/stream.mjpg" + (f"?client={client}" if client else ""))
        self.response = self.conn.getresponse()
        assert self.response.status == 200
        self.seqs: list[int] = []
        self.changed = threading.Condition()
        self.start()

    def run(self) -> None:
        try:
            while True:
                headers: dict[str, str] = {}
                line = self.response.readline()
                while line.strip() == b"":
                    line = self.response.readline()
                    if not line:
                        return
                while (line := self.response.readline().strip()):
                    name, _, value = line.decode().partition(":")
                    headers[name.strip().lower()] = value.strip()
                self.response.read(int(headers["content-length"]))
                with self.changed:
                    if headers.get("x-state-seq"):
                        self.seqs.append(int(headers["x-state-seq"]))
                    self.changed.notify_all()
        except (OSError, ValueError, KeyError, AttributeError):
            return  # closed

    def wait_for_seq(self, seq: int, timeout: float = 30.0) -> None:
        with self.changed:
            if not self.changed.wait_for(lambda: seq in self.seqs, timeout):
                raise AssertionError(f"the stream never showed state {seq}: {self.seqs[-5:]}")

    def close(self) -> None:
        """Hang up now (the reading thread may be blocked in a read)."""
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.join(timeout=10)
        self.response.close()
        self.conn.close()


@pytest.fixture
def start_viewer(make_client, tmp_path: Path) -> Iterator[Callable[..., str]]:
    started: list[tuple[ViewerService, WebServer]] = []

    def start(**config: Any) -> str:
        service = ViewerService(make_client(), keys=KEYS, config=ViewerConfig(**{
            "robot": ROBOT, "recordings_dir": str(tmp_path / "recordings"),
            "late_join_timeout_s": 0, "map_width": MAP_W, "map_height": MAP_H, **config}))
        service.start()
        web = WebServer(service, host="127.0.0.1", port=0)
        started.append((service, web))
        return web.start()

    yield start
    for service, web in started:
        web.stop()
        service.stop()


@pytest.fixture
def publish_state(make_client) -> Callable[..., None]:
    """Publishes states (declared at the first, once the viewer subscribed)."""
    bus = make_client()
    publishers: list[Any] = []

    def put(seq: int, url: str | None = None) -> None:
        """With ``url`` (the first state): put until that viewer shows it, since a matched
        route may still drop samples for a few hundred ms on a loaded machine."""
        if not publishers:
            publishers.append(bus.publisher(KEYS.state(ROBOT)))
            assert publishers[0].wait_matched(10.0)
        if url is None:
            publishers[0].put(state(seq).to_bytes())
            return
        put_until_seen(lambda: publishers[0].put(state(seq).to_bytes()),
                       lambda: (status_of(url)["state"] or {}).get("seq") == seq,
                       what=f"state {seq} at {url}")

    return put


def test_views_are_capped_the_oldest_idle_is_evicted_and_the_default_always_served(
        start_viewer, publish_state) -> None:
    url = start_viewer(max_views=2, client_ttl_s=600.0)
    publish_state(1, url)
    wait_until(lambda: status_of(url)["state"] is not None)
    a = Stream(url, "a")  # streams its (default) settings …
    assert post_json(url + "/api/settings?client=a", {"scale": 2})[0] == 200
    assert post_json(url + "/api/settings?client=b", {"scale": 3})[0] == 200
    b = Stream(url, "b")
    wait_until(lambda: views(url)["streamed"] == 2)  # … and follows its new settings
    publish_state(2)
    a.wait_for_seq(2)
    b.wait_for_seq(2)
    held = views(url)
    assert held["kept"] == 3 and held["max"] == 2  # a's, b's, and the default view a left
    assert held["picture_bytes"] >= 3 * PICTURE_BYTES

    # both views are streamed: a third distinct view is refused, the client's settings stay
    status, _, body = post_json(url + "/api/settings?client=c", {"scale": 4})
    assert status == 503 and "max_views 2" in json.loads(body)["error"]
    assert json.loads(http(url + "/api/settings?client=c")[2])["settings"]["scale"] == 1.0
    assert http(url + "/snapshot.png?client=c")[0] == 200  # c still gets the default view
    assert http(url + "/snapshot.png")[0] == 200
    assert views(url)["refused"] == 1

    # a's stream ends: its view is idle, and the next new view evicts it
    a.close()
    wait_until(lambda: views(url)["streamed"] == 1)
    assert post_json(url + "/api/settings?client=c", {"scale": 4})[0] == 200
    assert http(url + "/snapshot.png?client=c")[0] == 200
    held = views(url)
    assert held["evicted"] == 1 and held["kept"] == 3  # b, c and the default view
    assert held["picture_bytes"] <= 3 * (PICTURE_BYTES + 100_000)
    b.close()


def test_a_view_nobody_looks_at_is_dropped_with_its_picture(start_viewer,
                                                            publish_state) -> None:
    url = start_viewer(client_ttl_s=0.3)
    publish_state(1, url)
    for k in range(5):
        assert post_json(f"{url}/api/settings?client=t{k}", {"sigma_k": 1 + k})[0] == 200
        assert http(f"{url}/snapshot.png?client=t{k}")[0] == 200
    assert views(url)["picture_bytes"] > 0
    wait_until(lambda: views(url) | {"max": 0, "evicted": 0, "refused": 0} == {
        "kept": 0, "streamed": 0, "max": 0, "evicted": 0, "refused": 0, "picture_bytes": 0})


def test_small_soak_default_clients_see_every_state_while_others_churn(
        start_viewer, publish_state) -> None:
    """A small version of benchmarks/bench_viewer_soak.py: 40 distinct settings asked by
    8 clients (4 of them streaming) beside 2 default-view streams, 4 views allowed."""
    url = start_viewer(max_views=4, client_ttl_s=1.0)
    publish_state(1, url)
    defaults = [Stream(url), Stream(url, "plain")]
    for d in defaults:
        d.wait_for_seq(1)
    before = views(url)
    streams: dict[str, Stream] = {}
    refused = 0
    for k in range(40):
        client = f"c{k % 8}"
        status, _, body = post_json(f"{url}/api/settings?client={client}",
                                    {"scale": 1.0 + k / 10, "mode": ("all", "inter")[k % 2]})
        streaming = k % 8 < 4
        if status == 503 and not streaming:  # every kept view is streamed by others
            refused += 1
            assert "max_views 4" in json.loads(body)["error"]
        else:  # a streaming client leaves its own view: that makes room
            assert status == 200, body
        if streaming and client not in streams:
            streams[client] = Stream(url, client)
        elif not streaming:  # its view, if it has one, else (503) it was refused
            assert http(f"{url}/snapshot.png?client={client}")[0] in (200, 503)
        publish_state(2 + k)
        for d in defaults:  # the default view shows every state, whatever the others do
            d.wait_for_seq(2 + k)
        held = views(url)
        assert held["kept"] <= 4 + 1
        assert held["picture_bytes"] <= (4 + 1) * (PICTURE_BYTES + 100_000)
    assert refused > 0 and views(url)["refused"] >= refused
    for s in (*streams.values(), *defaults):
        s.close()
    # everybody left: every view is dropped, and with it every picture
    wait_until(lambda: views(url)["kept"] == 0 and views(url)["picture_bytes"] == 0)
    assert before["picture_bytes"] > 0 and before["kept"] == 1


def test_recordings_are_capped_in_number_time_and_disk_space(start_viewer,
                                                             publish_state) -> None:
    url = start_viewer(max_recordings=1, max_recording_s=1.0, fps=10.0)
    publish_state(1, url)
    status, _, body = post_json(url + "/api/record/start?client=r1", {})
    assert status == 200, body
    status, _, body = post_json(url + "/api/record/start?client=r2", {})
    assert status == 503 and "max_recordings 1" in json.loads(body)["error"]
    # the running one stops by itself after max_recording_s; then another may start
    wait_until(lambda: status_of(url)["recording"] == [])
    status, _, body = post_json(url + "/api/record/stop?client=r1", {})
    info = json.loads(body)
    assert status == 200 and not info["recording"] and "max_recording_s" in info["limit"]
    assert info["frames"] >= 1
    assert post_json(url + "/api/record/start?client=r2", {})[0] == 200
    assert post_json(url + "/api/record/stop?client=r2", {})[0] == 200

    full = start_viewer(min_free_disk_mb=1e12)  # asks for more space than any disk has
    status, _, body = post_json(full + "/api/record/start?client=r1", {})
    assert status == 503 and "min_free_disk_mb" in json.loads(body)["error"]
    assert status_of(full)["recording"] == []
