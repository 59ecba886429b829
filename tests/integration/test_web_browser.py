"""The web viewer in a real headless Chromium (Debian's /usr/bin/chromium via Playwright).

A live viewer service on loopback Zenoh gets states from the test (the robot drives, so
every state looks different); the page must load, show a moving picture, change it when
the mode changes, select a feature by clicking it, and keep settings per browser tab.
Chromium missing is a failure with a clear message, never a skip.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from common.keys import Keys
from common.messages import SlamState
from services.visualiser.service import ViewerService
from services.visualiser.settings import ViewerConfig
from services.visualiser.web import WebServer

CHROMIUM = os.environ.get("SLAMLENS_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
KEYS = Keys()
ROBOT = "robot1"
# two clusters of three features
LANDMARKS = np.array([[0.5, 0.5], [0.9, 0.5], [0.7, 0.85],
                      [2.3, 2.3], [2.7, 2.3], [2.5, 2.65]])
IDS = np.arange(20, 26)


def state(seq: int) -> SlamState:
    n = len(LANDMARKS)
    P = np.eye(3 + 2 * n) * 0.05 ** 2
    angle = 0.15 * seq  # the robot drives a circle: every picture differs
    pose = np.array([1.5 + 0.6 * math.cos(angle), 1.5 + 0.6 * math.sin(angle), angle + 1.57])
    return SlamState(robot=ROBOT, seq=seq, stamp=0.1 * seq, step="update", pose=pose,
                     landmark_ids=IDS, landmarks=LANDMARKS, covariance=P)


TOKEN = "browser-token-0123456789abcdef"


@pytest.fixture
def live_viewer(make_client, tmp_path: Path) -> Iterator[str]:
    """A viewer (map view) at a URL, fed 10 states a second until the test ends."""
    yield from _live_viewer(make_client, tmp_path, token=None)


@pytest.fixture
def live_viewer_with_token(make_client, tmp_path: Path) -> Iterator[str]:
    """The same, asking every request for TOKEN (as a viewer bound beyond loopback)."""
    yield from _live_viewer(make_client, tmp_path, token=TOKEN)


def _live_viewer(make_client, tmp_path: Path, *, token: str | None) -> Iterator[str]:
    service = ViewerService(make_client(), keys=KEYS, config=ViewerConfig(
        robot=ROBOT, recordings_dir=str(tmp_path)))
    service.start()
    web = WebServer(service, host="127.0.0.1", port=0, token=token)
    url = web.start()
    publisher = make_client().publisher(KEYS.state(ROBOT))
    time.sleep(0.3)
    stop = threading.Event()

    def drive() -> None:
        seq = 1
        while not stop.is_set():
            publisher.put(state(seq).to_bytes())
            seq += 1
            stop.wait(0.1)

    driver = threading.Thread(target=drive, daemon=True)
    driver.start()
    try:
        yield url
    finally:
        stop.set()
        driver.join()
        web.stop()
        service.stop()


@pytest.fixture
def browser() -> Iterator:
    from playwright.sync_api import Error, sync_playwright

    if not Path(CHROMIUM).exists():
        pytest.fail(f"Chromium is needed for the browser test and {CHROMIUM} does not exist "
                    "(install Debian's chromium, or set SLAMLENS_CHROMIUM)")
    with sync_playwright() as p:
        try:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        except Error as exc:
            pytest.fail(f"Chromium at {CHROMIUM} did not start: {exc}")
        try:
            yield browser
        finally:
            browser.close()


def open_page(browser, url: str, errors: list[str], *, path: str = "/"):
    page = browser.new_context(viewport={"width": 1600, "height": 1000}).new_page()
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(url + path)
    page.wait_for_function("window.slamlens && window.slamlens.frames >= 2", timeout=15000)
    return page


def settings_of(url: str, client: str) -> dict:
    with urllib.request.urlopen(f"{url}/api/settings?client={client}", timeout=10) as r:
        return json.loads(r.read())["settings"]


def features(url: str) -> dict:
    with urllib.request.urlopen(f"{url}/api/features", timeout=10) as r:
        return json.loads(r.read())


def red_on_canvas(page, u: float, v: float, half: int = 5) -> int:
    """Red-dominant pixels of the page's video canvas around image pixel (u, v)."""
    return page.evaluate("""([u, v, h]) => {
        const c = document.getElementById('video');
        const d = c.getContext('2d').getImageData(Math.round(u) - h, Math.round(v) - h,
                                                  2 * h + 1, 2 * h + 1).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4) {
            const r = d[i], g = d[i + 1], b = d[i + 2];
            if (r > 100 && r > 1.5 * g && r > 1.5 * b) n++;
        }
        return n;
    }""", [u, v, half])


def wait_for_frames(page, more: int = 2) -> None:
    now = page.evaluate("window.slamlens.frames")
    page.wait_for_function(f"window.slamlens.frames >= {now + more}", timeout=15000)


def test_the_page_shows_a_live_view_with_per_tab_settings(live_viewer, browser) -> None:
    url = live_viewer
    errors: list[str] = []
    page = open_page(browser, url, errors)
    assert page.title() == "slamlens viewer"
    page.wait_for_function(
        "document.getElementById('status').textContent.includes('state seq')", timeout=10000)
    assert "robot robot1" in page.text_content("#status")

    # the video updates while states change
    first = page.locator("#video").screenshot()
    frames_before = page.evaluate("window.slamlens.frames")
    seq_before = page.evaluate("window.slamlens.seq")
    wait_for_frames(page, 5)
    assert page.evaluate("window.slamlens.seq") > seq_before
    assert page.evaluate("window.slamlens.frames") >= frames_before + 5
    assert page.locator("#video").screenshot() != first

    # where the pairs are in the picture (map view: the top-down camera is affine on the
    # floor, so a pair's midpoint projects to the midpoint of its features' pixels)
    uv = np.array(features(url)["uv"], dtype=float)
    intra = (uv[0] + uv[1]) / 2  # a pair inside one cluster
    inter = (uv[1] + uv[4]) / 2  # a pair across clusters
    assert red_on_canvas(page, *intra) >= 40
    assert red_on_canvas(page, *inter) >= 40

    # a second browser (its own sessionStorage) gets its own client id and settings
    other = open_page(browser, url, errors)
    client_a = page.evaluate("window.slamlens.client")
    client_b = other.evaluate("window.slamlens.client")
    assert client_a != client_b

    # mode change in tab A: intra-cluster glyphs disappear from A's video only
    page.select_option("select[name=mode]", "inter")
    page.wait_for_function("window.slamlens.settings.mode === 'inter'", timeout=10000)
    wait_for_frames(page)
    assert red_on_canvas(page, *intra) == 0
    assert red_on_canvas(page, *inter) >= 40
    assert settings_of(url, client_a)["mode"] == "inter"
    assert settings_of(url, client_b)["mode"] == "all"
    wait_for_frames(other)
    assert red_on_canvas(other, *intra) >= 40
    assert other.evaluate("window.slamlens.settings.mode") == "all"

    # click feature 25 in tab B: only its pairs remain (pair 20-21 goes away)
    box = other.locator("#video").bounding_box()
    size = other.evaluate("[document.getElementById('video').width, "
                          "document.getElementById('video').height]")
    u, v = uv[5]
    other.mouse.click(box["x"] + u * box["width"] / size[0],
                      box["y"] + v * box["height"] / size[1])
    other.wait_for_function("window.slamlens.settings.selected_feature === 25", timeout=10000)
    assert other.input_value("#feature") == "25"
    wait_for_frames(other)
    assert red_on_canvas(other, *intra) == 0
    assert red_on_canvas(other, *((uv[0] + uv[5]) / 2)) >= 40
    assert settings_of(url, client_a)["selected_feature"] is None

    # a bad value typed into a control: a clear message, settings unchanged
    page.fill("input[name=cluster_threshold_m]", "-3")
    page.dispatch_event("input[name=cluster_threshold_m]", "change")
    page.wait_for_function("document.getElementById('error').textContent.length > 0",
                           timeout=10000)
    assert "cluster_threshold_m" in page.text_content("#error")
    assert settings_of(url, client_a)["cluster_threshold_m"] == 0.6
    assert errors == []


def test_the_page_works_from_the_url_with_the_token(live_viewer_with_token, browser) -> None:
    """The URL a viewer bound beyond loopback prints: the page keeps the token in a cookie,
    so its own requests and its websocket carry it; the address bar loses it."""
    url = live_viewer_with_token
    errors: list[str] = []
    page = open_page(browser, url, errors, path=f"/?token={TOKEN}")
    assert page.url == url + "/"  # redirected: the token is out of the address bar
    wait_for_frames(page, 3)  # the websocket carries the cookie
    page.select_option("select[name=mode]", "inter")  # and so do the page's fetches
    page.wait_for_function("window.slamlens.settings.mode === 'inter'", timeout=10000)
    client = page.evaluate("window.slamlens.client")
    request = urllib.request.Request(f"{url}/api/settings?client={client}",
                                     headers={"Authorization": f"Bearer {TOKEN}"})
    with urllib.request.urlopen(request, timeout=10) as r:
        assert json.loads(r.read())["settings"]["mode"] == "inter"
    assert errors == []

    # a browser without the token gets nothing but the reason
    stranger = browser.new_context().new_page()
    response = stranger.goto(url + "/")
    assert response is not None and response.status == 401
    assert "token" in stranger.content()
