"""The AR page's websocket against bad pages: refused, counted, bounded, and freed.

A real viewer (in-process, real Zenoh on loopback, aiohttp on a free port) and aiohttp
websocket clients playing pages: garbage, a decode bomb, an oversized frame, frames faster
than allowed, a camera name taken or not the viewer's; every refusal is answered and
counted, the session keeps at most a few frames whatever a page sends, and a page that
leaves frees its camera (its session, thread and publisher). No registration service
runs: frames come back as they went, with the note saying why.
"""

from __future__ import annotations

import asyncio
import json
import threading
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import cv2
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import CameraFrame, SlamState
from slamlens.services.visualiser.ar import KEPT_FRAMES, ArHub, ArLimits
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewerConfig
from slamlens.services.visualiser.web import WebServer

KEYS = Keys()
ROBOT = "robot1"


@pytest.fixture
def viewer(make_client, tmp_path: Path) -> Iterator[tuple[str, ArHub]]:
    bus = make_client()
    service = ViewerService(bus, keys=KEYS, config=ViewerConfig(robot=ROBOT,
                                                                recordings_dir=str(tmp_path)))
    service.start()
    hub = ArHub(bus, KEYS, service.api, base_camera="phone",
                limits=ArLimits(max_cameras=2, max_frame_bytes=200_000, max_fps=1.0,
                                wait_s=0.2))
    web = WebServer(service, host="127.0.0.1", port=0, ar=hub)
    url = web.start()
    yield url, hub
    web.stop()
    service.stop()


def jpeg(width: int = 320, height: int = 240) -> bytes:
    image = np.full((height, width, 3), 90, np.uint8)
    return cv2.imencode(".jpg", image)[1].tobytes()


def status(url: str) -> dict:
    with urllib.request.urlopen(f"{url}/api/status", timeout=10) as r:
        return json.loads(r.read())


async def next_json(ws: aiohttp.ClientWebSocketResponse) -> dict:
    while True:
        msg = await asyncio.wait_for(ws.receive(), 30)
        if msg.type == aiohttp.WSMsgType.TEXT:
            return json.loads(msg.data)
        assert msg.type == aiohttp.WSMsgType.BINARY, msg


def show_a_robot(make_client, hub) -> None:
    """A robot's state, put until the viewer shows the robot (a page can ask for it then)."""
    pub = make_client().publisher(KEYS.state(ROBOT))
    assert pub.wait_matched()  # type: ignore[attr-defined]
    n = 2
    state = SlamState(robot=ROBOT, seq=1, stamp=0.1, step="update", pose=np.zeros(3),
                      landmark_ids=np.arange(n), landmarks=np.zeros((n, 2)),
                      covariance=np.eye(3 + 2 * n))
    seen = threading.Event()
    while not seen.is_set():
        pub.put(state.to_bytes())
        if hub.api.robot_names():
            seen.set()
        seen.wait(0.1)


def test_bad_pages_are_refused_counted_and_freed(viewer, make_client) -> None:
    url, hub = viewer
    ws_url = url.replace("http", "ws") + "/ar/ws?client=page1&camera=phone-1"
    show_a_robot(make_client, hub)
    captured: list[CameraFrame] = []
    make_client().subscribe(KEYS.capture("phone-1"),
                            lambda k, p: captured.append(CameraFrame.from_bytes(p)))

    async def run() -> None:
        async with aiohttp.ClientSession() as http:
            # names: not this viewer's, then taken
            async with http.get(url.replace("http", "ws") + "/ar/ws?client=x&camera=cam9",
                                headers={"Upgrade": "websocket", "Connection": "Upgrade",
                                         "Sec-WebSocket-Version": "13",
                                         "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ=="}
                                ) as r:
                assert r.status == 409 and "named phone" in (await r.json())["error"]
            async with http.ws_connect(ws_url) as ws:
                with pytest.raises(aiohttp.WSServerHandshakeError) as taken:
                    await http.ws_connect(ws_url)
                assert taken.value.status == 409
                # a good frame comes back (no registration service: as it went, with why)
                await ws.send_str(json.dumps({"tag": 1}))
                await ws.send_bytes(jpeg())
                header = await next_json(ws)
                assert header["tag"] == 1 and header["overlay"] is False
                assert "registered" in header["note"]
                # garbage, a decode bomb: refused, each answered
                bomb = bytearray(jpeg())
                sof = bomb.index(b"\xff\xc0")
                bomb[sof + 5:sof + 9] = (20000).to_bytes(2, "big") * 2
                for bad in (b"not a jpeg", bytes(bomb)):
                    await ws.send_bytes(bad)
                    assert "refused" in await next_json(ws)
                # faster than max_fps (1 Hz, burst 2): refused; the session keeps few frames
                refused = 0
                for _ in range(30):
                    await ws.send_bytes(jpeg())
                for _ in range(30):
                    message = await next_json(ws)
                    refused += "refused" in message
                    if refused and len(hub.sessions[0]._frames) <= KEPT_FRAMES:
                        break
                assert refused >= 1
                assert len(hub.sessions[0]._frames) <= KEPT_FRAMES
                # an oversized frame: the websocket closes (1009), counted
                await ws.send_bytes(b"\xff\xd8" + b"\0" * 300_000)
                msg = await asyncio.wait_for(ws.receive(), 30)
                while msg.type in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY):
                    msg = await asyncio.wait_for(ws.receive(), 30)
                assert msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED,
                                    aiohttp.WSMsgType.CLOSING)

    asyncio.run(run())
    # the page left: its camera is freed (session, thread, publisher)
    deadline_status = status(url)
    for _ in range(300):
        if not hub.sessions:
            break
        deadline_status = status(url)
        threading.Event().wait(0.05)
    assert hub.sessions == [] and hub.closed == 1, deadline_status
    assert not any(t.name == "viewer-ar-phone-1" for t in threading.enumerate())
    s = status(url)
    assert s["ar"]["refused"]["ar frame"] >= 2 and s["ar"]["refused"]["ar rate"] >= 1
    assert s["refused"]["web ar camera"] >= 2 and s["refused"]["web websocket"] >= 1
    assert captured and all(f.camera == "phone-1" for f in captured)  # on the bus
