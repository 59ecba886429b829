"""``slamlens registration --source browser`` as a real process over real Zenoh on loopback.

The test plays the viewer's AR page: it publishes the frames of the synthetic head-mounted
camera's walk (services/harness/ar_video.py) on ``slamlens/camera/C/capture`` and checks what comes
back against the pose each frame was rendered from: registrations of every frame, a second
camera at once (starting from the first one's registration), bad frames refused and
counted while the service goes on, a third camera beyond the limit refused, and a camera
that stops sending released (its liveliness token gone).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import CameraFrame, CameraPose, Registration
from slamlens.services.harness.ar_video import Video, render_walk, truth_pixels, write_calibration
from slamlens.services.harness.procs import spawn, stop
from tests.integration.test_registration_service import Inbox
from tests.routes import put_until_seen
from tests.waiting import wait_until

KEYS = Keys()
ROBOT = "r1"


@pytest.fixture(scope="module")
def video() -> Video:
    return render_walk(16, arc_deg=30.0)


def frame_bytes(video: Video, camera: str, i: int, stamp: float, *, quality: int = 85) -> bytes:
    ok, jpeg = cv2.imencode(".jpg", video.frames[i], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    h, w = video.frames[i].shape[:2]
    return CameraFrame(camera=camera, seq=i + 1, stamp=stamp, encoding="jpeg", width=w,
                       height=h, data=jpeg.tobytes()).to_bytes()


def feature_error_px(video: Video, i: int, reg: Registration) -> float:
    """Largest distance between the landmarks projected through the registration and
    through the frame's true pose (cv2.projectPoints both, the true intrinsics)."""
    points = np.column_stack([video.landmarks, np.zeros(len(video.landmarks))])
    T = np.asarray(reg.T_camera_from_map)
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, T[:3, 3], np.asarray(reg.K),
                              np.asarray(reg.dist))
    return float(np.abs(uv.reshape(-1, 2) - truth_pixels(video, i, points)).max())


def send_and_wait(pub, inbox: Inbox, payload: bytes, stamp: float,
                  matched: Callable[[object], bool] | None = None) -> object:
    """Put one frame until the message of that very frame (its stamp) comes back."""
    def seen() -> object:
        return next((m for m in inbox.all() if abs(m.stamp - stamp) < 1e-9
                     and (matched is None or matched(m))), None)
    put_until_seen(lambda: pub.put(payload), seen, what=f"frame {stamp}", timeout_s=60)
    return seen()


def test_browser_cameras_register_leave_and_refuse(make_client, router_endpoint,
                                                   tmp_path: Path, video: Video) -> None:
    calibration = write_calibration(video, tmp_path / "phone.yml")
    proc = spawn("registration", "--source", "browser", "--mode", "head-mounted",
                 "--camera", "phone", "--robot", ROBOT, "--calibration", str(calibration),
                 "--browser-idle-s", "1.5", "--max-browser-cameras", "2",
                 "--connect", router_endpoint)
    try:
        proc.wait_for_line("registration ready", timeout=60)
        client = make_client()
        regs = {c: Inbox(Registration, client, KEYS.registration(c, ROBOT))
                for c in ("phone-a", "phone-b")}
        poses = Inbox(CameraPose, client, KEYS.camera_pose("phone-a"))
        pub_a = client.publisher(KEYS.capture("phone-a"), latest_wins=True)
        pub_b = client.publisher(KEYS.capture("phone-b"), latest_wins=True)
        assert pub_a.wait_matched() and pub_b.wait_matched()  # type: ignore[attr-defined]

        # camera a: the robot stands at its map origin; the first frames register it
        t0 = time.time()
        stamp = t0
        for i in range(6):
            stamp = t0 + 0.1 * i
            send_and_wait(pub_a, poses, frame_bytes(video, "phone-a", i, stamp), stamp)
        errors = []
        for i in range(6, 16):
            stamp = t0 + 0.1 * i
            reg = send_and_wait(pub_a, regs["phone-a"], frame_bytes(video, "phone-a", i, stamp),
                                stamp)
            errors.append(feature_error_px(video, i, reg))  # type: ignore[arg-type]
        # each frame's own registration, through the board: the page's target is 3 px
        assert max(errors) < 3.0 and float(np.median(errors)) < 1.0, errors

        # camera b at the same time: its own camera, registered from a's registration
        reg_b = send_and_wait(pub_b, regs["phone-b"],
                              frame_bytes(video, "phone-b", 10, t0 + 5.0), t0 + 5.0)
        assert reg_b.camera == "phone-b" and reg_b.reason == "from camera phone-a"  # type: ignore
        assert feature_error_px(video, 10, reg_b) < 3.0  # type: ignore[arg-type]
        assert set(client.alive(KEYS.any_camera_alive())) >= {
            KEYS.camera_alive("phone-a"), KEYS.camera_alive("phone-b")}

        # bad frames: refused, counted, and camera a goes on with the next good one
        good = video.frames[3]
        ok, jpeg = cv2.imencode(".jpg", good)
        bomb = bytearray(jpeg.tobytes())
        sof = bomb.index(b"\xff\xc0")
        bomb[sof + 5:sof + 9] = (20000).to_bytes(2, "big") * 2  # claims 20000x20000
        for payload in (b"garbage", CameraFrame(camera="phone-a", seq=1, stamp=1.0,
                                                encoding="jpeg", width=20000, height=20000,
                                                data=bytes(bomb)).to_bytes(),
                        CameraFrame(camera="phone-a", seq=1, stamp=1.0, encoding="jpeg",
                                    width=1280, height=720,
                                    data=jpeg.tobytes()[:600] + b"\0" * 100).to_bytes(),
                        CameraFrame(camera="phone-a", seq=1, stamp=1.0, encoding="jpeg",
                                    width=640, height=360, data=jpeg.tobytes()).to_bytes()):
            pub_a.put(payload)
        stamp = t0 + 6.0
        send_and_wait(pub_a, regs["phone-a"], frame_bytes(video, "phone-a", 12, stamp), stamp)

        # a third camera beyond --max-browser-cameras 2: refused
        pub_c = client.publisher(KEYS.capture("phone-c"), latest_wins=True)
        assert pub_c.wait_matched()  # type: ignore[attr-defined]
        pub_c.put(frame_bytes(video, "phone-c", 0, t0 + 7.0))

        # camera b stops sending: released (its liveliness token goes) while a stays
        def b_gone() -> bool:
            pub_a.put(frame_bytes(video, "phone-a", 13, time.time()))  # a keeps sending
            return KEYS.camera_alive("phone-b") not in client.alive(KEYS.any_camera_alive())
        wait_until(b_gone, timeout=30.0)
        assert KEYS.camera_alive("phone-a") in client.alive(KEYS.any_camera_alive())
    finally:
        out, err = stop(proc)
    summary = json.loads(out.split("registration stopped: ", 1)[1].splitlines()[0])
    refused = summary["browser"]["refused"]
    # garbage, a decode bomb and a size mismatch are refused on arrival; the undecodable
    # JPEG when read, unless a newer frame replaced it first (then it is skipped unread)
    assert refused.get("browser frame", 0) >= 3, (refused, err[-3000:])
    assert refused.get("browser camera", 0) >= 1, refused
    assert summary["browser"]["joined"] == 2 and summary["browser"]["left"] >= 1, summary
    assert "camera phone-b: left" in err
    assert "Traceback" not in err, err[-3000:]
