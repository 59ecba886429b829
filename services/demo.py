"""``slamlens demo``: the whole system on one machine, as real separate processes.

It starts a Zenoh router on loopback, then the estimator, the behaviour monitor, the
synthetic overhead camera with registration, the AR viewer and, last, the simulated
robot — each a ``slamlens`` process of its own, exactly as they would run on several
machines — prints the browser link and a live one-line summary, and stops them all on
Ctrl-C (or after ``--duration``). Their logs go to one folder, named at start.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.bus import ZenohBus
from common.cli import bus_flags, setup_logging, stop_event
from common.config import settings_from_args
from common.errors import ConfigError, MessageError, SlamlensError
from common.geometry import all_relative_covariances, pd_size_m
from common.keys import Keys
from common.messages import Health, SlamState
from common.session import BusSettings, free_tcp_endpoint, open_bus
from services.settings import DemoSettings

log = logging.getLogger("slamlens.demo")

@dataclass
class _Child:
    name: str
    proc: subprocess.Popen
    log_path: Path


def _free_http(host_port: str) -> str:
    """``host_port`` if its port is free, else (or for port 0) a free port on the host."""
    host, _, port = host_port.rpartition(":")
    with socket.socket() as s:
        try:
            if int(port) == 0:
                raise OSError("port 0: pick one")
            s.bind((host, int(port)))
            return host_port
        except (OSError, ValueError):
            s.bind((host, 0))
            return f"{host}:{s.getsockname()[1]}"


def _router_endpoint(listen: tuple[str, ...]) -> str:
    if listen:
        endpoint = str(listen[0])
        if endpoint.startswith("tcp/") and endpoint.endswith(":0"):
            return free_tcp_endpoint(endpoint[4:].rsplit(":", 1)[0])
        return endpoint
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", 7447))
            return "tcp/127.0.0.1:7447"
        except OSError:
            return free_tcp_endpoint()


class _Summary:
    """Collects states and health for the live one-line summary."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.states = 0
        self.last: SlamState | None = None
        self.health: Health | None = None
        self.times: list[float] = []

    def on_state(self, key: str, payload: bytes) -> None:
        try:
            state = SlamState.from_bytes(payload)
        except MessageError:
            return
        with self.lock:
            self.states += 1
            self.last = state
            self.times.append(time.monotonic())
            if len(self.times) > 200:
                del self.times[:100]

    def on_health(self, key: str, payload: bytes) -> None:
        try:
            health = Health.from_bytes(payload)
        except MessageError:
            return
        with self.lock:
            self.health = health

    def line(self) -> str:
        with self.lock:
            state, health = self.last, self.health
            now = time.monotonic()
            recent = [t for t in self.times if now - t <= 2.0]
        if state is None:
            return "waiting for the estimator's first state…"
        rate = len(recent) / 2.0
        mean_pd = float("nan")
        if state.n >= 2:
            _, _, Pd = all_relative_covariances(state.covariance, state.n)
            mean_pd = float(np.mean(pd_size_m(Pd)))
        text = (f"t {state.stamp:7.1f} s | seq {state.seq:6d} | {state.n:3d} landmarks | "
                f"{rate:5.1f} states/s | mean P_d size {mean_pd * 100:6.2f} cm")
        if health is not None:
            text += " | health " + ("ok" if health.ok else
                                    f"VIOLATIONS, suspects {list(map(int, health.suspects))}")
        return text


def _wait_alive(bus: ZenohBus, key: str, stop: threading.Event,
                children: list[_Child], timeout_s: float = 120.0) -> None:
    """Wait for a service's liveliness token (e.g. the camera) before going on."""
    deadline = time.monotonic() + timeout_s
    while not stop.is_set() and time.monotonic() < deadline:
        if bus.alive(key, timeout=1.0):
            return
        for child in children:
            if child.proc.poll() is not None:
                return  # the main loop reports it
        time.sleep(0.2)


def run(command: str, args: argparse.Namespace) -> int:
    if bus_flags(args).secure or bus_flags(args).name:
        raise ConfigError("the demo runs every service on loopback without TLS; for a secure "
                          "set-up start the services with their own identities "
                          "(docs/security.md)")
    setup_logging(args, "demo")
    s = settings_from_args(DemoSettings, args)
    flags = bus_flags(args)
    stop = stop_event()
    keys = Keys(flags.prefix)
    endpoint = _router_endpoint(flags.listen)
    log_dir = Path(s.log_dir or tempfile.mkdtemp(prefix="slamlens-demo-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    have_camera = importlib.util.find_spec("services.registration.service") is not None
    have_viewer = importlib.util.find_spec("services.visualiser.service") is not None
    http = _free_http(s.http) if have_viewer else ""
    common = ["--connect", endpoint, "--prefix", flags.prefix]

    plan: list[tuple[str, list[str]]] = [
        ("router", ["router", "--listen", endpoint, "--prefix", flags.prefix]),
    ]
    estimator = ["estimator", "--robot", s.robot, *common]
    if s.faulty:
        estimator += ["--fault", s.fault,
                      "--faulty-features", ",".join(map(str, s.faulty_features)),
                      "--fault-onset", str(s.fault_onset)]
        magnitude = s.fault_magnitude
        if magnitude is None and s.fault == "map-update":
            magnitude = 5e-4
        if magnitude is not None:
            estimator += ["--fault-magnitude", str(magnitude)]
    plan.append(("estimator", estimator))
    plan.append(("monitor", ["monitor", "--robot", s.robot, *common]))
    camera = None
    if have_camera and s.synthetic_camera:
        camera = s.camera
        plan.append(("registration", ["registration", "--camera", camera, "--robot", s.robot,
                                      "--source", "synthetic", *common]))
    link = f"http://{http}/"
    if have_viewer:
        viewer = ["viewer", "--robot", s.robot, "--http", http, *common]
        if camera:
            viewer += ["--camera", camera]
        from services.visualiser.web_access import is_loopback, new_token

        if not is_loopback(http.rpartition(":")[0].strip("[]")):
            # beyond loopback the viewer asks for a token: give it one, and put it in the link
            token = new_token()
            token_file = log_dir / "viewer.token"
            token_file.write_text(token + "\n")
            token_file.chmod(0o600)
            viewer += ["--token-file", str(token_file)]
            link += f"?token={token}"
        plan.append(("viewer", viewer))
    sim = ["sim", "--robot", s.robot, "--seed", str(s.seed), "--rate", str(s.rate),
           "--loops", str(s.loops), *common]
    if camera:
        sim += ["--hold", "3"]  # stand still at the start pose while the camera registers
    plan.append(("sim", sim))

    children: list[_Child] = []
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    bus: ZenohBus | None = None
    try:
        for name, argv in plan:
            if name == "sim" and camera and bus is not None:
                _wait_alive(bus, keys.camera_alive(camera), stop, children)
            path = log_dir / f"{name}.log"
            handle = path.open("w")
            proc = subprocess.Popen([sys.executable, "-m", "services", *argv], env=env,
                                    stdout=handle, stderr=subprocess.STDOUT)
            children.append(_Child(name, proc, path))
            if name == "router":
                time.sleep(0.5)  # the others connect to it
                bus = open_bus(BusSettings(connect=(endpoint,)))
        assert bus is not None
        summary = _Summary()
        bus.subscribe(keys.state(s.robot), summary.on_state)
        bus.subscribe(keys.health(s.robot), summary.on_health)
        print(f"slamlens demo: router {endpoint}, logs in {log_dir}", flush=True)
        if have_viewer:
            print(f"open {link} in a browser", flush=True)
        else:
            print("(the viewer is not installed: showing the summary only)", flush=True)
        deadline = time.monotonic() + s.duration_s if s.duration_s else None
        tty = sys.stdout.isatty()
        last_print = 0.0
        while not stop.wait(0.25):
            for child in children:
                code = child.proc.poll()
                if code is not None and child.name != "sim":
                    tail = child.log_path.read_text(errors="replace").splitlines()[-5:]
                    raise SlamlensError(f"{child.name} exited with code {code}; its log "
                                        f"({child.log_path}) ends:\n  " + "\n  ".join(tail))
            now = time.monotonic()
            if tty:
                print("\r" + summary.line()[:150].ljust(150), end="", flush=True)
            elif now - last_print >= 2.0:
                last_print = now
                print(summary.line(), flush=True)
            if deadline is not None and now >= deadline:
                break
        if tty:
            print()
        print("final: " + summary.line(), flush=True)
    finally:
        if bus is not None:
            bus.close()
        for child in reversed(children):
            if child.proc.poll() is None:
                child.proc.terminate()
        for child in reversed(children):
            try:
                child.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait()
    return 0
