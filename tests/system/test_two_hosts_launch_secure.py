"""The paper run end to end with the secure launch files (tests): two network
namespaces, "robot" and "workstation", joined by a veth pair; on each one
`slamlens launch deploy/*_secure.toml` — its own router, mutual TLS between them, every
service with its identity. The workstation registers the synthetic camera while the
simulated robot holds at its start; the robot's estimator applies every input, its monitor
checks every state and finds nothing wrong; the workstation's viewer shows the last state
over the registered camera with the monitor's health; nothing a real service says is
refused but the camera's tracked pose (docs/security.md, limits)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
from pathlib import Path

from slamlens.common.certs import extend_authority
from slamlens.services.harness.netns import Hosts, curl_json
from slamlens.services.harness.procs import REPO, Service, slamlens_cmd

NAMES = ["router-ws", "router-robot", "robot-robot1", "monitor-robot1", "camera-overhead",
         "viewer-lab"]
EVENTS = 1090  #: states after the initial one: 545 odometry + 545 observation batches


def _launch(ns: str, name: str, workstation: str, home: Path, *extra: str) -> Service:
    argv = ["ip", "netns", "exec", ns,
            *slamlens_cmd("launch", f"deploy/{name}.toml", "--set", f"workstation={workstation}",
                          *extra)]
    return Service(argv, env={"HOME": str(home)}, cwd=REPO)


def _viewer(ns: str) -> dict:
    try:
        return curl_json(ns, "http://127.0.0.1:8080/api/status", timeout=5.0) or {}
    except subprocess.TimeoutExpired:
        return {}


def _final(lines: list[str], service: str, name: str) -> dict:
    prefix = f"[{service}] {name} stopped: "
    return json.loads(next(ln for ln in lines if ln.startswith(prefix))[len(prefix):])


def test_the_paper_run_with_the_secure_launch_files(two_hosts: Hosts, tmp_path: Path) -> None:
    h = two_hosts
    home = tmp_path / "home"
    extend_authority(home / "slamlens-pki", NAMES, hosts=[h.workstation_ip])
    workstation = _launch(h.workstation, "workstation_secure", h.workstation_ip, home)
    robot = None
    try:
        workstation.wait_for_line("[launch] all 3 services ready", timeout=120)
        robot = _launch(h.robot, "robot_secure", h.workstation_ip, home, "--set", "rate=0")
        robot.wait_for_line("[launch] all 5 services ready", timeout=120)
        done = robot.wait_for_line("[driver] sim done: ", timeout=180)
        assert "all applied by the estimator" in done
        counts = json.loads(done.split("sim done: ", 1)[1].split(" in ")[0])
        assert counts["Odometry"] + counts["Observations"] == EVENTS
        robot.wait_for_line("[launch] driver finished (exit 0)", timeout=30)
        deadline = time.monotonic() + 60
        status: dict = {}
        while time.monotonic() < deadline:  # the last state and its health reach the viewer
            status = _viewer(h.workstation)
            if (status.get("state") or {}).get("seq") == EVENTS and \
                    (status.get("health") or {}).get("seq") == EVENTS:
                break
            time.sleep(0.5)
        assert (status.get("state") or {}).get("seq") == EVENTS, status
        assert status["health"]["ok"] and status["health"]["suspects"] == []
        assert status["cameras"][0]["registration"]["status"] in ("registered",
                                                                  "marker not found")
    finally:
        outputs = {}
        for name, proc in (("robot", robot), ("workstation", workstation)):
            if proc is None:
                continue
            started = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            proc.wait(15)
            outputs[name] = (proc.returncode, time.monotonic() - started,
                             proc.output()[0].splitlines())
    for name, (code, took, lines) in outputs.items():
        assert code == 0, "\n".join(lines[-30:])
        assert took < 2.5, f"the {name}'s launch took {took:.1f} s to stop"
        assert lines[-1].startswith("[launch] stopped: ") and "respawned: none" in lines[-1]
        assert any("(mutual TLS); roles enforced for " in ln for ln in lines)
        refused = [ln for ln in lines if ln.startswith("[router]") and "refused" in ln
                   and "router stopped" not in ln]
        assert all(re.search(r"refused(?: \d+ more)?: camera-overhead may not \w+ \(ingress\) "
                             r"on slamlens/robot/robot1/tracked", ln) for ln in refused), \
            refused
    robot_lines = outputs["robot"][2]
    estimator = _final(robot_lines, "estimator", "estimator")
    assert estimator["odometry"] + estimator["observation_batches"] == EVENTS
    assert estimator["lost"] == 0 and estimator["dropped"] == 0
    monitor = _final(robot_lines, "monitor", "monitor")
    assert monitor["checked"] >= EVENTS and monitor["lost"] == 0
    assert monitor["violations"] == 0 and monitor["verdict"] == "ok", monitor
    assert any("camera overhead: robot robot1 registered" in ln
               for ln in outputs["workstation"][2]), "the camera never registered"
