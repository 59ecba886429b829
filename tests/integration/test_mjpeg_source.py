"""An HTTP MJPEG camera: registered, its stall said on the viewer's page, and retried.

The test runs a local MJPEG server (127.0.0.1, a free port) serving the synthetic overhead
camera's frames, and ``slamlens registration --source http://…`` as a real process. Frames
come through as they were served (no second encoding) and register the robot; when the
server stops sending on an open connection (a stalled camera), the viewer's status — what
its page shows under the picture — says the source was lost and is retried; when the server
sends again, frames flow again and the note goes.
"""

from __future__ import annotations

import http.server
import json
import threading
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import CameraFrame, Registration
from slamlens.services.harness.procs import spawn, stop
from slamlens.services.registration.calibration import save_calibration, synthetic_calibration
from slamlens.services.registration.synthetic import (
    ImagingSettings,
    SceneSettings,
    SyntheticCamera,
    fit_hfov_deg,
    overhead_pose,
)
from slamlens.services.visualiser.camera_sources import SourceWatch
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewerConfig
from slamlens.services.visualiser.web import WebServer
from tests.integration.test_registration_service import Inbox
from tests.waiting import wait_until

KEYS = Keys()
ROBOT, CAMERA = "r1", "top"
ARENA = (-1.0, -1.0, 2.0, 2.0)
W, H = 640, 360


class Camera:
    """The MJPEG server's state: its frames, and whether it sends them."""

    def __init__(self, jpegs: list[bytes]) -> None:
        self.jpegs = jpegs
        self.sending = threading.Event()
        self.sending.set()
        self.stop = threading.Event()
        self.served = 0


def make_server(camera: Camera) -> http.server.ThreadingHTTPServer:
    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            k = 0
            try:
                while not camera.stop.is_set():
                    if not camera.sending.is_set():  # stalled: the connection stays open
                        camera.stop.wait(0.05)
                        continue
                    jpeg = camera.jpegs[k % len(camera.jpegs)]
                    self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                     + str(len(jpeg)).encode() + b"\r\n\r\n" + jpeg + b"\r\n")
                    self.wfile.flush()
                    camera.served += 1
                    k += 1
                    camera.stop.wait(0.05)  # the camera's frame rate, 20 Hz
            except (BrokenPipeError, ConnectionResetError):
                pass

    return http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)


@pytest.fixture
def mjpeg_camera(tmp_path: Path) -> Iterator[tuple[str, Camera, Path]]:
    hfov = fit_hfov_deg(W, H, arena_xy=ARENA, height_m=3.0)
    calib = synthetic_calibration(W, H, hfov_deg=hfov)
    save_calibration(tmp_path / "top.yml", calib)
    cam = SyntheticCamera(calib.K, W, H, T_world_from_camera=overhead_pose(
        centre_xy=(0.5, 0.5), height_m=3.0, yaw_deg=8.0), scene=SceneSettings(),
        imaging=ImagingSettings(noise_sigma=2.0, blur_kernel=3))
    jpegs = [cv2.imencode(".jpg", cam.render(robot_pose=(0, 0, 0), frame_index=k))[1].tobytes()
             for k in range(4)]
    camera = Camera(jpegs)
    server = make_server(camera)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/stream.mjpg", camera, \
            tmp_path / "top.yml"
    finally:
        camera.stop.set()
        server.shutdown()
        server.server_close()


def sources_note(url: str) -> str:
    with urllib.request.urlopen(f"{url}/api/status", timeout=10) as r:
        return json.loads(r.read())["sources"].get(CAMERA, "")


def test_mjpeg_stream_registers_and_a_stall_is_shown_and_retried(
        make_client, router_endpoint, mjpeg_camera) -> None:
    url, camera, calibration = mjpeg_camera
    bus = make_client()
    viewer = ViewerService(bus, keys=KEYS, config=ViewerConfig(robot=ROBOT, camera=CAMERA))
    watch = SourceWatch(bus, KEYS, (CAMERA,), period_s=0.5)
    web = WebServer(viewer, host="127.0.0.1", port=0, sources=watch)
    viewer.start()
    watch.start()
    page = web.start()
    client = make_client()
    frames = Inbox(CameraFrame, client, KEYS.frame(CAMERA))
    regs = Inbox(Registration, client, KEYS.registration(CAMERA, ROBOT))
    proc = spawn("registration", "--source", url, "--camera", CAMERA, "--robot", ROBOT,
                 "--calibration", str(calibration), "--stall-s", "1",
                 "--reconnect-max-s", "0.5", "--connect", router_endpoint)
    try:
        proc.wait_for_line("registration ready", timeout=60)
        wait_until(lambda: len(regs) >= 1, timeout=60)  # the robot's marker registered it
        first = frames.last()
        assert first.data in camera.jpegs and (first.width, first.height) == (W, H)
        assert sources_note(page) == ""

        camera.sending.clear()  # the camera stalls: the connection stays open, silent
        wait_until(lambda: "source lost" in sources_note(page), timeout=60)
        note = sources_note(page)
        assert "stalled" in note and "retrying" in note, note

        camera.sending.set()  # back: reopened, frames again, the note goes
        count = len(frames)
        wait_until(lambda: len(frames) > count + 5 and sources_note(page) == "", timeout=60)
        assert frames.last().data in camera.jpegs
    finally:
        out, err = stop(proc)
        web.stop()
        watch.stop()
        viewer.stop()
    assert "Traceback" not in err, err[-3000:]
    assert "lost:" in err and "is back" in err, err[-3000:]  # one line each way
    assert np.isfinite(regs.last().reprojection_error_px)
