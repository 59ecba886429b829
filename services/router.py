"""``slamlens router``: the Zenoh library's own router, run in-process.

There is no router binary to install: a Python Zenoh session opened in ``router`` mode
routes for every client and peer that connects to it.
"""

from __future__ import annotations

import argparse
import logging

from common.cli import add_common_flags, setup_logging, stop_event
from common.session import open_bus, router_settings

log = logging.getLogger("slamlens.router")


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    add_common_flags(parser, config=False)


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "router")
    stop = stop_event()
    bus = open_bus(router_settings(args.listen, args.zenoh_config, connect=args.connect))
    try:
        log.info("router listening on %s%s", ", ".join(args.listen or ["tcp/127.0.0.1:7447"]),
                 f", linked to {', '.join(args.connect)}" if args.connect else "")
        print("router ready", flush=True)
        stop.wait()
    finally:
        bus.close()
    print("router stopped", flush=True)
    return 0
