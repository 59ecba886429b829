"""Pieces every service's ``cli.py`` shares: common flags, logging, stop signals, errors.

Common flags (SPEC §9): ``--connect ENDPOINT`` (repeatable), ``--listen ENDPOINT``,
``--zenoh-config FILE``, ``--prefix``, ``--config FILE``, ``--secure DIR --name NAME``
(SPEC §7b: mutual TLS with that identity), plus ``-v``/``-q`` for logging.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable

from common.errors import SlamlensError
from common.keys import DEFAULT_PREFIX, Keys
from common.session import BusSettings

log = logging.getLogger("slamlens")


def add_common_flags(parser: argparse.ArgumentParser, *, config: bool = True) -> None:
    """Add the SPEC §9 common flags to a service's parser."""
    g = parser.add_argument_group("bus")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to (repeatable); default tcp/127.0.0.1:7447")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 config file (flags override it)")
    g.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix (default: slamlens)")
    g.add_argument("--secure", metavar="DIR",
                   help="mutual TLS with an identity of the authority in DIR (slamlens certs); "
                        "endpoints must then be tls/HOST:PORT (default tls/127.0.0.1:7447)")
    g.add_argument("--name", metavar="NAME",
                   help="the identity in --secure DIR to use, e.g. robot-r1 (docs/security.md)")
    if config:
        parser.add_argument("--config", metavar="FILE",
                            help="TOML file with this service's settings (flags override it)")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


def bus_settings(args: argparse.Namespace) -> BusSettings:
    return BusSettings(connect=tuple(args.connect), listen=tuple(args.listen),
                       zenoh_config=args.zenoh_config, secure=getattr(args, "secure", None),
                       name=getattr(args, "name", None), prefix=args.prefix)


def keys_from(args: argparse.Namespace) -> Keys:
    return Keys(args.prefix)


def setup_logging(args: argparse.Namespace, name: str) -> None:
    level = logging.WARNING if getattr(args, "quiet", False) else (
        logging.DEBUG if getattr(args, "verbose", 0) else logging.INFO)
    logging.basicConfig(level=level, stream=sys.stderr,
                        format=f"%(asctime)s {name} %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")


def stop_event() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so services shut down cleanly."""
    event = threading.Event()

    def handler(signum: int, frame: object) -> None:
        event.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)
    return event


def run_cli(fn: Callable[[], int | None]) -> int:
    """Run a service's main: known errors become one line on stderr and exit code 1."""
    try:
        code = fn()
    except SlamlensError as exc:
        print(f"slamlens: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    return int(code or 0)
