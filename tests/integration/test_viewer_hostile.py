"""Well-formed but hostile input to a real ``slamlens viewer`` process.

* a decode bomb on the camera's frame key: a JPEG of a few hundred bytes whose header
  claims 20000 × 20000 pixels (1.2 GB once decoded). The viewer reads the header's size
  before decoding and refuses it; its peak memory (``VmHWM``, reset with
  ``/proc/PID/clear_refs``) stays within 1.5 × its idle ``VmRSS``;
* requests the web server refuses (a nested JSON body, an oversized body, request line,
  header or websocket message): each a 4xx and one log line with the reason, never a
  traceback, and the viewer goes on serving.
"""

from __future__ import annotations

import asyncio
import json
import socket
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import cv2
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import CameraFrame, Registration
from slamlens.services.harness.procs import Service, spawn, stop
from slamlens.services.harness.web_client import http, post_json
from slamlens.services.visualiser.jpeg import JpegError, jpeg_size
from tests.routes import put_until_seen
from tests.waiting import wait_until

KEYS = Keys()
ROBOT, CAMERA = "robot1", "top"
WIDTH, HEIGHT = 800, 600


def registration() -> Registration:
    K = np.array([[600.0, 0, WIDTH / 2], [0, 600.0, HEIGHT / 2], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.diag([1.0, -1.0, -1.0]), [-1.5, 1.5, 3.0]
    return Registration(camera=CAMERA, robot=ROBOT, stamp=0.0, K=K, dist=np.zeros(5),
                        width=WIDTH, height=HEIGHT, T_camera_from_map=T,
                        reprojection_error_px=0.3)


def jpeg(width: int, height: int) -> bytes:
    image = np.full((height, width, 3), (120, 100, 80), np.uint8)
    ok, data = cv2.imencode(".jpg", image)
    assert ok
    return data.tobytes()


def bomb(width: int, height: int) -> bytes:
    """A 16 × 16 JPEG whose frame header (SOF0) says ``width`` × ``height``."""
    data = bytearray(jpeg(16, 16))
    at = data.find(b"\xff\xc0")  # FF C0, length (2), precision (1), height (2), width (2)
    assert at > 0
    data[at + 5:at + 7] = height.to_bytes(2, "big")
    data[at + 7:at + 9] = width.to_bytes(2, "big")
    return bytes(data)


def frame(seq: int, data: bytes, width: int = WIDTH, height: int = HEIGHT) -> bytes:
    return CameraFrame(camera=CAMERA, seq=seq, stamp=0.1 * seq, encoding="jpeg", width=width,
                       height=height, data=data).to_bytes()


def memory_mb(pid: int) -> dict[str, float]:
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text()
                  .splitlines() if ":" in line)
    return {k: int(fields[k].split()[0]) / 1024 for k in ("VmRSS", "VmHWM")}


@pytest.fixture
def viewer(router_endpoint: str, tmp_path: Path) -> Iterator[tuple[Service, str]]:
    proc = spawn("viewer", "--robot", ROBOT, "--camera", CAMERA, "--connect", router_endpoint,
                 "--http", "127.0.0.1:0", "--late-join-timeout-s", "0",
                 "--recordings-dir", str(tmp_path / "recordings"))
    try:
        url = proc.wait_for_line("viewer ready").split()[-1]
        yield proc, url
    finally:
        if proc.poll() is None:
            stop(proc)


def status_of(url: str) -> dict:
    code, _, body = http(url + "/api/status")
    assert code == 200, body
    return json.loads(body)


def test_the_jpeg_header_size_is_read_without_decoding() -> None:
    assert jpeg_size(jpeg(800, 600)) == (800, 600)
    assert jpeg_size(bomb(20000, 20000)) == (20000, 20000)
    progressive = cv2.imencode(".jpg", np.zeros((37, 53, 3), np.uint8),
                               [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    assert jpeg_size(progressive) == (53, 37)  # SOF2
    for bad in (b"", b"\xff\xd8", b"GIF89a....", jpeg(8, 8)[:20], b"\xff\xd8\xff\xda\x00\x02"):
        with pytest.raises(JpegError):
            jpeg_size(bad)


def test_a_decode_bomb_on_the_frame_key_is_refused_before_decoding(viewer, make_client) -> None:
    proc, url = viewer
    bus = make_client()
    reg_pub = bus.publisher(KEYS.registration(CAMERA, ROBOT))
    frame_pub = bus.publisher(KEYS.frame(CAMERA), latest_wins=True)
    assert reg_pub.wait_matched(10.0) and frame_pub.wait_matched(10.0)  # type: ignore[attr-defined]
    # the first frame is put until shown: a matched route may still drop samples for a
    # few hundred ms on a loaded machine (zenoh 1.10)
    put_until_seen(lambda: frame_pub.put(frame(1, jpeg(WIDTH, HEIGHT))),
                   lambda: (status_of(url)["cameras"][0]["frame"] or {}).get("seq") == 1,
                   what="the first frame")
    assert http(url + "/snapshot.png")[0] == 200  # rendered once: the idle working set

    idle = memory_mb(proc.pid)["VmRSS"]
    Path(f"/proc/{proc.pid}/clear_refs").write_text("5")  # VmHWM := VmRSS from here on
    refused = 0

    def send_bomb(header: tuple[int, int], says: tuple[int, int]) -> None:
        nonlocal refused
        data = bomb(*header)
        assert len(data) < 1000
        frame_pub.put(frame(2 + refused, data, *says))
        refused += 1
        wait_until(lambda: status_of(url)["bad_messages"].get(f"frame {CAMERA}") == refused)

    # (the JPEG header's size, the size the message says)
    send_bomb((20000, 20000), (WIDTH, HEIGHT))  # a lie: refused, header and message differ
    send_bomb((20000, 20000), (20000, 20000))  # not registered yet: the configured bound
    reg_pub.put(registration().to_bytes())
    wait_until(lambda: status_of(url)["cameras"][0]["registration"] is not None)
    send_bomb((3000, 3000), (3000, 3000))  # under that bound, but 4 × the registered size
    reasons = ["the JPEG header says 20000×20000 pixels, the message 800×600",
               "a 20000×20000 JPEG has more pixels than 16777216 (max_frame_pixels",
               "a 3000×3000 JPEG has more pixels than 1920000 (4 × the registered 800×600"]
    frame_pub.put(frame(10, jpeg(WIDTH, HEIGHT)))  # and the camera goes on
    wait_until(lambda: status_of(url)["cameras"][0]["frame"]["seq"] == 10)

    peak = memory_mb(proc.pid)["VmHWM"]
    assert peak <= 1.5 * idle, f"peak {peak:.0f} MB against {idle:.0f} MB idle"
    out, err = stop(proc)
    for reason in reasons:
        assert sum(reason in line for line in err.splitlines()) == 1, (reason, err[-2000:])
    assert "Traceback" not in err
    # its last line says what it did: the bombs counted against the camera
    last = out.strip().splitlines()[-1]
    assert last.startswith("viewer stopped: "), out[-500:]
    final = json.loads(last.removeprefix("viewer stopped: "))
    assert final["cameras"] == [CAMERA] and final["bad_messages"] == {f"frame {CAMERA}": 3}


async def _oversized_websocket_message(url: str) -> aiohttp.WSMessage:
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(url.replace("http://", "ws://") + "/ws?client=big",
                                      max_msg_size=0) as ws:
            await ws.send_str("x" * 100_000)
            while True:  # frames may come first; then the server closes
                msg = await ws.receive(timeout=10)
                if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED,
                                aiohttp.WSMsgType.CLOSING):
                    return msg


def raw_request(url: str, data: bytes) -> bytes:
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(data)
        return s.recv(200)


def test_refused_requests_are_one_line_each_never_a_traceback(viewer) -> None:
    proc, url = viewer
    nested = b"[" * 30_000 + b"]" * 30_000  # inside the body bound, past the JSON parser's
    status, _, body = http(url + "/api/settings?client=t1", method="POST", body=nested)
    assert status == 400 and "nested" in json.loads(body)["error"]
    nested_object = b'{"a":' * 5_000 + b'1' + b"}" * 5_000
    status, _, body = http(url + "/api/settings?client=t1", method="POST", body=nested_object)
    assert status == 400, body
    status, _, body = post_json(url + "/api/settings?client=t1", {"colour_robot": [[[1]]]})
    assert status == 400 and "colour_robot" in json.loads(body)["error"]
    status, _, body = http(url + "/api/settings?client=t1", method="POST",
                           body=b'{"mode": "' + b"x" * 100_000 + b'"}')
    assert status == 413, body
    host = url.removeprefix("http://")
    reply = raw_request(url, b"GET /" + b"a" * 20_000 + f" HTTP/1.1\r\nHost: {host}\r\n\r\n"
                        .encode())
    assert reply.startswith(b"HTTP/1.") and b" 400 " in reply.split(b"\r\n")[0]
    reply = raw_request(url, f"GET / HTTP/1.1\r\nHost: {host}\r\nX-Big: ".encode()
                        + b"a" * 20_000 + b"\r\n\r\n")
    assert b" 400 " in reply.split(b"\r\n")[0]
    closed = asyncio.run(_oversized_websocket_message(url))
    assert closed.type == aiohttp.WSMsgType.CLOSE and closed.data == 1009  # message too big

    status = status_of(url)  # still serving, and it counted every refusal
    assert status["refused"] == {"web request": 4, "web http": 2, "web websocket": 1}
    assert json.loads(http(url + "/api/settings?client=t1")[2])["settings"]["mode"] == "all"
    _, err = stop(proc)
    assert "Traceback" not in err, err[-3000:]
    lines = [line for line in err.splitlines() if "dropped bad web" in line]
    assert len(lines) == 7, err[-3000:]
    assert sum("nested this deep" in line for line in lines) == 2
    assert sum("8190 bytes" in line for line in lines) == 2
    assert sum("exceeds limit" in line for line in lines) == 1
