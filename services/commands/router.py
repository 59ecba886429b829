"""``slamlens router``: the Zenoh library's own router, run in-process.

There is no router binary to install: a Python Zenoh session opened in ``router`` mode
routes for every client and peer that connects to it. It has no settings file (no
``--config``): Zenoh's configuration is ``--zenoh-config FILE``, with the flags over it only
where they are given. It listens where ``--listen`` says, else where the file says, else on
``tcp/127.0.0.1:7447`` (loopback only); ``--connect ENDPOINT`` links it to another router
(e.g. the robot's to the workstation's).

With ``--secure DIR --name router-X`` it serves mutual TLS only and enforces the roles of
every identity in DIR (docs/security.md, :mod:`slamlens.common.security`); what it refuses
shows in its log
(:mod:`slamlens.services.commands.router_log`).
"""

from __future__ import annotations

import argparse
import json
import logging

from slamlens.common.cli import bus_settings, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.endpoints import effective_endpoints
from slamlens.common.session import build_config, open_bus, router_settings
from slamlens.common.status import Report, announce
from slamlens.common.zenoh_bus import ZenohBus
from slamlens.services.commands.router_log import ZenohLog
from slamlens.services.commands.settings import RouterSettings

log = logging.getLogger("slamlens.router")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "router")
    own = settings_from_args(RouterSettings, args)
    bus_flags = bus_settings(args)
    settings = router_settings(bus_flags.listen, bus_flags.zenoh_config,
                               connect=bus_flags.connect, secure=bus_flags.secure,
                               name=bus_flags.name, prefix=bus_flags.prefix)
    conf = build_config(settings)  # every flag and file checked before anything opens
    acl = json.loads(conf.get_json("access_control"))
    if own.print_acl:
        print(json.dumps(acl, indent=2))
        return 0
    zenoh_log = ZenohLog(access_control=bool(acl.get("enabled")))
    zenoh_log.start()
    stop = stop_event()
    bus = open_bus(settings)
    try:
        endpoints = ", ".join(effective_endpoints(conf, "listen", "router"))
        links = effective_endpoints(conf, "connect", "router")
        linked = f", linked to {', '.join(links)}" if links else ""
        if settings.secure:
            names = [s["id"] for s in acl.get("subjects", [])]
            log.info("router %s listening on %s%s (mutual TLS); roles enforced for %s",
                     settings.name, endpoints, linked, ", ".join(names) or "nobody")
        else:
            log.info("router listening on %s%s", endpoints, linked)
        announce(bus, args, "router", lambda: _report(bus, zenoh_log))
        print("router ready", flush=True)
        stop.wait()
    finally:
        bus.close()
        zenoh_log.stop()
    refused = zenoh_log.reader.refused_total()
    print(f"router stopped{f': refused {refused} messages' if refused else ''}", flush=True)
    return 0


def _report(bus: ZenohBus, zenoh_log: ZenohLog) -> Report:
    """The router's status: the sessions linked to it (its admin space) and what it refused."""
    sessions = {"client": 0, "peer": 0, "router": 0}
    zid = str(bus.session.info.zid())
    for reply in bus.session.get(f"@/{zid}/session/transport/unicast/*", timeout=0.5):
        if reply.ok is not None:
            try:
                kind = json.loads(reply.ok.payload.to_bytes()).get("whatami", "")
            except ValueError:
                continue
            if kind in sessions:
                sessions[kind] += 1
    refused = zenoh_log.reader.refused_total()
    linked = f", {sessions['router']} routers" if sessions["router"] else ""
    return Report(state=f"{sessions['client']} clients{linked}",
                  counts={"clients": float(sessions["client"]),
                          "routers": float(sessions["router"]),
                          "peers": float(sessions["peer"]), "refused": float(refused)},
                  dropped=refused, rated=("refused",))
