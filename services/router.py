"""``slamlens router``: the Zenoh library's own router, run in-process.

There is no router binary to install: a Python Zenoh session opened in ``router`` mode
routes for every client and peer that connects to it. It has no settings of its own (no
``--config``): Zenoh's configuration is ``--zenoh-config FILE``, with ``--listen`` over it.
"""

from __future__ import annotations

import argparse
import logging

from common.cli import bus_flags, setup_logging, stop_event
from common.session import open_bus, router_settings

log = logging.getLogger("slamlens.router")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "router")
    stop = stop_event()
    flags = bus_flags(args)
    bus = open_bus(router_settings(flags.listen, flags.zenoh_config or None,
                                   connect=flags.connect))
    try:
        log.info("router listening on %s%s", ", ".join(flags.listen or ["tcp/127.0.0.1:7447"]),
                 f", linked to {', '.join(flags.connect)}" if flags.connect else "")
        print("router ready", flush=True)
        stop.wait()
    finally:
        bus.close()
    print("router stopped", flush=True)
    return 0
