"""Every ``slamlens`` command, registered here: the module that runs it, its one-line help,
and the settings dataclass its flags and TOML keys are built from.

A command's module (under ``slamlens.services``) has ``run(command, args) -> int``; it is
imported only when the command runs, and ``--help`` loads only its settings module, so
``slamlens sim`` never loads OpenCV and ``slamlens --help`` is instant. A test holds every
row to its module and class (tests/unit/test_cli.py).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

PACKAGE = "slamlens.services"  #: where the commands' modules are


@dataclass(frozen=True)
class Command:
    """One ``slamlens`` command."""

    module: str  #: module with ``run(command, args) -> int``, under ``slamlens.services``
    help: str  #: one line, for ``slamlens --help`` and the command's own
    settings: str = ""  #: "module:Class" of its settings (flags + TOML keys), under
    #: ``slamlens.services``; "" = none
    bus: bool = True  #: takes the common bus flags (--connect, --listen, --zenoh-config …)
    config: bool = True  #: its settings may come from --config FILE (False: flags only)

    def settings_class(self) -> type | None:
        if not self.settings:
            return None
        module, _, name = self.settings.partition(":")
        cls: type = getattr(import_service_module(module), name)
        return cls


def import_service_module(name: str) -> Any:
    """The module ``slamlens.services.NAME``."""
    return importlib.import_module(f"{PACKAGE}.{name}")


COMMANDS: dict[str, Command] = {
    "router": Command("commands.router", "a Zenoh router, in-process (no binary to install)",
                      "commands.settings:RouterSettings", config=False),
    "sim": Command("slam.cli", "simulated robot: odometry, observations, truth",
                   "slam.settings:SimSettings"),
    "estimator": Command("slam.cli", "the EKF-SLAM estimator service",
                         "slam.settings:EstimatorSettings"),
    "replay": Command("commands.replay", "a recorded dataset (MRCLAM, rosbag2) as a robot "
                      "driver", "slam.settings:ReplaySettings"),
    "serial": Command("slam.cli", "a real robot on a serial line",
                      "slam.settings:SerialSettings"),
    "monitor": Command("monitor.cli", "the covariance behaviour monitor",
                       "monitor.settings:MonitorSettings"),
    "summary": Command("slam.cli", "what remote viewers draw of the newest state, "
                       "on request", "slam.settings:SummarySettings"),
    "tune": Command("slam.cli", "noise settings fitted to runs with ground truth",
                    "slam.settings:TuneSettings", bus=False),
    "registration": Command("registration.cli",
                            "camera capture and fiducial registration",
                            "registration.settings:RegistrationSettings"),
    "calibrate": Command("registration.cli",
                         "camera intrinsics from ChArUco board images",
                         "registration.settings:CalibrateSettings", bus=False),
    "detect": Command("registration.cli", "the fiducial markers in images (text or JSON)",
                      "registration.settings:DetectSettings", bus=False),
    "viewer": Command("visualiser.cli", "the AR renderer and its web viewers",
                      "visualiser.settings:ViewerConfig"),
    "figures": Command("commands.figures",
                       "regenerate the paper's Figs. 3-8 (into docs/figures by default)",
                       "commands.settings:FigureSettings", bus=False),
    "demo": Command("commands.demo", "all of it on one machine, with a browser link",
                    "commands.settings:DemoSettings"),
    "record": Command("recorder.cli", "record the bus into an MCAP file (with "
                      "Foxglove channels)", "recorder.settings:RecordSettings"),
    "play": Command("recorder.cli", "publish an MCAP recording back on the bus",
                    "recorder.settings:PlaySettings"),
    "foxglove": Command("recorder.cli", "the live scene over Foxglove's WebSocket "
                        "protocol", "recorder.settings:FoxgloveSettings"),
    "ros2": Command("ros2.cli", "a robot to and from ROS 2 over rmw_zenoh: RViz markers, "
                    "pose, path, tf, health; a ROS 2 estimator or robot in",
                    "ros2.settings:Ros2Settings"),
    "rerun": Command("rerun.cli", "the live scene into Rerun (an .rrd file, a viewer, "
                     "a gRPC server); needs the rerun extra", "rerun.settings:RerunSettings"),
    "certs": Command("commands.certs", "create or extend the certificate authority for "
                     "mutual TLS", "commands.settings:CertsSettings", bus=False, config=False),
    "launch": Command("commands.launch", "a described group of services, supervised: order, "
                      "readiness, respawn, one log", "commands.settings:LaunchSettings",
                      bus=False, config=False),
    "status": Command("commands.status", "every live service across hosts, with rates, drops "
                      "and epoch", "commands.settings:StatusSettings", config=False),
    "register": Command("commands.register", "re-register a camera and print the new "
                        "registration", "commands.settings:RegisterSettings", config=False),
}
