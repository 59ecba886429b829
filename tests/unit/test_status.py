"""The status protocol's pieces: keys, names, the announcer's rates and answers, the table."""

from __future__ import annotations

import pytest

from slamlens.common.errors import ConfigError
from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import ServiceStatus
from slamlens.common.status import Report, StatusAnnouncer, role_name
from slamlens.services.commands.status import cells, gather, table


def test_status_keys_name_identity_service_and_instance() -> None:
    keys = Keys("lab/slamlens")
    key = keys.status("robot-r1", "estimator", "0a1b")
    assert key == "lab/slamlens/status/robot-r1/estimator/0a1b"
    assert keys.status_of(key) == ("robot-r1", "estimator", "0a1b")
    assert keys.status_of("lab/slamlens/robot/r1/state") is None
    assert keys.status_of("other/status/a/b/c") is None
    assert keys.any_status() == "lab/slamlens/status/**"
    with pytest.raises(ConfigError):
        keys.status("robot/r1", "estimator", "x")


@pytest.mark.parametrize(("service", "robot", "camera", "name"), [
    ("estimator", "r1", None, "robot-r1"), ("sim", "r1,r2", None, "robot-r1"),
    ("replay", "robot3", None, "robot-robot3"), ("monitor", "r1", None, "monitor-r1"),
    ("registration", "r1", "top", "camera-top"),
])
def test_a_service_without_identity_is_named_for_its_role(service, robot, camera,
                                                          name) -> None:
    assert role_name(service, robot=robot, camera=camera) == name
    assert role_name("router").startswith("router-")
    assert role_name("viewer", robot="r1").startswith("viewer-")


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_announcer_answers_with_counts_and_rates_over_the_last_seconds() -> None:
    bus = InProcessBus()
    keys = Keys()
    clock = Clock()
    counts = {"states": 0.0, "landmarks": 3.0}
    announcer = StatusAnnouncer(
        bus, keys, service="estimator", name="robot-r1", robot="r1", clock=clock,
        provider=lambda: Report(state="running", counts=dict(counts), dropped=2, lost=1,
                                epoch=7), period_s=3600.0)
    try:
        assert bus.alive(keys.any_status()) == [announcer.key]
        first = ServiceStatus.from_bytes(bus.get(announcer.key)[0].payload)
        assert (first.service, first.name, first.robot, first.epoch) == ("estimator",
                                                                         "robot-r1", "r1", 7)
        assert (first.dropped, first.lost, first.state) == (2, 1, "running")
        assert first.rates == {"states": 0.0}  # only the first count is rated by default
        for step in range(1, 11):  # 10 states/s for 10 s
            clock.now += 1.0
            counts["states"] = 10.0 * step
            status = announcer.snapshot()
        assert status.rates == {"states": pytest.approx(10.0)}
        assert status.uptime_s == pytest.approx(10.0)
        for _ in range(6):  # then nothing for 6 s: the rate falls to 0 within the window
            clock.now += 1.0
            status = announcer.snapshot()
        assert status.rates["states"] == pytest.approx(0.0)
    finally:
        announcer.close()


def test_a_failing_provider_is_said_not_raised() -> None:
    bus = InProcessBus()

    def broken() -> Report:
        raise KeyError("gone")

    announcer = StatusAnnouncer(bus, Keys(), service="viewer", name="viewer-x",
                                provider=broken, period_s=3600.0)
    try:
        assert ServiceStatus.from_bytes(announcer.latest_bytes()).state == "status unavailable"
    finally:
        announcer.close()


def test_gather_lists_alive_and_answering_services_and_the_table_shows_them() -> None:
    bus = InProcessBus()
    keys = Keys()
    est = StatusAnnouncer(bus, keys, service="estimator", name="robot-r1", robot="r1",
                          provider=lambda: Report(counts={"states": 5.0}, epoch=9),
                          period_s=3600.0)
    silent = keys.status("viewer-lab", "viewer", "ffff")
    bus.declare_alive(silent)  # alive, but no queryable: "no answer"
    try:
        rows = gather(bus, keys, timeout_s=0.5)
        # the silent one has no host to sort by: first
        assert [(r["service"], r["answered"]) for r in rows] == [("viewer", False),
                                                                 ("estimator", True)]
        row = next(r for r in rows if r["service"] == "estimator")
        assert row["epoch"] == 9 and row["robot"] == "r1" and row["alive"]
        text = table(rows)
        header, *lines = text.splitlines()
        assert header.split() == ["SERVICE", "NAME", "HOST", "ROBOT", "CAMERA", "STATE", "RATE",
                                  "DROPPED", "LOST", "EPOCH", "VERSION", "UP"]
        assert any(line.split()[:2] == ["viewer", "viewer-lab"] and "no answer" in line
                   for line in lines)
        assert cells(row)[:2] == ["estimator", "robot-r1"] and cells(row)[9] == "9"
        assert table([]) == "no slamlens service is alive on this bus"
    finally:
        est.close()
