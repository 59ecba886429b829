"""`slamlens launch` as a supervisor, with real processes on loopback: order and readiness,
one combined log, respawn with back-off (an estimator with a checkpoint resumes its map),
a failure before readiness ending the group, and a clean stop within 2 s."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

from slamlens.common.keys import Keys
from slamlens.common.messages import Health, ServiceStatus
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.procs import REPO, Service, slamlens_cmd

KEYS = Keys()


def _launch(tmp_path: Path, text: str, *extra: str) -> Service:
    path = tmp_path / "group.toml"
    path.write_text(text)
    return Service(slamlens_cmd("launch", str(path), *extra), cwd=REPO)


def _group(endpoint: str, *, checkpoint: str = "", sim: bool = True) -> str:
    text = f"""
[launch]
respawn_max_s = 4.0

[defaults]
connect = ["{endpoint}"]

[service.router]
command = "router"
listen = ["{endpoint}"]
connect = []

[service.estimator]
command = "estimator"
after = ["router"]
{f'checkpoint = "{checkpoint}"' if checkpoint else ''}

[service.monitor]
command = "monitor"
after = ["router"]
"""
    if sim:
        text += """
[service.sim]
command = "sim"
after = ["estimator", "monitor"]
rate = 0
"""
    return text


def _stop(proc: Service) -> tuple[float, list[str]]:
    """SIGTERM the launch; (seconds it took to exit, its whole output)."""
    started = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("slamlens launch did not exit on SIGTERM") from None
    took = time.monotonic() - started
    out, _ = proc.output()
    return took, out.splitlines()


def _index(lines: list[str], text: str) -> int:
    return next(i for i, line in enumerate(lines) if text in line)


def test_order_readiness_one_log_and_a_clean_stop(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    proc = _launch(tmp_path, _group(endpoint), "--log-dir", str(tmp_path / "logs"))
    bus = None
    try:
        proc.wait_for_line("[launch] all 4 services ready", timeout=90)
        proc.wait_for_line("[launch] sim finished (exit 0)", timeout=120)
        # the monitor was ready before the simulator started: it checks every state
        bus = open_bus(BusSettings(connect=(endpoint,)))
        deadline = time.monotonic() + 60
        seq = 0
        while time.monotonic() < deadline:
            replies = bus.get(KEYS.health("robot1"))
            seq = Health.from_bytes(replies[0].payload).seq if replies else 0
            if seq >= 1090:
                break
            time.sleep(0.2)
        assert seq == 1090  # 545 odometry + 545 observation batches of the paper run
    finally:
        if bus is not None:
            bus.close()
        took, lines = _stop(proc)
    assert proc.returncode == 0, "\n".join(lines[-20:])
    assert took < 2.0, f"the group took {took:.2f} s to stop"
    # started in order, each once what it waits for said it is ready
    assert _index(lines, "[router] router ready") < _index(lines, "[launch] estimator started")
    assert _index(lines, "[router] router ready") < _index(lines, "[launch] monitor started")
    assert _index(lines, "[estimator] estimator ready") < _index(lines, "[launch] sim started")
    assert _index(lines, "[monitor] monitor ready") < _index(lines, "[launch] sim started")
    # one log: every service's stdout and stderr lines, by name
    assert any(re.match(r"\[sim\] \d\d:\d\d:\d\d sim INFO simulating paper", ln) for ln in lines)
    assert any(ln.startswith("[sim] sim done: ") and "all applied" in ln for ln in lines)
    monitor = json.loads(next(ln for ln in lines if ln.startswith("[monitor] monitor stopped: "))
                         .split(": ", 1)[1])
    # every state of the run (and the estimator's initial one, if it was up first)
    assert monitor["checked"] in (1090, 1091) and monitor["lost"] == 0
    assert monitor["violations"] == 0
    assert lines[-1] == ("[launch] stopped: 4 services; respawned: none; exit codes: router 0, "
                         "estimator 0, monitor 0, sim 0")
    logs = tmp_path / "logs"
    assert "estimator ready" in (logs / "estimator.log").read_text()
    assert "[sim] sim done" in (logs / "launch.log").read_text()


def _estimator_status(bus) -> ServiceStatus | None:
    for sample in bus.get(KEYS.any_status()):
        status = ServiceStatus.from_bytes(sample.payload)
        if status.service == "estimator":
            return status
    return None


def test_a_killed_service_is_respawned_with_back_off(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    proc = _launch(tmp_path, _group(endpoint, checkpoint=str(tmp_path / "ckpt"), sim=False))
    bus = None
    try:
        first = proc.wait_for_line("[launch] estimator started (pid ", timeout=60)
        proc.wait_for_line("[launch] all 3 services ready", timeout=60)
        bus = open_bus(BusSettings(connect=(endpoint,)))
        before = _estimator_status(bus)
        assert before is not None and before.epoch
        checkpoint = tmp_path / "ckpt" / "estimator-robot1.ckpt"
        deadline = time.monotonic() + 30
        while not checkpoint.exists():  # written within a second of the start
            assert time.monotonic() < deadline, "the estimator wrote no checkpoint"
            time.sleep(0.05)
        waits = []
        pid = int(re.search(r"pid (\d+)", first).group(1))  # type: ignore[union-attr]
        for _ in range(2):
            os.kill(pid, signal.SIGKILL)
            line = proc.wait_for_line("[launch] estimator exited with signal SIGKILL: "
                                      "respawning in ", timeout=30)
            waits.append(float(re.search(r"in ([\d.]+) s", line).group(1)))  # type: ignore[union-attr]
            again = proc.wait_for_line("[launch] estimator respawned (pid ", timeout=30)
            pid = int(re.search(r"pid (\d+)", again).group(1))  # type: ignore[union-attr]
            proc.wait_for_line("[estimator] estimator ready", timeout=60)
        assert waits == [0.5, 1.0]  # the back-off doubles while it keeps failing
        after = None
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # the old token lingers until Zenoh drops it
            after = _estimator_status(bus)
            if after is not None and after.pid == pid:
                break
            time.sleep(0.1)
        assert after is not None and after.pid == pid
        assert after.epoch == before.epoch  # the checkpoint: the same map goes on
        assert after.state == "resumed"
    finally:
        if bus is not None:
            bus.close()
        took, lines = _stop(proc)
    assert proc.returncode == 0
    assert took < 2.0
    assert "respawned: estimator ×2" in lines[-1]


def test_a_service_failing_before_it_is_ready_ends_the_group(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    text = f"""
[service.router]
command = "router"
listen = ["{endpoint}"]

[service.camera]
command = "registration"
after = ["router"]
connect = ["{endpoint}"]
source = "{tmp_path}/nope.mp4"
calibration = "deploy/calibration_synthetic_1280x720.yml"
"""
    proc = _launch(tmp_path, text)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    assert err.strip().splitlines() == [
        f"slamlens: error: {tmp_path}/group.toml: camera (`slamlens registration --connect "
        f"{endpoint} --source {tmp_path}/nope.mp4 --calibration "
        "deploy/calibration_synthetic_1280x720.yml`) exited with code 1 before it was ready: "
        f"slamlens: error: source {tmp_path}/nope.mp4 does not exist"]
    lines = out.splitlines()
    assert "[router] router stopped" in lines  # the rest of the group was stopped
    assert lines[-1].startswith("[launch] failed: 2 services; respawned: none; exit codes: "
                                "router 0, camera 1")
