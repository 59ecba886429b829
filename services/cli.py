"""The ``slamlens`` program: one command per service (SPEC §9).

Each command is a row of :data:`COMMANDS`: the module whose ``run(command, args) -> int``
runs it, its one-line help, and the settings dataclass its flags are built from
(:func:`slamlens.common.config.add_flags`; every field a TOML key of ``--config FILE`` and a flag).
Modules are imported only when needed, so ``slamlens sim`` never loads OpenCV and
``slamlens --help`` is instant; ``--help`` of a command loads only its settings module.
docs/cli.md is generated from the same parsers (``python -m slamlens.services.cli_reference``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from typing import Any

from slamlens.common.cli import add_common_flags, run_cli
from slamlens.common.config import add_flags
from slamlens.common.memory import keep_freed_memory

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
    "router": Command("router", "a Zenoh router, in-process (no binary to install)",
                      "settings:RouterSettings", config=False),
    "sim": Command("slam.cli", "simulated robot: odometry, observations, truth",
                   "slam.settings:SimSettings"),
    "estimator": Command("slam.cli", "the EKF-SLAM estimator service",
                         "slam.settings:EstimatorSettings"),
    "replay": Command("slam.cli", "a recorded dataset (MRCLAM) as a robot driver",
                      "slam.settings:ReplaySettings"),
    "serial": Command("slam.cli", "a real robot on a serial line",
                      "slam.settings:SerialSettings"),
    "monitor": Command("slam.cli", "the covariance behaviour monitor",
                       "slam.settings:MonitorSettings"),
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
    "figures": Command("figures",
                       "regenerate the paper's Figs. 3-8 (into docs/figures by default)",
                       "settings:FigureSettings", bus=False),
    "demo": Command("demo", "all of it on one machine, with a browser link",
                    "settings:DemoSettings"),
    "record": Command("recorder.cli", "record the bus into an MCAP file (with "
                      "Foxglove channels)", "recorder.settings:RecordSettings"),
    "play": Command("recorder.cli", "publish an MCAP recording back on the bus",
                    "recorder.settings:PlaySettings"),
    "foxglove": Command("recorder.cli", "the live scene over Foxglove's WebSocket "
                        "protocol", "recorder.settings:FoxgloveSettings"),
    "certs": Command("certs", "create or extend the certificate authority for "
                     "mutual TLS", "settings:CertsSettings", bus=False, config=False),
    "launch": Command("launch", "a described group of services, supervised: order, "
                      "readiness, respawn, one log", "settings:LaunchSettings",
                      bus=False, config=False),
    "status": Command("status", "every live service across hosts, with rates, drops "
                      "and epoch", "settings:StatusSettings", config=False),
    "register": Command("register", "re-register a camera and print the new "
                        "registration", "settings:RegisterSettings", config=False),
}


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser of ``slamlens NAME``: its settings' flags, then the common flags."""
    command = COMMANDS[name]
    parser = argparse.ArgumentParser(prog=f"slamlens {name}", description=command.help)
    groups: dict[str, Any] = {}
    cls = command.settings_class()
    if cls is not None:
        add_flags(parser, cls, title=f"{name} settings (also TOML keys of --config)",
                  groups=groups)
    add_common_flags(parser, bus=command.bus, config=cls is not None and command.config,
                     groups=groups)
    return parser


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slamlens", description="See whether an EKF-SLAM estimator is right.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, command in COMMANDS.items():
        sub.add_parser(name, help=command.help, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        parser = _parser()
        if not argv or argv[0] in {"-h", "--help"}:
            parser.print_help()
            return 0 if argv else 2
        parser.error(f"unknown command {argv[0]!r}; choose from {', '.join(COMMANDS)}")
    name = argv[0]
    args = command_parser(name).parse_args(argv[1:])
    keep_freed_memory()  # before the command starts any thread (common/memory.py)
    module = import_service_module(COMMANDS[name].module)
    return run_cli(lambda: module.run(name, args))


if __name__ == "__main__":
    sys.exit(main())
