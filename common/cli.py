"""Pieces every service's ``cli.py`` shares: common flags, logging, stop signals, errors.

Common flags (docs/cli.md) are settings too (:mod:`slamlens.common.config`), declared once below:
:class:`BusFlags` (``--connect ENDPOINT`` repeatable, ``--listen ENDPOINT``,
``--zenoh-config FILE``, ``--prefix``, ``--secure DIR --name NAME`` for mutual TLS with an
identity, docs/security.md) for every command on the bus, ``--config FILE`` for
every command with settings, and :class:`LogFlags` (``-v``/``-q``) for all. A new common
flag is one more field here (then read it from :func:`bus_flags`).

Stop signals: :func:`stop_event`, which acts on the first SIGINT or SIGTERM whichever
thread receives it, and :func:`run_cli`, which then ends the process as soon as the command
has returned.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NoReturn

from slamlens.common.bus import Bus
from slamlens.common.config import add_flags, flag_values, setting, settings_from_mapping
from slamlens.common.errors import SlamlensError
from slamlens.common.keys import DEFAULT_PREFIX, Keys
from slamlens.common.session import BusSettings, open_bus

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


def command_bus(args: argparse.Namespace) -> Bus:
    """The bus a command talks on, opened as its bus flags say (``--connect``, ``--listen``,
    ``--zenoh-config``, ``--secure``, ``--name``, ``--prefix``): every command's one preamble."""
    return open_bus(bus_settings(args))


def keys_from(args: argparse.Namespace) -> Keys:
    return Keys(bus_flags(args).prefix)


def one_blas_thread() -> None:
    """One BLAS thread unless the user says otherwise (call it before numpy is imported).

    The estimator's O(n²) downdate is memory-bound and the monitor's Cholesky is small; on
    a shared machine a second BLAS thread waiting for a busy core stalls them by up to 20×
    (docs/estimator.md, docs/monitor.md).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


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
#: the signals that stop a service
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _recorded_only(signum: int, frame: object) -> None:
    """The Python-level handler: nothing to do (:class:`_StopTaker` acts on the signal)."""


class _StopTaker:
    """The process's one taker of the stop signals (see :func:`stop_event`).

    Python's C-level signal handler runs on whichever thread the kernel delivered the
    signal to and writes the signal's number to the wakeup fd; this object's daemon thread
    ``slamlens-stop`` reads it there at once and stops the service. The pipe's two ends are
    raw descriptors that stay open for the life of the process (a closed wakeup fd could
    be reused by another file).
    """

    def __init__(self) -> None:
        self._read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)  # the C handler must never block
        self._lock = threading.Lock()
        self._event: threading.Event | None = None
        self._grace_s: float | None = None
        signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        threading.Thread(target=self._take, name="slamlens-stop", daemon=True).start()

    def serve(self, event: threading.Event, grace_s: float | None) -> None:
        """From now on the stop signals set ``event`` (and arm a watchdog of ``grace_s``)."""
        with self._lock:
            self._event, self._grace_s = event, grace_s

    def stopping(self) -> bool:
        """Whether a stop signal has set the current event."""
        with self._lock:
            return self._event is not None and self._event.is_set()

    def _take(self) -> None:
        while True:
            taken = os.read(self._read_fd, 64)
            if any(number in STOP_SIGNALS for number in taken):
                self._stop()

    def _stop(self) -> None:
        with self._lock:
            event, grace_s = self._event, self._grace_s
        # a later signal: already shutting down, within the watchdog's time (a Ctrl-C
        # reaches a launch's services both from the terminal and from the launch)
        if event is None or event.is_set():
            return
        event.set()
        if grace_s is not None:
            timer = threading.Timer(grace_s, _overdue,
                                    args=(f"the shutdown took longer than {grace_s:g} s",))
            timer.daemon = True
            timer.start()


def _overdue(reason: str) -> None:
    try:
        print(f"slamlens: {reason}: exiting now", file=sys.stderr, flush=True)
        sys.stdout.flush()
    finally:
        os._exit(0)


_taker: _StopTaker | None = None


def stop_event(grace_s: float | None = SHUTDOWN_GRACE_S) -> threading.Event:
    """An event set by the first SIGINT or SIGTERM, so services shut down cleanly.

    The kernel delivers a signal sent to the process to any of its threads that does not
    block it, and a Zenoh session runs many; Python runs its signal handlers only in the
    main thread, and only once that thread runs Python code again, which a main thread
    waiting without a timeout (``stop.wait()``, a join) never does. So the handler here
    does not act: Python's C-level handler, on whichever thread received the signal,
    writes its number to the wakeup fd (:func:`signal.set_wakeup_fd`), and a thread of our
    own, ``slamlens-stop``, blocked reading it, sets the event at once. No signal mask is
    changed (threads and child processes, such as a launch's services, inherit none), and
    nothing else in a slamlens process may set the wakeup fd.

    The first signal sets the event and arms a watchdog: a service whose clean shutdown
    (joining its threads, closing its Zenoh session) has not ended ``grace_s`` later — on an
    oversubscribed machine it can take seconds — says so in one line and exits with status
    0 at once, so it never outlives its 2 s. ``grace_s=None`` (the recorder, which must
    finish its file) waits for the clean end however long it takes. Later signals change
    nothing. Called again, the signals set the new event instead; called outside the main
    thread (where signals cannot be set up), the event is only a plain event.
    """
    global _taker
    event = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        return event
    if _taker is None:
        _taker = _StopTaker()  # wakeup fd and taker before the handlers: no signal lost
    _taker.serve(event, grace_s)
    for number in STOP_SIGNALS:
        signal.signal(number, _recorded_only)
    return event


def _end_now(code: int) -> NoReturn:
    """End the process with ``code`` as Python's exit begins — threading's exit functions
    (sessions left open closed, :mod:`slamlens.common.zenoh_bus`) and the join of non-daemon
    threads, the atexit functions (logging's flush among them), the standard streams
    flushed — without the interpreter's finalization after it."""
    try:
        shutdown = getattr(threading, "_shutdown", None)
        if shutdown is not None:
            shutdown()
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)


def run_cli(fn: Callable[[], int | None]) -> int:
    """Run a service's main: known errors become one line on stderr and exit code 1.

    After a stop signal, once the command has returned (its final line said, its session
    closed, its files finished), the process ends here: the atexit functions run and the
    standard streams are flushed, then :func:`os._exit`. Python's own finalization after
    that (tearing down modules and native libraries' objects; the viewer's took 0.4–1.7 s
    on a loaded machine) is beyond the reach of the shutdown watchdog, which cannot run
    during it, and while it runs a second signal would find the default handlers back and
    end the process by that signal instead of with status 0.
    """
    try:
        code = int(fn() or 0)
    except SlamlensError as exc:
        print(f"slamlens: error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        code = 0
    if _taker is not None and _taker.stopping() \
            and threading.current_thread() is threading.main_thread():
        _end_now(code)
    return code
