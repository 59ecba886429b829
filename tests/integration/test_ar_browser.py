"""The AR page in Debian's Chromium, its camera a video file, against the truth it shows.

Chromium's fake camera plays the synthetic head-mounted camera's walk round the paper world
(services/harness/ar_video.py: a Y4M file, ``C420``, every frame's index coded in its
corner). The page sends its frames to a live viewer (in-process, real Zenoh on loopback),
which has them registered by ``slamlens registration --source browser`` (a real process,
the video's true intrinsics as its calibration) and answers each with the robot's state —
the paper world's true landmarks — drawn over it. The pictures the page shows are read back
from its canvas: each feature cone must land within 3 px of where the same cone lands drawn
through the frame's true camera pose.
"""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Iterator

import pytest

from slamlens.services.harness.ar_rig import (
    CONES_ONLY,
    ArRig,
    cone_offsets,
    open_ar_page,
    post_settings,
    shown_picture,
    start_rig,
)
from slamlens.services.harness.ar_video import Video, read_index, render_walk


@pytest.fixture(scope="module")
def walk() -> Video:
    return render_walk(48, arc_deg=60.0)


@pytest.fixture
def rig(make_client, router_endpoint, tmp_path, walk) -> Iterator[ArRig]:
    yield from start_rig(make_client, router_endpoint, tmp_path, walk)


def test_ar_page_registers_and_draws_the_features_on_the_truth(rig: ArRig) -> None:
    p, browser, page, errors = open_ar_page(rig.y4m, rig.url)
    try:
        client = page.evaluate("window.slamlensAr.client")
        post_settings(rig.url, client, CONES_ONLY)
        page.wait_for_function("window.slamlensAr.overlays >= 10", timeout=90000)
        checked: list[float] = []
        frames = set()
        while len(frames) < 6:
            answered = page.evaluate("window.slamlensAr.answered")
            page.wait_for_function(f"window.slamlensAr.answered > {answered}", timeout=30000)
            image, last = shown_picture(page)
            index = read_index(image)
            if not last or not last["overlay"] or index is None or index in frames:
                continue
            offsets = cone_offsets(rig.video, index, image)
            assert len(offsets) >= 8, (index, offsets)  # most of the 15 cones in view
            checked += offsets
            frames.add(index)
        assert max(checked) <= 3.0, checked
        status = json.loads(urllib.request.urlopen(f"{rig.url}/api/status",
                                                   timeout=10).read())
        cams = status["ar"]["cameras"]
        assert [c["camera"] for c in cams] == ["phone-test"] and cams[0]["overlays"] >= 10
        # where each overlaid answer's time went, by the page's clock: the parts fit inside
        # the whole (the viewer's own time, drawing included, within frame → shown)
        timings = page.evaluate("window.slamlensAr.timings")
        assert len(timings) >= 10
        for t in timings:
            assert 0 <= t["draw"] <= t["server"] and t["encode"] >= 0 and t["show"] >= 0, t
            assert t["encode"] + t["server"] + t["show"] <= t["total"] + 1.0, t
        assert errors == []
    finally:
        browser.close()
        p.stop()
