"""Every running service announces itself and says how it is doing (``slamlens status``).

The status protocol (docs/protocol.md):

* **Key.** ``PREFIX/status/{name}/{service}/{instance}``: ``name`` is the service's identity
  (the certificate's common name with ``--secure``, else the name of its role:
  ``robot-R``, ``monitor-R``, ``camera-C``, ``viewer-HOST``, ``router-HOST``),
  ``service`` the command it runs (``estimator``, ``sim`` …) and ``instance`` a random
  token of this process (one identity may run several processes).
* **Presence.** The process holds a Zenoh liveliness token on that key while it runs, so
  ``slamlens status`` finds every live service on every host linked to its router with a
  liveliness query (or subscriber) on ``PREFIX/status/**``, and sees one vanish when its
  process dies.
* **Answer.** A queryable on the same key answers a ``get`` with a
  :class:`~slamlens.common.messages.ServiceStatus`: robot, camera, state, epoch, counts and rates,
  drops, version. A worker thread rebuilds it once a second from the service's own
  counters (its *provider*); the Zenoh callback only hands over those bytes, never waits.
* **Access control.** Every identity may declare the queryable, reply and hold the token
  under ``PREFIX/status/{its own name}/**`` and nothing else there
  (:func:`slamlens.common.security.access_control`); reading it is everyone's ``read`` rule.

A service's ``cli.py`` registers its provider with :func:`announce`; the service modules
themselves need not know.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import logging
import os
import secrets
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from slamlens.common.bus import Bus
from slamlens.common.cli import bus_flags
from slamlens.common.keys import Keys
from slamlens.common.messages import ServiceStatus

log = logging.getLogger("slamlens.status")

#: how often a service rebuilds its status (and how fresh ``slamlens status`` is)
PERIOD_S = 1.0
#: rates are taken over about this long
RATE_WINDOW_S = 5.0


@dataclass(frozen=True)
class Report:
    """What a service's provider says now: plain numbers it already keeps."""

    state: str = "running"  #: a few words: running, waiting for an estimator, ok, fault …
    counts: Mapping[str, float] = field(default_factory=dict)  #: totals, main output first
    dropped: int = 0  #: messages discarded (malformed, foreign, refused)
    lost: int = 0  #: samples known missed for good
    epoch: int | None = None  #: the map epoch it is on
    rates: Mapping[str, float] = field(default_factory=dict)  #: rates it measures itself
    #: the counts whose rate per second is worth saying (None: the first count)
    rated: tuple[str, ...] | None = None


Provider = Callable[[], Report]


def version() -> str:
    """The installed slamlens version ("unknown" when run from a bare checkout)."""
    try:
        return importlib.metadata.version("slamlens")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _host() -> str:
    host = socket.gethostname().split(".")[0] or "host"
    return "".join(c if c.isalnum() or c == "-" else "-" for c in host)


def role_name(service: str, *, robot: str | None = None, camera: str | None = None) -> str:
    """The identity a service would hold for its role (docs/security.md names), used as its name
    when it runs without ``--secure``."""
    first_robot = (robot or "").split(",")[0]
    first_camera = (camera or "").split(",")[0]
    if service in ("sim", "replay", "serial", "estimator", "summary") and first_robot:
        return f"robot-{first_robot}"
    if service == "monitor" and first_robot:
        return f"monitor-{first_robot}"
    if service == "registration" and first_camera:
        return f"camera-{first_camera}"
    if service == "router":
        return f"router-{_host()}"
    return f"viewer-{_host()}"


class StatusAnnouncer:
    """Holds a service's status token and answers its status queries (module docstring)."""

    def __init__(self, bus: Bus, keys: Keys, *, service: str, name: str, provider: Provider,
                 robot: str | None = None, camera: str | None = None,
                 period_s: float = PERIOD_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.service, self.name = service, name
        self._bus = bus  # the token and the queryable live as long as its session
        self.robot, self.camera = robot or None, camera or None
        self.key = keys.status(name, service, secrets.token_hex(4))
        self._provider = provider
        self._period_s = period_s
        self._clock = clock
        self._started_wall = time.time()
        self._started = clock()
        self._host = socket.gethostname()
        self._version = version()
        self._history: deque[tuple[float, Mapping[str, float]]] = deque()
        self._lock = threading.Lock()
        self._failed = False
        self._stop = threading.Event()
        self._bytes = self._build().to_bytes()
        bus.serve_latest(self.key, self.latest_bytes)  # answerable before it is seen alive
        bus.declare_alive(self.key)
        self._thread = threading.Thread(target=self._loop, name=f"status {service}",
                                        daemon=True)
        self._thread.start()

    def latest_bytes(self) -> bytes:
        with self._lock:
            return self._bytes

    def snapshot(self) -> ServiceStatus:
        """The status as it would be answered now (built afresh)."""
        return self._build()

    def _report(self) -> Report:
        try:
            report = self._provider()
            self._failed = False
            return report
        except Exception as exc:  # a provider bug must not take the service down
            if not self._failed:
                log.warning("status of %s could not be read: %s", self.service, exc)
            self._failed = True
            return Report(state="status unavailable")

    def _build(self) -> ServiceStatus:
        report = self._report()
        now = self._clock()
        counts = {str(k): float(v) for k, v in report.counts.items()}
        with self._lock:
            self._history.append((now, counts))
            while len(self._history) > 2 and now - self._history[1][0] >= RATE_WINDOW_S:
                self._history.popleft()
            then, old = self._history[0]
        span = now - then
        rated = report.rated if report.rated is not None else tuple(counts)[:1]
        rates = {str(k): float(v) for k, v in report.rates.items()}
        for k in rated:
            if k in counts and k not in rates:
                rates[k] = (counts[k] - old.get(k, 0.0)) / span if span > 0.5 else 0.0
        return ServiceStatus(
            service=self.service, name=self.name, host=self._host, pid=os.getpid(),
            version=self._version, started=self._started_wall, uptime_s=now - self._started,
            state=report.state or "running", robot=self.robot, camera=self.camera,
            epoch=report.epoch, counts=counts, rates=rates, dropped=int(report.dropped),
            lost=int(report.lost))

    def _loop(self) -> None:
        while not self._stop.wait(self._period_s):
            payload = self._build().to_bytes()
            with self._lock:
                self._bytes = payload

    def close(self) -> None:
        self._stop.set()


def announce(bus: Bus, args: argparse.Namespace, service: str, provider: Provider, *,
             robot: str | None = None, camera: str | None = None) -> StatusAnnouncer:
    """Announce the service a command runs (its identity from ``--name``, else its role)."""
    flags = bus_flags(args)
    name = flags.name or role_name(service, robot=robot, camera=camera)
    return StatusAnnouncer(bus, Keys(flags.prefix), service=service, name=name,
                           provider=provider, robot=robot, camera=camera)


def counts_of(values: Mapping[str, Any], *names: str) -> dict[str, float]:
    """The numeric entries ``names`` of a service's summary, in that order."""
    return {n: float(values[n]) for n in names if isinstance(values.get(n), (int, float))}
