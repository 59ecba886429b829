"""``slamlens viewer --source summary`` on real Zenoh (docs/remote_viewers.md):
the viewer pulls the robot's summary instead of subscribing to the full state, and serves
the clustered min / mean / max picture over the camera."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from slamlens.common.keys import Keys
from slamlens.services.slam.settings import SummarySettings
from slamlens.services.slam.summary_service import SummaryService
from tests.integration.viewer_rig import (
    CAMERA,
    HEIGHT,
    LANDMARKS,
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

KEYS = Keys()


@contextmanager
def summary_of_state_7(make_client, put) -> Iterator[SummaryService]:
    """The robot's summary service on its own thread, once it holds state seq 7."""
    summary = SummaryService(make_client(), keys=KEYS, robot=ROBOT,
                             settings=SummarySettings(robot=ROBOT, hold_s=1.0))
    halt = threading.Event()
    worker = threading.Thread(target=summary.run, args=(halt,), daemon=True)
    worker.start()
    try:
        state = make_state(7).to_bytes()

        def delivered() -> bool:
            # a fresh route can drop a sample just after matching: put again until the
            # summary service has one (the same state; a repeat changes nothing)
            if summary.received >= 1:
                return True
            put(KEYS.state(ROBOT), state)
            return False

        wait_until(delivered, timeout=60.0)
        yield summary
    finally:
        halt.set()
        worker.join(5.0)


def _registered_viewer(start, put):
    """A ``--source summary`` viewer over a registered camera with a frame (no state yet
    asserted: the callers wait for what they need of it)."""
    service, url = start(camera=CAMERA, source="summary")
    put(KEYS.registration(CAMERA, ROBOT), make_registration().to_bytes())
    put(KEYS.frame(CAMERA), make_frame(1).to_bytes())
    return service, url


def test_the_viewer_draws_the_clustered_picture_from_the_summary(
        start_viewer, publisher, make_client) -> None:  # noqa: F811
    with summary_of_state_7(make_client, publisher) as summary:
        _, url = _registered_viewer(start_viewer, publisher)
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


def test_a_selection_pulls_its_pairs_from_the_summary(start_viewer, publisher,  # noqa: F811
                                                      make_client) -> None:
    """Selecting a feature or a cluster in ``--source summary`` asks the robot for
    ``what=pairs`` of it: the view then shows that selection's pairs at
    full detail — a glyph at each of its pairs' midpoints, none elsewhere; without a
    selection the clusters' min / mean / max come back."""
    with summary_of_state_7(make_client, publisher):
        service, url = _registered_viewer(start_viewer, publisher)
        wait_until(lambda: (s := status_of(url))["state"] is not None
                   and s["cameras"][0]["registration"] is not None
                   and s["cameras"][0]["frame"] is not None, timeout=20.0)
        puller = service.intake._puller_of[ROBOT]
        assert puller.query.what == "clusters"

        def shows(client: str, pairs: list[tuple[int, int]], absent: list[tuple[int, int]]
                  ) -> bool:
            image, _ = snapshot(url, client)
            return (all(red_pixels(image, midpoint(i, j)) >= 40 for i, j in pairs)
                    and all(red_pixels(image, midpoint(i, j)) == 0 for i, j in absent))

        # feature 10 (index 0): its five pairs, no pair without it
        http(url + "/api/settings?client=f", data={"selected_feature": 10})
        wait_until(lambda: shows("f", [(0, k) for k in range(1, 6)], [(1, 2), (3, 4), (4, 5)]),
                   timeout=30.0)
        query = puller.query
        assert (query.what, query.feature, query.cluster) == ("pairs", 10, None)
        state = service.store.snapshot().robots[0].state
        assert state is not None and state.summary is not None
        assert state.summary.what == "pairs" and state.summary.selected_feature == 10
        assert len(state.summary.pairs) == 5

        # the second cluster (features 13–15, by the robot's stable ids): its three pairs
        groups = state.summary.groups
        assert groups is not None
        second = int(groups[3])
        assert int(groups[4]) == int(groups[5]) == second != int(groups[0])
        http(url + "/api/settings?client=f", data={"selected_feature": "none",
                                                   "selected_cluster": second})
        wait_until(lambda: shows("f", [(3, 4), (3, 5), (4, 5)], [(0, 1), (0, 3), (2, 5)]),
                   timeout=30.0)
        assert (puller.query.what, puller.query.cluster) == ("pairs", second)

        # no selection: the clusters' min / mean / max again, no individual pair
        http(url + "/api/settings?client=f", data={"selected_cluster": "none"})
        a, b = LANDMARKS[:3].mean(axis=0), LANDMARKS[3:].mean(axis=0)

        def clustered() -> bool:
            image, _ = snapshot(url, "f")
            return (red_pixels(image, pixel_of(a + 0.5 * (b - a))) >= 40
                    and red_pixels(image, midpoint(3, 4)) == 0)

        wait_until(clustered, timeout=30.0)
        assert puller.query.what == "clusters"
