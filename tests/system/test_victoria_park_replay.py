"""Victoria Park (GTSAM's file) through the real processes at --rate 0: router +
``slamlens estimator --config deploy/victoria_park.toml`` + ``slamlens monitor`` +
``slamlens replay FILE --format victoria-park`` (docs/drivers.md). Every input is applied,
the map holds the park's 151 trees, and the monitor — which checks the newest state when it
falls behind — never sees an estimator fault. The figures of the whole run, every state
checked, are benchmarks/victoria_park.py's (docs/consistency.md, "Victoria Park")."""

from __future__ import annotations

import json

import pytest

from slamlens.common.keys import Keys
from slamlens.common.messages import Health
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.procs import spawn, stop
from tests.conftest import REPO, SHARED_DATA
from tests.waiting import wait_until

FILE = SHARED_DATA / "victoria_park" / "victoria_park_gtsam.txt"
ROBOT = "park"
INPUTS = 2 * 6968 + 3331  # two Odometry a step, one Observations a pose with sightings


def _latest_health_seq(bus) -> int | None:
    replies = bus.get(Keys().health(ROBOT), timeout=5.0)
    return Health.from_bytes(replies[0].payload).seq if replies else None


def _final(output: str, name: str) -> dict:
    line = next(x for x in output.splitlines() if x.startswith(f"{name} stopped: "))
    return json.loads(line.removeprefix(f"{name} stopped: "))


@pytest.mark.timeout(600)
def test_victoria_park_replays_whole_through_the_processes() -> None:
    endpoint = free_tcp_endpoint()
    env = {"OPENBLAS_NUM_THREADS": "1"}
    router = spawn("router", "--listen", endpoint)
    procs = [router]
    bus = None
    try:
        router.wait_for_line("router ready", timeout=30)
        est = spawn("estimator", "--config", str(REPO / "deploy" / "victoria_park.toml"),
                    "--robot", ROBOT, "--connect", endpoint, env=env)
        mon = spawn("monitor", "--robot", ROBOT, "--connect", endpoint, env=env)
        procs += [est, mon]
        est.wait_for_line("estimator ready", timeout=60)
        mon.wait_for_line("monitor ready", timeout=60)
        bus = open_bus(BusSettings(connect=(endpoint,)))
        replay = spawn("replay", str(FILE), "--format", "victoria-park", "--robot", ROBOT,
                       "--rate", "0", "--connect", endpoint)
        procs.append(replay)
        line = replay.wait_for_line("replay done", timeout=480)
        assert "all applied by the estimator" in line
        counts = json.loads(line.split("replay done: ", 1)[1].split(" in ")[0])
        assert (counts["Odometry"], counts["Observations"]) == (2 * 6968, 3331)
        # the monitor has checked the last state when its latest Health (a get) is that one
        wait_until(lambda: _latest_health_seq(bus) == INPUTS, timeout=300,
                   what="the monitor's Health of the last state")
        estimator = _final(stop(est)[0], "estimator")
        assert estimator["seq"] == estimator["states"] == INPUTS
        assert estimator["landmarks"] == 151
        assert (estimator["refused"], estimator["lost"], estimator["gated"]) == (0, 0, 0)
        mon_out, mon_log = stop(mon)
        monitor = _final(mon_out, "monitor")
        assert monitor["estimator_fault_seen"] is False, mon_log[-2000:]
        assert monitor["states_by_verdict"]["fault"] == 0
        assert "no estimator fault seen" in mon_out and "ESTIMATOR FAULT" not in mon_log
    finally:
        if bus is not None:
            bus.close()
        for p in reversed(procs):
            if p.poll() is None:
                stop(p)
