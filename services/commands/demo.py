"""``slamlens demo``: the whole system on one machine, as real separate processes.

The demo is a launch (:mod:`slamlens.services.commands.launch`): from its settings it builds a
launch plan —
a Zenoh router on loopback, the estimator, the behaviour monitor, the synthetic overhead
camera with registration, the AR viewer and, once they are all ready, the simulated robot
(which first stands still while the camera registers) — writes it to ``LOG_DIR/demo.toml``
(``slamlens launch LOG_DIR/demo.toml`` runs the same group), and supervises it: each
service a ``slamlens`` process of its own, exactly as on several machines, its output in
``LOG_DIR/NAME.log``. It prints the browser link and a live one-line summary, and stops
everything on Ctrl-C (or after ``--duration``).

A taken port is refused, not replaced: the router's (``--listen``, default 7447) and the
viewer's (``--http``); port 0 asks for any free one, and the link printed is the real one.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import re
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from slamlens.common.cli import bus_flags, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError, MessageError, ServiceError
from slamlens.common.geometry import all_relative_covariances, pd_size_m
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.common.verdict import summary_text
from slamlens.services.commands.launch import Supervisor
from slamlens.services.commands.launch_file import plan_from_mapping, to_toml
from slamlens.services.commands.settings import DemoSettings

log = logging.getLogger("slamlens.demo")

DEFAULT_ROUTER_PORT = 7447


def _port_taken(host: str, port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return True
    return False


def _router_endpoint(listen: tuple[str, ...]) -> str:
    """Where the demo's router listens: ``--listen`` (port 0: a free one), else 7447 on
    loopback; a taken port is an error (another router or demo is running there)."""
    endpoint = str(listen[0]) if listen else f"tcp/127.0.0.1:{DEFAULT_ROUTER_PORT}"
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not port.isdigit():
        raise ConfigError(f"--listen {endpoint}: the demo's router listens on tcp/HOST:PORT")
    if int(port) == 0:
        return free_tcp_endpoint(host)
    if _port_taken(host, int(port)):
        raise ConfigError(f"port {port} on {host} is taken (another slamlens router or demo? "
                          "`slamlens status` lists what runs): stop it, or give --listen "
                          f"tcp/{host}:PORT (port 0: any free port)")
    return endpoint


def _check_http(host_port: str) -> str:
    """The viewer's address, if its port is free (port 0: the viewer picks one)."""
    host, _, port = host_port.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"--http {host_port}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    if int(port) and _port_taken(host, int(port)):
        raise ConfigError(f"viewer address {host_port} is taken (another viewer or demo?): "
                          f"stop it, or give --http {host}:PORT (port 0: any free port)")
    return host_port


def demo_launch(s: DemoSettings, *, endpoint: str, prefix: str, http: str | None,
                camera: str | None) -> dict[str, Any]:
    """The demo as a launch file's tables (:mod:`slamlens.services.commands.launch_file`)."""
    bus = {"connect": [endpoint], "prefix": prefix}
    services: dict[str, dict[str, Any]] = {
        "router": {"command": "router", "listen": [endpoint], "prefix": prefix},
    }
    estimator: dict[str, Any] = {"command": "estimator", "after": ["router"], "robot": s.robot,
                                 **bus}
    if s.faulty:
        estimator.update(fault=s.fault, faulty_features=list(s.faulty_features),
                         fault_onset=s.fault_onset)
        magnitude = s.fault_magnitude
        if magnitude is None and s.fault == "map-update":
            magnitude = 5e-4
        if magnitude is not None:
            estimator["fault_magnitude"] = magnitude
    services["estimator"] = estimator
    services["monitor"] = {"command": "monitor", "after": ["router"], "robot": s.robot, **bus}
    if camera:
        services["registration"] = {"command": "registration", "after": ["router"],
                                    "camera": camera, "robot": s.robot,
                                    "source": "synthetic", **bus}
    if http is not None:
        viewer: dict[str, Any] = {"command": "viewer", "after": ["router"], "robot": s.robot,
                                  "http": http, **bus}
        if camera:
            viewer["camera"] = camera
        services["viewer"] = viewer
    sim: dict[str, Any] = {"command": "sim", "after": [n for n in services if n != "router"],
                           "robot": s.robot, "seed": s.seed, "rate": s.rate,
                           "loops": s.loops, "required": False, **bus}
    if camera:
        sim["hold_s"] = 3.0  # stand still at the start pose while the camera registers
    services["sim"] = sim
    for table in services.values():  # a failure ends the demo with what it said
        table["respawn"] = False
        table.setdefault("required", True)
    return {"launch": {"description": "slamlens demo: every service on one machine",
                       "respawn": False},
            "service": services}


class _Summary:
    """The live one-line summary. The Zenoh callbacks only keep the newest payload and
    count; states are decoded by whoever asks for the line (the demo's own loop)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.states = 0
        self._state: bytes | None = None
        self._health: bytes | None = None
        self.times: list[float] = []

    def on_state(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.states += 1
            self._state = payload
            self.times.append(time.monotonic())
            if len(self.times) > 200:
                del self.times[:100]

    def on_health(self, key: str, payload: bytes) -> None:
        with self.lock:
            self._health = payload

    def line(self) -> str:
        with self.lock:
            state_bytes, health_bytes = self._state, self._health
            now = time.monotonic()
            recent = [t for t in self.times if now - t <= 2.0]
        state = health = None
        try:
            state = SlamState.from_bytes(state_bytes) if state_bytes else None
            health = Health.from_bytes(health_bytes) if health_bytes else None
        except MessageError:
            pass
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
            text += " | " + summary_text(health)  # the page's and the legend's words
        return text


def run(command: str, args: argparse.Namespace) -> int:
    flags = bus_flags(args)
    if flags.secure or flags.name:
        raise ConfigError("the demo runs every service on loopback without TLS; for a secure "
                          "set-up start the services with their own identities "
                          "(docs/security.md)")
    setup_logging(args, "demo")
    s = settings_from_args(DemoSettings, args)
    stop = stop_event(grace_s=None)  # its own stop is bounded: services killed after 1.5 s
    keys = Keys(flags.prefix)
    endpoint = _router_endpoint(flags.listen)
    have_camera = importlib.util.find_spec("slamlens.services.registration.service") is not None
    have_viewer = importlib.util.find_spec("slamlens.services.visualiser.service") is not None
    http = _check_http(s.http) if have_viewer else None
    camera = s.camera if have_camera and s.synthetic_camera else None
    raw = demo_launch(s, endpoint=endpoint, prefix=flags.prefix, http=http, camera=camera)
    plan = plan_from_mapping(raw, source="slamlens demo")
    log_dir = Path(s.log_dir or tempfile.mkdtemp(prefix="slamlens-demo-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    (log_dir / "demo.toml").write_text(
        "# `slamlens demo` as a launch file: `slamlens launch THIS_FILE` runs the same group\n"
        + to_toml(raw))

    supervisor = Supervisor(plan, echo=False, log_dir=str(log_dir))
    group_stop = threading.Event()
    errors: list[BaseException] = []

    def supervise() -> None:
        try:
            supervisor.run(group_stop)
        except BaseException as exc:  # said by the demo's own loop
            errors.append(exc)

    thread = threading.Thread(target=supervise, name="demo launch")
    thread.start()
    bus = None
    try:
        if not supervisor.wait_ready("router", stop):
            return _finish(thread, group_stop, errors, log_dir)
        bus = open_bus(BusSettings(connect=(endpoint,), prefix=flags.prefix))
        summary = _Summary()
        bus.subscribe(keys.state(s.robot), summary.on_state)
        bus.subscribe(keys.health(s.robot), summary.on_health)
        print(f"slamlens demo: router {endpoint}, logs in {log_dir}", flush=True)
        if http is not None:
            ready = supervisor.wait_ready("viewer", stop)
            url = re.search(r"(http://\S+)", ready)
            if url:  # beyond loopback the viewer puts its access token in it
                link = url.group(1) if "?" in url.group(1) else url.group(1).rstrip("/") + "/"
                print(f"open {link} in a browser", flush=True)
        else:
            print("(the viewer is not installed: showing the summary only)", flush=True)
        deadline = time.monotonic() + s.duration_s if s.duration_s else None
        tty = sys.stdout.isatty()
        last_print = 0.0
        while not stop.wait(0.25) and not errors and supervisor.failure is None:
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
        if supervisor.failure is None and not errors:
            print("final: " + summary.line(), flush=True)
    finally:
        if bus is not None:
            bus.close()
        code = _finish(thread, group_stop, errors, log_dir)
    return code


def _finish(thread: threading.Thread, group_stop: threading.Event,
            errors: list[BaseException], log_dir: Path) -> int:
    group_stop.set()
    thread.join()
    if errors:
        error = errors[0]
        if isinstance(error, ServiceError):
            raise ServiceError(f"{error} (logs in {log_dir})")
        raise error
    return 0
