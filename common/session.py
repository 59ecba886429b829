"""Opening Zenoh sessions the slamlens way.

Precedence: the Zenoh config file (``--zenoh-config``, JSON5 as Zenoh reads it) first,
then ``--connect`` / ``--listen`` over it. Whenever endpoints are explicit, multicast
scouting is switched off, so nothing leaves the endpoints the user named.

With no file and no endpoints, a service connects as a client to the default router at
``tcp/127.0.0.1:7447`` (what ``slamlens router`` listens on), again with multicast
scouting off: slamlens never talks to the network unless told to. A client waits up to
10 s for its router to appear, so services may be started in any order.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from common.bus import ZenohBus
from common.errors import BusError, ConfigError

log = logging.getLogger(__name__)

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
ROUTER_WAIT_MS = 10_000  #: how long a client waits for its router before giving up


@dataclass(frozen=True)
class BusSettings:
    """Where a session connects and listens."""

    connect: tuple[str, ...] = ()  #: endpoints to connect to, e.g. tcp/127.0.0.1:7447
    listen: tuple[str, ...] = ()  #: endpoints to listen on
    zenoh_config: str | None = None  #: path of a Zenoh JSON5 config file
    mode: str | None = None  #: "client", "peer" or "router"; derived when None
    extra: dict[str, str] = field(default_factory=dict)  #: raw JSON5 inserts, key → value


def _check_endpoint(endpoint: str) -> str:
    proto, sep, rest = endpoint.partition("/")
    if not sep or proto not in {"tcp", "udp", "tls", "quic", "ws", "unixsock-stream"} or not rest:
        raise ConfigError(f"endpoint {endpoint!r} is not of the form tcp/HOST:PORT")
    return endpoint


def build_config(settings: BusSettings):  # -> zenoh.Config
    """The ``zenoh.Config`` for ``settings`` (see module docstring for the precedence)."""
    import zenoh

    if settings.zenoh_config:
        path = Path(settings.zenoh_config)
        if not path.is_file():
            raise ConfigError(f"Zenoh config file {path} does not exist")
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as exc:
            raise ConfigError(f"Zenoh config file {path} is invalid: {exc}") from None
    else:
        conf = zenoh.Config()

    connect = [_check_endpoint(e) for e in settings.connect]
    listen = [_check_endpoint(e) for e in settings.listen]
    explicit = bool(connect or listen)
    if not settings.zenoh_config and not explicit and settings.mode != "router":
        connect = [DEFAULT_ROUTER]
        explicit = True

    mode = settings.mode
    if mode is None and (explicit or not settings.zenoh_config):
        mode = "peer" if listen else "client"
    try:
        if mode is not None:
            conf.insert_json5("mode", json.dumps(mode))
        if connect or (explicit and not settings.zenoh_config):
            conf.insert_json5("connect/endpoints", json.dumps(connect))
        if listen or (explicit and not settings.zenoh_config):
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        if explicit:
            conf.insert_json5("scouting/multicast/enabled", "false")
        if mode == "client" and not settings.zenoh_config:
            # services may start before their router (the demo, a reboot): wait for it
            conf.insert_json5("connect/timeout_ms", f"{{client: {ROUTER_WAIT_MS}}}")
        # the advanced publishers of SPEC §7a need timestamps (off by default in client
        # mode); they also give the estimator its publication order (HLC per session)
        conf.insert_json5("timestamping/enabled", "true")
        for key, value in settings.extra.items():
            conf.insert_json5(key, value)
    except Exception as exc:
        raise ConfigError(f"bad Zenoh setting: {exc}") from None
    return conf


def open_bus(settings: BusSettings) -> ZenohBus:
    """Open a Zenoh session for ``settings`` and wrap it as a bus."""
    import zenoh

    conf = build_config(settings)
    try:
        session = zenoh.open(conf)
    except Exception as exc:
        where = ", ".join(settings.connect or settings.listen) or "the configured endpoints"
        raise BusError(f"cannot open a Zenoh session on {where}: {exc}") from None
    return ZenohBus(session)


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/HOST:PORT`` endpoint on a port that is free right now (tests, demo)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"


def router_settings(listen: Sequence[str], zenoh_config: str | None = None, *,
                    connect: Sequence[str] = ()) -> BusSettings:
    """Settings of an in-process router listening on ``listen`` and linked to the routers
    at ``connect`` (a robot's router connects to the workstation's: traffic between
    services on the robot never crosses the link)."""
    return BusSettings(listen=tuple(listen) or (DEFAULT_ROUTER,), connect=tuple(connect),
                       zenoh_config=zenoh_config, mode="router")
