"""`slamlens status` and `slamlens register` against real services on loopback.

One group of real processes — router, estimator, monitor, the synthetic overhead camera
with registration, a viewer and the simulator standing still at its start pose — and a
second camera that never sees its robot. Status lists every one with what it serves;
a killed service leaves the list; register re-registers the camera that sees its robot,
and says clearly when nobody answers or nothing new comes.
"""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from slamlens.common.session import free_tcp_endpoint
from slamlens.services.harness.procs import REPO, Service, slamlens_cmd, spawn, stop

CALIBRATION = "deploy/calibration_synthetic_1280x720.yml"


def _run(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(slamlens_cmd(*args), cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def group():
    endpoint = free_tcp_endpoint()
    bus = ("--connect", endpoint)
    procs: dict[str, Service] = {}

    def start(name: str, ready: str, *args: str) -> None:
        procs[name] = spawn(*args)
        procs[name].wait_for_line(ready, timeout=90)

    try:
        start("router", "router ready", "router", "--listen", endpoint)
        start("estimator", "estimator ready", "estimator", *bus)
        start("monitor", "monitor ready", "monitor", *bus)
        start("registration", "registration ready", "registration", "--camera", "overhead",
              "--source", "synthetic", "--calibration", CALIBRATION, *bus)
        start("blind", "registration ready", "registration", "--camera", "blind", "--robot",
              "nobody", "--source", "synthetic", "--fps", "5", *bus)
        start("viewer", "viewer ready", "viewer", "--camera", "overhead", "--http",
              "127.0.0.1:0", *bus)
        procs["sim"] = spawn("sim", "--hold", "600", *bus)  # stands at the map origin
        yield endpoint, procs
    finally:
        for proc in reversed(list(procs.values())):
            if proc.poll() is None:
                stop(proc)


def _status(endpoint: str) -> list[dict]:
    out = _run("status", "--json", "--connect", endpoint)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def _until_listed(endpoint: str, want: set[str], timeout: float = 60.0,
                  sim_state: str = "") -> list[dict]:
    """The status rows once ``want`` are all listed and answering (and the simulator says
    ``sim_state``: a service's status is rebuilt once a second)."""
    deadline = time.monotonic() + timeout
    while True:
        rows = _status(endpoint)
        if want <= {r["service"] for r in rows} and all(r["answered"] for r in rows) and (
                not sim_state or any(r["service"] == "sim" and r["state"] == sim_state
                                     for r in rows)):
            return rows
        assert time.monotonic() < deadline, rows
        time.sleep(0.2)


def test_status_lists_every_live_service_with_what_it_serves(group) -> None:
    endpoint, procs = group
    rows = _until_listed(endpoint, {"router", "estimator", "monitor", "registration",
                                    "viewer", "sim"}, sim_state="holding at the start pose")
    by = {}
    for row in rows:
        by.setdefault(row["service"], []).append(row)
    assert len(by["registration"]) == 2
    est, = by["estimator"]
    assert (est["name"], est["robot"], est["state"]) == ("robot-robot1", "robot1", "running")
    assert est["pid"] == procs["estimator"].pid and est["epoch"] > 0
    assert est["version"] and est["host"] and est["uptime_s"] > 0
    assert est["counts"]["states"] >= 0 and "states" in est["rates"]
    mon, = by["monitor"]
    assert mon["name"] == "monitor-robot1" and mon["robot"] == "robot1"
    cams = {r["camera"]: r for r in by["registration"]}
    assert cams["overhead"]["name"] == "camera-overhead"
    assert cams["overhead"]["robot"] == "robot1" and cams["blind"]["robot"] == "nobody"
    viewer, = by["viewer"]
    assert viewer["camera"] == "overhead" and viewer["name"].startswith("viewer-")
    assert "serving http://127.0.0.1:" in viewer["state"]
    sim, = by["sim"]
    assert sim["name"] == "robot-robot1" and sim["state"] == "holding at the start pose"
    assert sim["counts"]["Truth"] > 0
    router, = by["router"]
    assert router["counts"]["clients"] >= 6  # the six services and this query's session
    table = _run("status", "--once", "--connect", endpoint)
    assert table.returncode == 0, table.stderr
    header, *lines = table.stdout.splitlines()
    assert header.split()[:3] == ["SERVICE", "NAME", "HOST"]
    assert any(line.split()[:2] == ["estimator", "robot-robot1"] for line in lines)
    assert len(lines) == len(rows)


def test_register_prints_the_new_registration(group) -> None:
    endpoint, _ = group
    out = _run("register", "--camera", "overhead", "--connect", endpoint)
    assert out.returncode == 0, out.stderr
    first = out.stdout.splitlines()[0]
    assert first.startswith("camera overhead registered robot robot1: registered, "
                            "reprojection error ")
    assert "T_camera_from_map =" in out.stdout
    again = _run("register", "--camera", "overhead", "--robot", "robot1", "--connect",
                 endpoint)
    assert again.returncode == 0, again.stderr


def test_register_says_clearly_when_nobody_answers(group) -> None:
    endpoint, _ = group
    out = _run("register", "--camera", "nope", "--connect", endpoint)
    assert out.returncode == 1
    assert out.stderr.strip() == ("slamlens: error: no registration service for camera 'nope' "
                                  "is alive (start `slamlens registration --camera nope`; "
                                  "`slamlens status` lists what runs)")
    out = _run("register", "--camera", "blind", "--timeout", "2", "--connect", endpoint)
    assert out.returncode == 1
    assert out.stderr.strip() == (
        "slamlens: error: camera 'blind' did not re-register within 2 s; it has published no "
        "registration yet (the robot must stand still at its map origin with its marker in "
        "view)")


def test_a_killed_service_leaves_the_list(group) -> None:
    endpoint, procs = group
    _until_listed(endpoint, {"monitor"})
    procs["monitor"].kill()
    procs["monitor"].wait(10)
    deadline = time.monotonic() + 30
    while "monitor" in {r["service"] for r in _status(endpoint)}:
        assert time.monotonic() < deadline, "the killed monitor is still listed"
        time.sleep(0.2)
