"""The ``slamlens`` program: one command per service (SPEC §9).

Each command lives in its service's ``cli.py`` and is imported only when run, so
``slamlens sim`` never loads OpenCV and ``slamlens --help`` is instant. A command module
exposes ``add_arguments(command, parser)`` and ``run(command, args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from common.cli import run_cli

#: command → (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "router": ("services.router", "a Zenoh router, in-process (no binary to install)"),
    "sim": ("services.slam.cli", "simulated robot: odometry, observations, truth"),
    "estimator": ("services.slam.cli", "the EKF-SLAM estimator service"),
    "replay": ("services.slam.cli", "a recorded dataset (MRCLAM) as a robot driver"),
    "serial": ("services.slam.cli", "a real robot on a serial line"),
    "monitor": ("services.slam.cli", "the covariance behaviour monitor"),
    "registration": ("services.registration.cli", "camera capture and fiducial registration"),
    "calibrate": ("services.registration.cli", "camera intrinsics from ChArUco board images"),
    "viewer": ("services.visualiser.cli", "the AR renderer and its web viewers"),
    "figures": ("services.visualiser.cli", "regenerate the paper's Figs. 3-8 into docs/"),
    "demo": ("services.demo", "all of it on one machine, with a browser link"),
    "certs": ("services.certs", "create or extend the certificate authority of SPEC §7b"),
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slamlens", description="See whether an EKF-SLAM estimator is right.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_module, text) in COMMANDS.items():
        sub.add_parser(name, help=text, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        parser = _parser()
        if not argv or argv[0] in {"-h", "--help"}:
            parser.print_help()
            return 0 if argv else 2
        parser.error(f"unknown command {argv[0]!r}; choose from {', '.join(COMMANDS)}")
    command = argv[0]
    module = importlib.import_module(COMMANDS[command][0])
    parser = argparse.ArgumentParser(prog=f"slamlens {command}",
                                     description=COMMANDS[command][1])
    module.add_arguments(command, parser)
    args = parser.parse_args(argv[1:])
    return run_cli(lambda: module.run(command, args))


if __name__ == "__main__":
    sys.exit(main())
