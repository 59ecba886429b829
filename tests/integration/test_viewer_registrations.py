"""Every re-registration is shown with who asked and how far the frame moved.

A real viewer service on loopback Zenoh receives Registration messages as the registration
service publishes them (start, requested, refused); ``/api/status`` lists each one once,
newest first, with its reason and the frame's move, and the page's script shows them.
"""

from __future__ import annotations

import dataclasses

from tests.integration import test_web_browser as browser_test
from tests.integration.viewer_rig import (
    CAMERA,
    KEYS,
    ROBOT,
    make_registration,
    status_of,
)
from tests.waiting import wait_until

# the browser fixture of that module, used here too (the viewer's: tests/integration/conftest.py)
browser = browser_test.browser


def test_each_registration_is_listed_once_with_who_asked_and_the_move(start_viewer, publisher,
                                                                      browser) -> None:
    _, url = start_viewer(camera=CAMERA)
    key = KEYS.registration(CAMERA, ROBOT)
    start = dataclasses.replace(make_registration(), epoch=7, reason="start")
    publisher(key, start.to_bytes())
    wait_until(lambda: len(status_of(url)["registrations"]) == 1)
    # the same registration published again (late joiners, status updates) is no new event
    publisher(key, start.to_bytes())
    asked = dataclasses.replace(make_registration(), stamp=4.0, epoch=7,
                                reason="requested by alice@desk", moved_m=0.031,
                                moved_deg=1.5)
    publisher(key, asked.to_bytes())
    wait_until(lambda: len(status_of(url)["registrations"]) == 2)
    refused = dataclasses.replace(
        asked, stamp=9.0, moved_m=None, moved_deg=None,
        reason="refused a re-registration requested by mallory: it would move the map "
               "frame 1.14 m / 93.0° while the robot is 0.80 m from its map origin")
    publisher(key, refused.to_bytes())
    wait_until(lambda: len(status_of(url)["registrations"]) == 3)

    status = status_of(url)
    events = status["registrations"]
    assert [e["reason"].split(" ")[0] for e in events] == ["refused", "requested", "start"]
    newest, middle, first = events
    assert newest["refused"] is True and "mallory" in newest["reason"]
    assert "1.14 m" in newest["reason"] and newest["moved_m"] is None
    assert middle["refused"] is False and middle["moved_m"] == 0.031
    assert middle["moved_deg"] == 1.5 and "alice@desk" in middle["reason"]
    assert first["epoch"] == 7 and first["camera"] == CAMERA and first["robot"] == ROBOT
    # the camera's current registration says why it is what it is
    (camera,) = status["cameras"]
    assert camera["registration"]["reason"] == refused.reason

    # and the page shows them, newest first, the refused one marked
    page = browser.new_context().new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(url + "/")
    page.wait_for_function("document.querySelectorAll('#registrations li').length === 3",
                           timeout=15000)
    items = page.locator("#registrations li")
    assert "mallory" in items.nth(0).inner_text()
    assert "bad" in (items.nth(0).get_attribute("class") or "")
    assert "alice@desk" in items.nth(1).inner_text()
    assert "moved 0.031 m / 1.5°" in items.nth(1).inner_text()
    assert errors == []
