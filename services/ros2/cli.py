"""Commands of the ROS 2 side: ``ros2`` (the bridge) and the rosbag2 player behind
``slamlens replay --format rosbag2``.

Each: its settings, a bus from the common flags, its work until SIGINT/SIGTERM (or the end
of the bag), one final line with its counts, and a clean close of the Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
from typing import Any

from slamlens.common.cli import command_bus, keys_from, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.common.progress import time_bar
from slamlens.common.status import Report, announce
from slamlens.services.ros2.settings import BagReplay, Ros2Settings

log = logging.getLogger("slamlens")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    return {"ros2": _run_bridge}[command](args)


def _run_bridge(args: argparse.Namespace) -> int:
    from slamlens.services.ros2.bridge import Ros2Bridge

    s = settings_from_args(Ros2Settings, args)
    stop = stop_event()
    bus = command_bus(args)
    try:
        bridge = Ros2Bridge(bus, keys=keys_from(args), settings=s)

        def status() -> Report:
            summary = bridge.summary()
            counts = {k: float(summary[k]) for k in ("states", "health", "received",
                                                     "imported")}
            return Report(state=f"domain {s.domain}, {s.distro}, from ROS: {s.from_ros}",
                          counts=counts, dropped=int(summary["dropped"]))

        announce(bus, args, "ros2", status, robot=s.robot)
        bridge.late_join()
        log.info("ROS 2 node %s in domain %d (%s): export %s, from ROS: %s",
                 s.node_name(), s.domain, s.distro, "on" if s.export else "off", s.from_ros)
        print("ros2 ready", flush=True)
        bridge.run(stop)
        print(f"ros2 stopped: {json.dumps(bridge.summary())}", flush=True)
        bridge.close()
    finally:
        bus.close()
    return 0


def _wait_for_estimator(out: Any, stop: threading.Event, s: BagReplay) -> bool:
    if not s.wait_for_estimator or out.wait_for_estimator(stop, timeout_s=s.wait_timeout_s):
        return True
    if stop.is_set():
        return False
    raise ConfigError(f"no estimator for robot {s.robot} appeared within "
                      f"{s.wait_timeout_s:g} s (use --no-wait to publish anyway)")


def run_bag(args: argparse.Namespace, s: BagReplay) -> int:
    """Play a rosbag2 folder as robot ``s.robot`` (inputs or estimates)."""
    from slamlens.common.robot_inputs import RobotPublisher, play
    from slamlens.services.ros2.bag import Bag
    from slamlens.services.ros2.states import StatePublisher

    setup_logging(args, "replay")
    bag = Bag(s.path, robot=s.robot, what=s.what)
    stop = stop_event()
    bus = command_bus(args)
    try:
        keys = keys_from(args)
        out: Any = (RobotPublisher(bus, keys=keys, robot=s.robot) if s.what == "inputs"
                    else StatePublisher(bus, keys=keys, robot=s.robot))
        state = {"now": "waiting for an estimator" if s.what == "inputs" else "replaying"}
        announce(bus, args, "replay", lambda: Report(
            state=state["now"], counts={k: float(v) for k, v in out.counts.items()}),
            robot=s.robot)
        print("replay ready", flush=True)
        if s.what == "inputs":
            if not _wait_for_estimator(out, stop, s):
                return 0
            if s.rate == 0 and s.wait_for_estimator:
                out.pace_on_estimator()
        state["now"] = "replaying"
        end = (s.start_s + s.duration_s) if s.duration_s else None
        total = (min(end, bag.duration_s) if end is not None else bag.duration_s) - s.start_s
        bar = time_bar(max(total, 0.0), desc=f"replay {s.robot}", mode=s.progress)
        try:
            wall = play(bag.events(start_s=s.start_s, end_s=end), out, stop, rate=s.rate,
                        bar=bar)
        finally:
            bar.close()
        applied = ""
        if getattr(out, "pacer", None) is not None and not stop.is_set():
            applied = (", all applied by the estimator" if out.pacer.drain(stop)
                       else ", NOT all applied: the estimator applied nothing for 10 s")
        verb = "stopped" if stop.is_set() else "done"
        counts = {**out.counts, "skipped": bag.stats.total_skipped}
        print(f"replay {verb}: {json.dumps(counts)} in {wall:.2f} s{applied}", flush=True)
    finally:
        bag.close()
        bus.close()
    return 0
