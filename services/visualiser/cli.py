"""``slamlens viewer``: the AR renderer and its web viewers.

Settings: :class:`slamlens.services.visualiser.settings.ViewerConfig` (flags built from it by
services/commands/cli.py).
"""

from __future__ import annotations

import argparse
import json
import logging

from slamlens.common.cli import command_bus, keys_from, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.status import Report, announce
from slamlens.services.visualiser.settings import ViewerConfig

log = logging.getLogger("slamlens.viewer")


def run(command: str, args: argparse.Namespace) -> int:
    # imported here so that `slamlens viewer --help` does not load the web stack
    from slamlens.services.visualiser.ar import ArHub, ArLimits
    from slamlens.services.visualiser.camera_sources import SourceWatch
    from slamlens.services.visualiser.service import ViewerService
    from slamlens.services.visualiser.web import WebServer, parse_http
    from slamlens.services.visualiser.web_access import (
        is_loopback,
        new_token,
        read_token,
        tls_context,
    )

    setup_logging(args, "viewer")
    config = settings_from_args(ViewerConfig, args)
    host, port = parse_http(config.http)
    # beyond loopback nothing is served without a token (docs/security.md)
    token = read_token(config.token_file) if config.token_file else (
        None if is_loopback(host) else new_token())
    if host in ("0.0.0.0", "::", ""):
        log.warning("the web viewer listens on every interface (%s): bind it to the one "
                    "interface its users reach (docs/security.md)", config.http)
    ssl_context = (None if config.tls_cert is None or config.tls_key is None
                   else tls_context(config.tls_cert, config.tls_key))
    stop = stop_event()
    bus = command_bus(args)
    keys = keys_from(args)
    service = ViewerService(bus, keys=keys, config=config)
    ar = None if config.max_ar_cameras == 0 else ArHub(
        bus, keys, service.api, base_camera=config.ar_camera, limits=ArLimits(
            max_cameras=config.max_ar_cameras, max_frame_bytes=config.max_ar_frame_bytes,
            max_frame_pixels=config.max_frame_pixels, max_fps=config.max_ar_fps,
            wait_s=config.ar_wait_s, jpeg_quality=config.jpeg_quality))
    sources = SourceWatch(bus, keys, config.cameras)
    web = WebServer(service, host=host, port=port, token=token,
                    allowed_hosts=config.allowed_hosts, allowed_origins=config.allowed_origins,
                    ar=ar, ssl_context=ssl_context, sources=sources)
    try:
        service.start()
        sources.start()
        url = web.start()

        def status() -> Report:
            now = service.api.status()
            state = now.get("state") or {}
            rates = {"states": float(state.get("rate_hz") or 0.0),
                     "rendered": float(now.get("fps") or 0.0)}
            return Report(state=f"serving {url}" if state else f"serving {url}, no state yet",
                          counts={"views": float(now.get("views_active") or 0),
                                  "clients": float(now.get("clients") or 0)},
                          rates=rates, rated=(),
                          dropped=int(sum(now.get("bad_messages", {}).values())))

        announce(bus, args, "viewer", status, robot=config.robot, camera=config.camera)
        if token is None:
            log.info("web viewer at %s", url)
        else:
            log.info("web viewer at %s: every request needs the access token (%s)", url,
                     f"from {config.token_file}" if config.token_file else "in the URL "
                     "printed on standard output")
        # a token read from a file stays out of the output (which may end up in a log)
        print(f"viewer ready {url if config.token_file else web.url_with_token}",
              flush=True)
        stop.wait()
        print(f"viewer stopped: {json.dumps(_final(service.api.status()))}", flush=True)
    finally:
        web.stop()
        sources.stop()
        service.stop()
        bus.close()
    return 0


def _final(status: dict) -> dict:
    """What the viewer did, for its last line: each robot's last state, what it refused."""
    return {"robots": {r["name"]: {"seq": (r["state"] or {}).get("seq"),
                                   "epoch": (r["state"] or {}).get("epoch"),
                                   "restarts": r["restarts"]} for r in status["robots"]},
            "cameras": [c["name"] for c in status["cameras"]],
            "clients": status["clients"], "bad_messages": status["bad_messages"],
            "failures": status["failures"]}
