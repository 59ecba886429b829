"""``slamlens viewer`` (the AR renderer and its web viewers) and ``slamlens figures``."""

from __future__ import annotations

import argparse
import logging

from common.cli import add_common_flags, bus_settings, keys_from, setup_logging, stop_event
from common.config import load_settings
from common.session import open_bus

log = logging.getLogger("slamlens.viewer")


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    if command == "figures":
        parser.add_argument("--output-dir", default="docs/figures",
                            help="where fig3a.png … are written (default: docs/figures)")
        parser.add_argument("--seed", type=int, default=None,
                            help="seed of the simulated runs (default: the figures' own)")
        parser.add_argument("-v", "--verbose", action="count", default=0)
        parser.add_argument("-q", "--quiet", action="store_true")
        return
    parser.add_argument("--robot", help="robot whose state is shown (default: robot1)")
    parser.add_argument("--camera", help="camera to draw over (default: none, the map view)")
    parser.add_argument("--view", choices=("auto", "camera", "map", "stereo"),
                        help="auto (default): the camera if one is named, else the map; "
                             "stereo: cameras C-left/C-right, or a stereo pair of the map")
    parser.add_argument("--http", metavar="HOST:PORT",
                        help="address of the web viewer (default: 127.0.0.1:8080; port 0: any)")
    parser.add_argument("--fps", type=float, help="render rate cap, Hz (default: 30)")
    parser.add_argument("--jpeg-quality", type=int, help="JPEG quality 10-100 (default: 80)")
    parser.add_argument("--recordings-dir", help="where recordings go (default: recordings)")
    parser.add_argument("--record-codec", choices=("mp4v", "MJPG"),
                        help="video codec: mp4v (.mp4, default) or MJPG (.avi)")
    parser.add_argument("--stereo-baseline", type=float, dest="stereo_baseline_m",
                        help="baseline of the map view's stereo pair, m (default: 0.065)")
    add_common_flags(parser)


def run(command: str, args: argparse.Namespace) -> int:
    if command == "figures":
        setup_logging(args, "figures")
        from services.visualiser.figures import main as figures_main

        return int(figures_main(args) or 0)
    return _run_viewer(args)


def _run_viewer(args: argparse.Namespace) -> int:
    # imported here so that `slamlens figures --help` does not load the web stack
    from services.visualiser.service import ViewerConfig, ViewerService
    from services.visualiser.web import WebServer, parse_http

    setup_logging(args, "viewer")
    overrides = {k: getattr(args, k) for k in (
        "robot", "camera", "view", "http", "fps", "jpeg_quality", "recordings_dir",
        "record_codec", "stereo_baseline_m")}
    config = load_settings(ViewerConfig, args.config, overrides)
    host, port = parse_http(config.http)
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    service = ViewerService(bus, keys=keys_from(args), config=config)
    web = WebServer(service, host=host, port=port)
    try:
        service.start()
        url = web.start()
        log.info("web viewer at %s", url)
        print(f"viewer ready {url}", flush=True)
        stop.wait()
    finally:
        web.stop()
        service.stop()
        bus.close()
    return 0
