"""Commands of the SLAM side: ``sim``, ``estimator``, ``replay``, ``serial``, ``monitor``.

Each command: settings from ``--config FILE`` (TOML) with flags over it, a bus from the
common flags, the service's ``run`` until SIGINT/SIGTERM (or the end of the data), and a
clean close of the Zenoh session.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from common.cli import add_common_flags, bus_settings, keys_from, setup_logging, stop_event
from common.config import load_settings
from common.errors import ConfigError
from common.session import open_bus

log = logging.getLogger("slamlens")


@dataclass(frozen=True)
class SimSettings:
    """``slamlens sim`` settings (TOML keys = these names)."""

    robot: str = "robot1"  #: robot name (key segment)
    scenario: str = "paper"  #: a packaged world name, or the path of a world TOML file
    seed: int = 0  #: random seed: same seed, same run
    rate: float = field(default=1.0, metadata={"min": 0.0})  #: × real time; 0 = as fast as possible
    #: laps of the waypoint loop; 0 = the world's default
    loops: int = field(default=0, metadata={"min": 0})
    anonymous: bool = False  #: withhold landmark ids (id −1) to exercise data association
    wait_for_estimator: bool = True  #: hold the first message until an estimator is alive
    wait_timeout_s: float = field(default=60.0, metadata={"min": 0.0})
    #: seconds the robot stands at its start pose (truth repeated at 10 Hz) before it
    #: moves, so that a camera can register the map frame there (paper §3.1)
    hold_s: float = field(default=0.0, metadata={"min": 0.0})


@dataclass(frozen=True)
class ReplaySettings:
    """``slamlens replay`` settings."""

    robot: str = "robot1"
    format: str = field(default="mrclam", metadata={"choices": ("mrclam",)})
    robot_index: int = field(default=1, metadata={"min": 1})  #: MRCLAM Robot{k}_*.dat
    rate: float = field(default=1.0, metadata={"min": 0.0})
    start_s: float = 0.0  #: dataset seconds to skip from the start
    duration_s: float = 0.0  #: dataset seconds to play; 0 = all
    wait_for_estimator: bool = True
    wait_timeout_s: float = field(default=60.0, metadata={"min": 0.0})


@dataclass(frozen=True)
class SerialSettings:
    """``slamlens serial`` settings (wire protocol in docs/drivers.md)."""

    robot: str = "robot1"
    port: str = ""  #: device path or pyserial URL (e.g. /dev/ttyUSB0, loop://)
    baudrate: int = field(default=115200, metadata={"min": 1})


def _overrides(args: argparse.Namespace, names: list[str]) -> dict[str, Any]:
    return {n: getattr(args, n, None) for n in names}


# ---------------------------------------------------------------------------------
# arguments
# ---------------------------------------------------------------------------------


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    add_common_flags(parser)
    parser.add_argument("--robot", help="robot name (default robot1)")
    if command == "sim":
        parser.add_argument("--scenario", help="world: 'paper' or a world TOML file")
        parser.add_argument("--seed", type=int)
        parser.add_argument("--rate", type=float, help="× real time; 0 = as fast as possible")
        parser.add_argument("--loops", type=int, help="laps of the loop (default: the world's)")
        parser.add_argument("--anonymous", action="store_true", default=None,
                            help="publish landmark id −1 (estimator associates)")
        parser.add_argument("--no-wait", dest="wait_for_estimator", action="store_false",
                            default=None, help="do not wait for an estimator to be alive")
        parser.add_argument("--hold", dest="hold_s", type=float,
                            help="seconds standing at the start pose before moving "
                                 "(lets a camera register the map frame)")
    elif command == "estimator":
        for flag, text in [("--sigma-v", "odometry speed noise σ, m/s"),
                           ("--sigma-w", "odometry turn-rate noise σ, rad/s"),
                           ("--sigma-range", "range noise σ, m"),
                           ("--sigma-bearing", "bearing noise σ, rad"),
                           ("--gate-chi2", "association gate on d² (id −1)"),
                           ("--new-landmark-chi2", "d² above which an id −1 is a new landmark"),
                           ("--fault-magnitude", "size of the planted fault (docs/estimator.md)"),
                           ("--fault-onset", "stamp (s) from which the fault acts")]:
            parser.add_argument(flag, type=float, help=text)
        parser.add_argument("--fault", help="plant a documented fault: map-update, "
                            "cross-covariance (docs/estimator.md)")
        parser.add_argument("--faulty-features", help="feature ids the fault acts on: ID,ID")
        parser.add_argument("--checkpoint", metavar="DIR",
                            help="crash recovery: save the map in DIR (atomically, at least "
                                 "once a second) and resume it from there on a restart")
    elif command == "replay":
        parser.add_argument("path", help="dataset folder (e.g. ../shared/data/mrclam6)")
        parser.add_argument("--format", help="dataset format (mrclam)")
        parser.add_argument("--robot-index", type=int, help="which robot of the dataset")
        parser.add_argument("--rate", type=float, help="× real time; 0 = as fast as possible")
        parser.add_argument("--start", dest="start_s", type=float, help="skip seconds")
        parser.add_argument("--duration", dest="duration_s", type=float, help="seconds to play")
        parser.add_argument("--no-wait", dest="wait_for_estimator", action="store_false",
                            default=None)
    elif command == "serial":
        parser.add_argument("--port", help="serial device or pyserial URL")
        parser.add_argument("--baudrate", type=int)
    elif command == "monitor":
        parser.add_argument("--rtol", type=float,
                            help="relative tolerance of the Loewner-order checks (rtol_growth)")


# ---------------------------------------------------------------------------------
# commands
# ---------------------------------------------------------------------------------


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    return {"sim": _run_sim, "estimator": _run_estimator, "replay": _run_replay,
            "serial": _run_serial, "monitor": _run_monitor}[command](args)


def _estimator_ready(out: Any, stop: threading.Event, s: SimSettings | ReplaySettings) -> bool:
    """Wait (if configured) for the robot's estimator; False if stopped while waiting."""
    if not s.wait_for_estimator or out.wait_for_estimator(stop, timeout_s=s.wait_timeout_s):
        return True
    if stop.is_set():
        return False
    raise ConfigError(f"no estimator for robot {s.robot!r} appeared within "
                      f"{s.wait_timeout_s:g} s (use --no-wait to publish anyway)")


def _run_sim(args: argparse.Namespace) -> int:
    from services.slam.drivers import RobotPublisher, play
    from services.slam.sim import Simulator
    from services.slam.world import load_world

    s = load_settings(SimSettings, args.config, _overrides(
        args, ["robot", "scenario", "seed", "rate", "loops", "anonymous", "wait_for_estimator",
               "hold_s"]))
    world = load_world(s.scenario)
    sim = Simulator(world, robot=s.robot, seed=s.seed, anonymous=s.anonymous,
                    loops=s.loops or None)
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    try:
        out = RobotPublisher(bus, keys=keys_from(args), robot=s.robot)
        if not _estimator_ready(out, stop, s):
            return 0
        log.info("simulating %s, seed %d, %.0f s of robot time at %s", world.name, s.seed,
                 sim.duration_s, f"{s.rate:g}× real time" if s.rate else "full speed")
        events = iter(sim.events())
        first = next(events)  # the Truth at t = 0: the robot at its start pose
        if s.hold_s:
            log.info("standing at the start pose for %.1f s", s.hold_s)
            hold_until = time.monotonic() + s.hold_s
            while time.monotonic() < hold_until and not stop.is_set():
                out.publish(first)
                stop.wait(0.1)
        if s.rate == 0 and s.wait_for_estimator:
            out.pace_on_estimator()
        wall = play(itertools.chain([first], events), out, stop, rate=s.rate,
                    progress_every_s=10.0 if s.rate and s.rate <= 5 else 0.0)
        _finish("sim", out, stop, wall)
    finally:
        bus.close()
    return 0


def _finish(name: str, out: Any, stop: threading.Event, wall: float) -> None:
    """The driver's final line: what it published, and whether the estimator applied it."""
    applied = ""
    if out.pacer is not None and not stop.is_set():
        applied = (", all applied by the estimator" if out.pacer.drain(stop)
                   else ", NOT all applied by the estimator within 10 s")
    verb = "stopped" if stop.is_set() else "done"
    log.info("%s in %.2f s wall: %s", verb, wall, out.counts)
    print(f"{name} {verb}: {json.dumps(out.counts)} in {wall:.2f} s{applied}", flush=True)


def _estimator_overrides(args: argparse.Namespace) -> dict[str, Any]:
    names = ["robot", "sigma_v", "sigma_w", "sigma_range", "sigma_bearing", "gate_chi2",
             "new_landmark_chi2", "fault", "faulty_features", "fault_magnitude", "fault_onset",
             "checkpoint"]
    return _overrides(args, names)


def _one_blas_thread() -> None:
    """One BLAS thread unless the user says otherwise (set before numpy is imported).

    The estimator's O(n²) downdate is memory-bound and the monitor's Cholesky is small; on
    a shared machine a second BLAS thread waiting for a busy core stalls them by up to 20×
    (docs/estimator.md, docs/monitor.md).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _run_estimator(args: argparse.Namespace) -> int:
    _one_blas_thread()
    from services.slam.estimator import EstimatorSettings
    from services.slam.estimator_service import EstimatorService

    settings = load_settings(EstimatorSettings, args.config, _estimator_overrides(args))
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    try:
        service = EstimatorService(bus, keys=keys_from(args), settings=settings)
        fault = "" if settings.fault == "none" else (
            f", planted fault {settings.fault} on {list(settings.faulty_features)}")
        log.info("estimator for %s ready%s", settings.robot, fault)
        print("estimator ready", flush=True)
        service.run(stop)
        print(f"estimator stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def _run_replay(args: argparse.Namespace) -> int:
    from services.slam.drivers import RobotPublisher, play
    from services.slam.mrclam import load_mrclam

    s = load_settings(ReplaySettings, args.config, _overrides(
        args, ["robot", "format", "robot_index", "rate", "start_s", "duration_s",
               "wait_for_estimator"]))
    run_ = load_mrclam(args.path, robot=s.robot_index, robot_name=s.robot)
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    try:
        out = RobotPublisher(bus, keys=keys_from(args), robot=s.robot)
        if not _estimator_ready(out, stop, s):
            return 0
        events = run_.events(start=s.start_s or None,
                             end=(s.start_s + s.duration_s) if s.duration_s else None)
        if s.rate == 0 and s.wait_for_estimator:
            out.pace_on_estimator()
        wall = play(events, out, stop, rate=s.rate, progress_every_s=30.0)
        _finish("replay", out, stop, wall)
    finally:
        bus.close()
    return 0


def _run_serial(args: argparse.Namespace) -> int:
    from services.slam.drivers import RobotPublisher
    from services.slam.serial_link import SerialLink

    s = load_settings(SerialSettings, args.config,
                      _overrides(args, ["robot", "port", "baudrate"]))
    if not s.port:
        raise ConfigError("serial: --port is required (a device path or a pyserial URL)")
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    link = SerialLink(s.port, baudrate=s.baudrate, robot=s.robot)
    try:
        out = RobotPublisher(bus, keys=keys_from(args), robot=s.robot)
        print("serial ready", flush=True)
        for message in link.messages(stop):
            out.publish(message)
        print(f"serial stopped: published {json.dumps(out.counts)}, parser {link.stats}",
              flush=True)
    finally:
        link.close()
        bus.close()
    return 0


def _run_monitor(args: argparse.Namespace) -> int:
    _one_blas_thread()
    from services.slam.monitor_service import MonitorService
    from services.slam.monitor_settings import MonitorSettings

    settings = load_settings(MonitorSettings, args.config,
                             {"robot": args.robot, "rtol_growth": args.rtol})
    robot = settings.robot
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    try:
        service = MonitorService(bus, keys=keys_from(args), robot=robot, settings=settings)
        print("monitor ready", flush=True)
        service.run(stop)
        print(f"monitor stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0
