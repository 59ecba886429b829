"""``slamlens router``: the Zenoh library's own router, run in-process.

There is no router binary to install: a Python Zenoh session opened in ``router`` mode
routes for every client and peer that connects to it. It listens where ``--listen`` says,
else where ``--zenoh-config FILE`` says, else on ``tcp/127.0.0.1:7447`` (loopback only),
and ``--connect ENDPOINT`` links it to another router (e.g. the robot's to the workstation's).

With ``--secure DIR --name router-X`` it serves mutual TLS only and enforces the roles of
every identity in DIR (SPEC §7b, :mod:`common.security`); what it refuses shows in its log
(:mod:`services.router_log`).
"""

from __future__ import annotations

import argparse
import json
import logging

from common.cli import add_common_flags, setup_logging, stop_event
from common.session import build_config, effective_endpoints, open_bus, router_settings
from services.router_log import ZenohLog

log = logging.getLogger("slamlens.router")


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    add_common_flags(parser, config=False)
    parser.add_argument("--print-acl", action="store_true",
                        help="print the access control generated from --secure DIR and exit")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "router")
    settings = router_settings(args.listen, args.zenoh_config, connect=args.connect,
                               secure=args.secure, name=args.name, prefix=args.prefix)
    conf = build_config(settings)  # every flag and file checked before anything opens
    acl = json.loads(conf.get_json("access_control"))
    if args.print_acl:
        print(json.dumps(acl, indent=2))
        return 0
    zenoh_log = ZenohLog(access_control=bool(acl.get("enabled")))
    zenoh_log.start()
    stop = stop_event()
    bus = open_bus(settings)
    try:
        endpoints = effective_endpoints(conf, "listen", "router")
        links = effective_endpoints(conf, "connect", "router")
        if links:
            log.info("linking to the router(s) at %s", ", ".join(links))
        if settings.secure:
            names = [s["id"] for s in acl.get("subjects", [])]
            log.info("router %s listening on %s (mutual TLS); roles enforced for %s",
                     settings.name, ", ".join(endpoints), ", ".join(names) or "nobody")
        else:
            log.info("router listening on %s", ", ".join(endpoints))
        print("router ready", flush=True)
        stop.wait()
    finally:
        bus.close()
        zenoh_log.stop()
        refused = zenoh_log.reader.refused_total()
        log.info("router stopped%s", f": refused {refused} messages" if refused else "")
    return 0
