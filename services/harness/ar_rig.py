"""The AR page's test rig (tests and benchmarks): a registration service for browser
cameras (a real process), a viewer with the AR page (in-process), the robot's state, and
Debian's Chromium whose fake camera plays the head-mounted walk (:mod:`ar_video`); and the
check of what the page shows against the truth (:func:`cone_offsets`).
"""

from __future__ import annotations

import base64
import json
import os
import threading
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamlens.common.errors import ConfigError
from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState
from slamlens.services.harness.ar_video import Video, write_calibration, write_y4m
from slamlens.services.harness.procs import Service, spawn, stop
from slamlens.services.visualiser.ar import ArHub, ArLimits
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewerConfig, ViewSettings
from slamlens.services.visualiser.web import WebServer

CHROMIUM = os.environ.get("SLAMLENS_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync",
                 "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream"]
KEYS = Keys()
ROBOT = "robot1"
CYAN = (255, 255, 0)  #: BGR of the cones in the check: no such colour in the video
#: only the feature cones, in CYAN: what the check measures
CONES_ONLY = {"robot": False, "path": False, "lines": False, "ellipsoids": False,
              "legend": False, "labels": False, "health": False, "rejected": False,
              "features": True, "colour_features": list(CYAN)}


def paper_state(video: Video, seq: int) -> SlamState:
    """The estimator's belief as the truth: the robot at its map origin, the true map."""
    n = len(video.landmarks)
    return SlamState(robot=ROBOT, seq=seq, stamp=0.1 * seq, step="update", pose=np.zeros(3),
                     landmark_ids=video.ids, landmarks=video.landmarks,
                     covariance=np.eye(3 + 2 * n) * 0.02 ** 2)


@dataclass
class ArRig:
    url: str
    video: Video
    y4m: Path
    registration: Service | None


def start_rig(make_client, router_endpoint: str, tmp_path: Path, video: Video, *,
              calibrated: bool = True, registration: bool = True,
              limits: ArLimits | None = None) -> Iterator[ArRig]:
    """Registration (a process), a viewer with the AR page, the robot's state at 10 Hz."""
    y4m = write_y4m(video, tmp_path / "walk.y4m")
    args = ["registration", "--source", "browser", "--mode", "head-mounted", "--camera",
            "phone", "--robot", ROBOT, "--connect", router_endpoint]
    if calibrated:
        args += ["--calibration", str(write_calibration(video, tmp_path / "phone.yml"))]
    service_proc = spawn(*args) if registration else None
    if service_proc is not None:
        service_proc.wait_for_line("registration ready", timeout=60)
    bus = make_client()
    service = ViewerService(bus, keys=KEYS, config=ViewerConfig(
        robot=ROBOT, recordings_dir=str(tmp_path)))
    service.start()
    hub = ArHub(bus, KEYS, service.api, base_camera="phone", limits=limits)
    web = WebServer(service, host="127.0.0.1", port=0, ar=hub)
    url = web.start()
    publisher = make_client().publisher(KEYS.state(ROBOT))
    assert publisher.wait_matched()  # type: ignore[attr-defined]
    done = threading.Event()

    def drive() -> None:
        seq = 1
        while not done.is_set():
            publisher.put(paper_state(video, seq).to_bytes())
            seq += 1
            done.wait(0.1)  # pacing: an estimator at 10 states a second

    driver = threading.Thread(target=drive, daemon=True)
    driver.start()
    try:
        yield ArRig(url, video, y4m, service_proc)
    finally:
        done.set()
        driver.join()
        web.stop()
        service.stop()
        if service_proc is not None:
            stop(service_proc)


def open_ar_page(y4m: Path, url: str, *, camera: str = "phone-test",
                 query: str = "") -> tuple[Any, ...]:
    """Chromium with the video as its camera, on the AR page; (playwright, browser, page)."""
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        raise ConfigError(f"Chromium is needed for the AR page's test rig and {CHROMIUM} "
                          "does not exist (install Debian's chromium, or set "
                          "SLAMLENS_CHROMIUM)")
    p = sync_playwright().start()
    browser = p.chromium.launch(executable_path=CHROMIUM, args=[
        *CHROMIUM_ARGS, f"--use-file-for-fake-video-capture={y4m}"])
    page = browser.new_context(viewport={"width": 1400, "height": 900}).new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(f"{url}/ar?camera={camera}{query}")
    page.wait_for_function("window.slamlensAr && window.slamlensAr.camera", timeout=15000)
    return p, browser, page, errors


def post_settings(url: str, client: str, changes: dict) -> dict:
    request = urllib.request.Request(f"{url}/api/ar/settings?client={client}",
                                     data=json.dumps(changes).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=10) as r:
        return json.loads(r.read())["settings"]


def shown_picture(page: Any) -> tuple[np.ndarray, dict]:
    """The picture on the page's canvas now (BGR) and the header of its frame."""
    data = page.evaluate("""() => ({png: document.getElementById('arview').toDataURL('image/png'),
                                    last: window.slamlensAr.last})""")
    raw = base64.b64decode(data["png"].split(",", 1)[1])
    image = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ConfigError("the page's canvas is not a PNG")
    return image, data["last"]


def cyan_mask(image: np.ndarray) -> np.ndarray:
    b, g, r = (image[..., k].astype(int) for k in range(3))
    return ((np.minimum(b, g) - r > 90) & (np.abs(b - g) < 60)).astype(np.uint8)


def as_shown(image: np.ndarray) -> np.ndarray:
    """What the page shows of a picture: the viewer's JPEG of it (quality 80) — its chroma
    subsampling blurs colour edges, so a reference is compared after the same."""
    _, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
    shown = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
    assert shown is not None
    return np.asarray(shown)


def cone_offsets(video: Video, index: int, shown: np.ndarray) -> list[float]:
    """Per feature cone in view: how far (px) its pixels in ``shown`` lie from where the
    same cone lands drawn through frame ``index``'s true camera (centroid of its cyan
    pixels in a box around it)."""
    truth = CameraModel(K=video.calib.K, dist=video.calib.dist, width=video.calib.width,
                        height=video.calib.height,
                        T_camera_from_map=np.linalg.inv(video.poses[index]))
    settings = ViewSettings().replace(**{k: (tuple(v) if isinstance(v, list) else v)
                                         for k, v in CONES_ONLY.items()})
    reference = as_shown(Renderer().render(as_shown(video.frames[index]),
                                           state=paper_state(video, 1), camera=truth,
                                           settings=settings))
    ref, got = cyan_mask(reference), cyan_mask(shown)
    count, _, stats, _ = cv2.connectedComponentsWithStats(ref)
    offsets = []
    for k in range(1, count):
        x, y, w, h, area = stats[k]
        if area < 40:
            continue
        y0, y1, x0, x1 = max(0, y - 8), y + h + 8, max(0, x - 8), x + w + 8
        r_box, g_box = ref[y0:y1, x0:x1], got[y0:y1, x0:x1]
        if g_box.sum() < 0.5 * r_box.sum():
            offsets.append(float("inf"))  # the cone is not where it should be
            continue
        ys, xs = np.nonzero(r_box)
        gy, gx = np.nonzero(g_box)
        offsets.append(float(np.hypot(gx.mean() - xs.mean(), gy.mean() - ys.mean())))
    return offsets
