"""``slamlens viewer --source summary`` on real Zenoh (issue 13, docs/remote_viewers.md):
the viewer pulls the robot's summary instead of subscribing to the full state, and serves
the clustered min / mean / max picture over the camera."""

from __future__ import annotations

import threading

import numpy as np

from common.keys import Keys
from services.slam.settings import SummarySettings
from services.slam.summary_service import SummaryService
from tests.integration.test_viewer_service import (  # noqa: F401  (fixtures)
    CAMERA,
    HEIGHT,
    LANDMARKS,
    ROBOT,
    WIDTH,
    make_frame,
    make_registration,
    make_state,
    midpoint,
    pixel_of,
    publisher,
    red_pixels,
    snapshot,
    start_viewer,
    status_of,
    viewers,
    wait_until,
)

KEYS = Keys()


def test_the_viewer_draws_the_clustered_picture_from_the_summary(
        start_viewer, publisher, make_client) -> None:  # noqa: F811
    summary = SummaryService(make_client(), keys=KEYS, robot=ROBOT,
                             settings=SummarySettings(robot=ROBOT, hold_s=1.0))
    halt = threading.Event()
    worker = threading.Thread(target=summary.run, args=(halt,), daemon=True)
    worker.start()
    try:
        publisher(KEYS.state(ROBOT), make_state(7).to_bytes())
        wait_until(lambda: summary.received >= 1)
        _, url = start_viewer(camera=CAMERA, source="summary")
        publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
        publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
        wait_until(lambda: (s := status_of(url))["state"] is not None
                   and s["state"]["seq"] == 7
                   and s["cameras"][0]["registration"] is not None
                   and s["cameras"][0]["frame"] is not None, timeout=20.0)
        assert summary.answered >= 1  # it came from the summary queryable

        image, headers = snapshot(url)  # the default settings: "all" pairs asked for
        assert headers["X-State-Seq"] == "7"
        assert image.shape == (HEIGHT, WIDTH, 3)
        a, b = LANDMARKS[:3].mean(axis=0), LANDMARKS[3:].mean(axis=0)
        # min, mean and max glyphs on the line between the two cluster centroids
        # (spread 0.15 of it before and after the middle: scene.py)
        for t in (0.35, 0.5, 0.65):
            assert red_pixels(image, pixel_of(a + t * (b - a))) >= 40, t
        # no glyph of an individual pair: the summary holds none (a full state's "all"
        # picture has one at every pair's midpoint)
        for i, j in [(0, 1), (3, 4), (2, 5)]:
            assert red_pixels(image, midpoint(i, j)) == 0, (i, j)

        publisher(KEYS.state(ROBOT), make_state(8).to_bytes())  # the next pull gets it
        wait_until(lambda: status_of(url)["state"]["seq"] == 8, timeout=20.0)
        assert int(snapshot(url)[1]["X-State-Seq"]) == 8
    finally:
        halt.set()
        worker.join(5.0)


def test_the_summary_intake_never_takes_the_full_state(start_viewer, publisher,  # noqa: F811
                                                       make_client) -> None:
    _, url = start_viewer(camera=CAMERA, source="summary")  # and no summary service
    # published states straight on the key (the publisher fixture would wait for the
    # viewer to take them, which is what must not happen)
    states = make_client().publisher(KEYS.state(ROBOT))
    states.put(make_state(3).to_bytes())
    publisher(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    wait_until(lambda: status_of(url)["cameras"][0]["registration"] is not None)
    states.put(make_state(4).to_bytes())
    publisher(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    wait_until(lambda: status_of(url)["cameras"][0]["frame"] is not None)
    assert status_of(url)["state"] is None  # published states are not its input
    assert np.array_equal(snapshot(url)[0].shape, (HEIGHT, WIDTH, 3))
