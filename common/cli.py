"""Pieces every service's ``cli.py`` shares: common flags, logging, stop signals, errors.

Common flags (docs/cli.md) are settings too (:mod:`slamlens.common.config`), declared once below:
:class:`BusFlags` (``--connect ENDPOINT`` repeatable, ``--listen ENDPOINT``,
``--zenoh-config FILE``, ``--prefix``, ``--secure DIR --name NAME`` for mutual TLS with an
identity, docs/security.md) for every command on the bus, ``--config FILE`` for
every command with settings, and :class:`LogFlags` (``-v``/``-q``) for all. A new common
flag is one more field here (then read it from :func:`bus_flags`).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from slamlens.common.config import add_flags, flag_values, setting, settings_from_mapping
from slamlens.common.errors import SlamlensError
from slamlens.common.keys import DEFAULT_PREFIX, Keys
from slamlens.common.session import BusSettings

log = logging.getLogger("slamlens")


@dataclass(frozen=True)
class BusFlags:
    """How a command reaches the bus (flags only: no TOML key)."""

    connect: tuple[str, ...] = setting(
        (), doc="Zenoh endpoint to connect to (repeatable); with neither --connect nor "
                "--listen: a client of tcp/127.0.0.1:7447", metavar="ENDPOINT",
        action="append", group="bus")
    listen: tuple[str, ...] = setting(
        (), doc="Zenoh endpoint to listen on (repeatable)", metavar="ENDPOINT",
        action="append", group="bus")
    zenoh_config: str = setting(
        "", doc="Zenoh JSON5 config file; empty = Zenoh's defaults (the flags above override "
                "it)", metavar="FILE",
        group="bus")
    prefix: str = setting(DEFAULT_PREFIX, doc="key prefix of every key expression",
                          group="bus")
    secure: str = setting(
        "", doc="folder of the certificate authority (slamlens certs): mutual TLS with the "
                "identity --name; endpoints must then be tls/HOST:PORT (default "
                "tls/127.0.0.1:7447); empty = plain", metavar="DIR", group="bus")
    name: str = setting(
        "", doc="the identity in --secure DIR, e.g. robot-robot1 (docs/security.md)",
        metavar="NAME", group="bus")


@dataclass(frozen=True)
class ConfigFlag:
    """Where a command's settings file is (a flag only)."""

    config: str = setting("", doc="TOML file with this command's settings (flags override it)",
                          metavar="FILE", group="settings file")


@dataclass(frozen=True)
class LogFlags:
    """How much a command logs (flags only)."""

    verbose: int = setting(0, doc="more logging", short="-v", action="count", group="logging")
    quiet: bool = setting(False, doc="warnings and errors only", short="-q", group="logging")


def add_common_flags(parser: argparse.ArgumentParser, *, bus: bool = True,
                     config: bool = True, groups: dict[str, Any] | None = None) -> None:
    """Add the common flags (docs/cli.md): the bus flags, ``--config FILE``, ``-v``/``-q``."""
    groups = {} if groups is None else groups
    if bus:
        add_flags(parser, BusFlags, groups=groups)
    if config:
        add_flags(parser, ConfigFlag, groups=groups)
    add_flags(parser, LogFlags, groups=groups)


def bus_flags(args: argparse.Namespace) -> BusFlags:
    """The common bus flags as given (defaults for those that were not)."""
    return settings_from_mapping(BusFlags, flag_values(BusFlags, args), source="flags")


def log_flags(args: argparse.Namespace) -> LogFlags:
    """``-v`` / ``-q`` as given."""
    return settings_from_mapping(LogFlags, flag_values(LogFlags, args), source="flags")


def bus_settings(args: argparse.Namespace) -> BusSettings:
    flags = bus_flags(args)
    return BusSettings(connect=flags.connect, listen=flags.listen,
                       zenoh_config=flags.zenoh_config or None, secure=flags.secure or None,
                       name=flags.name or None, prefix=flags.prefix)


def keys_from(args: argparse.Namespace) -> Keys:
    return Keys(bus_flags(args).prefix)


def setup_logging(args: argparse.Namespace, name: str) -> None:
    flags = log_flags(args)
    level = logging.WARNING if flags.quiet else (
        logging.DEBUG if flags.verbose else logging.INFO)
    logging.basicConfig(level=level, stream=sys.stderr,
                        format=f"%(asctime)s {name} %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")


#: seconds a service may take to shut down after SIGINT/SIGTERM before it is cut short
#: (docs/delivery.md: every service exits within 2 s of a signal, in every state, on any load)
SHUTDOWN_GRACE_S = 1.8


def stop_event(grace_s: float | None = SHUTDOWN_GRACE_S) -> threading.Event:
    """An event set by SIGINT or SIGTERM, so services shut down cleanly.

    The first signal sets the event and arms a watchdog: a service whose clean shutdown
    (joining its threads, closing its Zenoh session) has not ended ``grace_s`` later — on an
    oversubscribed machine it can take seconds — says so in one line and exits with status
    0 at once, so it never outlives its 2 s. ``grace_s=None`` (the recorder, which must
    finish its file) waits for the clean end however long it takes.
    """
    event = threading.Event()

    def overdue(reason: str) -> None:
        try:
            print(f"slamlens: {reason}: exiting now", file=sys.stderr, flush=True)
            sys.stdout.flush()
        finally:
            os._exit(0)

    def handler(signum: int, frame: object) -> None:
        if event.is_set():  # already shutting down, within the watchdog's time (a Ctrl-C
            return          # reaches a launch's services from the terminal and the launch)
        event.set()
        if grace_s is not None:
            timer = threading.Timer(grace_s, overdue,
                                    args=(f"the shutdown took longer than {grace_s:g} s",))
            timer.daemon = True
            timer.start()

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
