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
from common.cli import add_common_flags, setup_logging, stop_event
from common.errors import ConfigError, MessageError, SlamlensError
from common.geometry import all_relative_covariances, pd_size_m
from common.keys import Keys
from common.messages import Health, SlamState
from common.session import BusSettings, free_tcp_endpoint, open_bus

log = logging.getLogger("slamlens.demo")

#: features planted faulty by ``--faulty`` (ids of the paper world; one per cluster pair)
DEFAULT_FAULTY = "3,12"


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    add_common_flags(parser, config=False)
    parser.add_argument("--robot", default="robot1")
    parser.add_argument("--camera", default="overhead")
    parser.add_argument("--http", default="127.0.0.1:8080", help="viewer address HOST:PORT")
    parser.add_argument("--rate", type=float, default=1.0, help="× real time (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--loops", type=int, default=1000, help="laps of the loop (default: "
                        "practically endless)")
    parser.add_argument("--faulty", action="store_true",
                        help="plant the paper's programming fault in the estimator")
    parser.add_argument("--fault", default="map-update", help="fault kind with --faulty")
    parser.add_argument("--faulty-features", default=DEFAULT_FAULTY)
    parser.add_argument("--fault-onset", type=float, default=0.0)
    parser.add_argument("--fault-magnitude", type=float,
                        help="size of the fault (docs/estimator.md); for map-update the demo "
                             "uses 5e-4 m² unless given: the faulty glyphs grow clearly "
                             "without covering the picture (the estimator's own default, "
                             "2e-3, is the figures' stronger fault)")
    parser.add_argument("--no-camera", action="store_true",
                        help="no synthetic camera: the viewer shows the map view")
    parser.add_argument("--duration", type=float, default=0.0,
                        help="stop after this many seconds (0 = until Ctrl-C)")
    parser.add_argument("--log-dir", help="folder for the services' logs (default: a temp dir)")


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


def _router_endpoint(args: argparse.Namespace) -> str:
    if args.listen:
        endpoint = str(args.listen[0])
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
    if args.secure or args.name:
        raise ConfigError("the demo runs every service on loopback without TLS; for a secure "
                          "set-up start the services with their own identities "
                          "(docs/security.md)")
    setup_logging(args, "demo")
    stop = stop_event()
    keys = Keys(args.prefix)
    endpoint = _router_endpoint(args)
    log_dir = Path(args.log_dir or tempfile.mkdtemp(prefix="slamlens-demo-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    have_camera = importlib.util.find_spec("services.registration.service") is not None
    have_viewer = importlib.util.find_spec("services.visualiser.service") is not None
    http = _free_http(args.http) if have_viewer else ""
    common = ["--connect", endpoint, "--prefix", args.prefix]

    plan: list[tuple[str, list[str]]] = [
        ("router", ["router", "--listen", endpoint, "--prefix", args.prefix]),
    ]
    estimator = ["estimator", "--robot", args.robot, *common]
    if args.faulty:
        estimator += ["--fault", args.fault, "--faulty-features", args.faulty_features,
                      "--fault-onset", str(args.fault_onset)]
        magnitude = args.fault_magnitude
        if magnitude is None and args.fault == "map-update":
            magnitude = 5e-4
        if magnitude is not None:
            estimator += ["--fault-magnitude", str(magnitude)]
    plan.append(("estimator", estimator))
    plan.append(("monitor", ["monitor", "--robot", args.robot, *common]))
    camera = None
    if have_camera and not args.no_camera:
        camera = args.camera
        plan.append(("registration", ["registration", "--camera", camera, "--robot", args.robot,
                                      "--source", "synthetic", *common]))
    if have_viewer:
        viewer = ["viewer", "--robot", args.robot, "--http", http, *common]
        if camera:
            viewer += ["--camera", camera]
        plan.append(("viewer", viewer))
    sim = ["sim", "--robot", args.robot, "--seed", str(args.seed), "--rate", str(args.rate),
           "--loops", str(args.loops), *common]
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
        bus.subscribe(keys.state(args.robot), summary.on_state)
        bus.subscribe(keys.health(args.robot), summary.on_health)
        print(f"slamlens demo: router {endpoint}, logs in {log_dir}", flush=True)
        if have_viewer:
            print(f"open http://{http}/ in a browser", flush=True)
        else:
            print("(the viewer is not installed: showing the summary only)", flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
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
