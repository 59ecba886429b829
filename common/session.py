"""Opening Zenoh sessions the slamlens way.

Precedence: the Zenoh config file (``--zenoh-config``, JSON5 as Zenoh reads it) first,
then ``--connect`` / ``--listen`` over it. Whenever endpoints are explicit, multicast
scouting is switched off, so nothing leaves the endpoints the user named.

With no file and no endpoints, a service connects as a client to the default router at
``tcp/127.0.0.1:7447`` (what ``slamlens router`` listens on), again with multicast
scouting off: slamlens never talks to the network unless told to. A client waits up to
10 s for its router to appear, so services may be started in any order.

A router listens where ``--listen`` says, else where its Zenoh config file says, else on
``tcp/127.0.0.1:7447``: flags override only what they name.

``--secure DIR --name NAME`` (docs/security.md) makes every link mutual TLS with that identity and,
on a router, enforces the roles of every identity in DIR (:mod:`slamlens.common.security`); the
default endpoint is then ``tls/127.0.0.1:7447`` and a ``tcp/`` endpoint is an error.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slamlens.common.endpoints import check_endpoint, effective_endpoints, off_host
from slamlens.common.errors import BusError, ConfigError
from slamlens.common.keys import DEFAULT_PREFIX
from slamlens.common.zenoh_bus import ZenohBus

log = logging.getLogger(__name__)

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
DEFAULT_SECURE_ROUTER = "tls/127.0.0.1:7447"
ROUTER_WAIT_MS = 10_000  #: how long a client waits for its router before giving up


@dataclass(frozen=True)
class BusSettings:
    """Where a session connects and listens."""

    connect: tuple[str, ...] = ()  #: endpoints to connect to, e.g. tcp/127.0.0.1:7447
    listen: tuple[str, ...] = ()  #: endpoints to listen on
    zenoh_config: str | None = None  #: path of a Zenoh JSON5 config file
    mode: str | None = None  #: "client", "peer" or "router"; derived when None
    extra: dict[str, str] = field(default_factory=dict)  #: raw JSON5 inserts, key → value
    secure: str | None = None  #: directory of the certificate authority (docs/security.md)
    name: str | None = None  #: identity in ``secure`` (certificate common name)
    prefix: str = DEFAULT_PREFIX  #: key prefix the router's access control protects


def _sets_listen(conf: Any) -> bool:
    """Whether ``conf`` (a user's file) names listen endpoints rather than Zenoh's default."""
    import zenoh

    return conf.get_json("listen/endpoints") != zenoh.Config().get_json("listen/endpoints")


def build_config(settings: BusSettings):  # -> zenoh.Config
    """The ``zenoh.Config`` for ``settings`` (see module docstring for the precedence)."""
    import zenoh

    if bool(settings.secure) != bool(settings.name):
        raise ConfigError("--secure DIR and --name NAME go together")
    if settings.zenoh_config:
        path = Path(settings.zenoh_config)
        if not path.is_file():
            raise ConfigError(f"Zenoh config file {path} does not exist")
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as exc:
            raise ConfigError(f"Zenoh config file {path} is invalid: {zenoh_reason(exc)}") from None
    else:
        conf = zenoh.Config()

    default_router = DEFAULT_SECURE_ROUTER if settings.secure else DEFAULT_ROUTER
    connect = [check_endpoint(e) for e in settings.connect]
    listen = [check_endpoint(e) for e in settings.listen]
    explicit = bool(connect or listen)
    if settings.mode == "router" and not listen and not _sets_listen(conf):
        listen = [default_router]  # neither flag nor file says where: loopback only
        explicit = True
    if not settings.zenoh_config and not explicit and settings.mode != "router":
        connect = [default_router]
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
        # the advanced publishers of docs/delivery.md need timestamps (off by default in client
        # mode); they also give the estimator its publication order (HLC per session)
        conf.insert_json5("timestamping/enabled", "true")
        # on one host, large payloads (states of big maps) travel through shared memory;
        # to another host Zenoh sends their bytes as usual (docs/delivery.md)
        conf.insert_json5("transport/shared_memory/enabled", "true")
        for key, value in settings.extra.items():
            conf.insert_json5(key, value)
    except Exception as exc:
        raise ConfigError(f"bad Zenoh setting: {zenoh_reason(exc)}") from None
    if settings.secure and settings.name:
        from slamlens.common import security

        security.apply(conf, directory=settings.secure, name=settings.name,
                       prefix=settings.prefix, mode=mode or json.loads(conf.get_json("mode")))
    return conf


def listen_endpoints(settings: BusSettings) -> list[str]:
    """Where a session opened with ``settings`` listens (the flags', else the file's)."""
    conf = build_config(settings)
    return effective_endpoints(conf, "listen", json.loads(conf.get_json("mode")) or "peer")


_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def zenoh_reason(exc: BaseException) -> str:
    """A Zenoh error as one readable line: without the Rust source locations it carries."""
    text = _RUST_LOCATION.sub("", str(exc)).strip()
    return " ".join(text.split())


def open_bus(settings: BusSettings) -> ZenohBus:
    """Open a Zenoh session for ``settings`` and wrap it as a bus."""
    import zenoh

    conf = build_config(settings)
    mode = json.loads(conf.get_json("mode")) or "peer"
    try:
        session = zenoh.open(conf)
    except Exception as exc:
        where = ", ".join(effective_endpoints(conf, "connect", mode)
                          or effective_endpoints(conf, "listen", mode)) or "no endpoint"
        reason = zenoh_reason(exc)
        if "Unable to connect to any of" in reason:
            hint = (" (or it refused this identity's certificate: see the router's log)"
                    if settings.secure else "")
            raise BusError(f"no Zenoh router answered at {where}: is `slamlens router` "
                           f"running there?{hint}") from None
        raise BusError(f"cannot open a Zenoh session on {where}: {reason}") from None
    return ZenohBus(session, off_host=off_host(effective_endpoints(conf, "connect", mode)))


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/HOST:PORT`` endpoint on a port that is free right now (tests, demo)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"


def router_settings(listen: Sequence[str], zenoh_config: str | None = None, *,
                    connect: Sequence[str] = (), secure: str | None = None,
                    name: str | None = None, prefix: str = DEFAULT_PREFIX) -> BusSettings:
    """Settings of an in-process router listening on ``listen`` (else where the Zenoh
    config file says, else on loopback: see :func:`build_config`) and linked to the
    routers at ``connect`` (a robot's router connects to the workstation's: traffic
    between services on the robot never crosses the link)."""
    return BusSettings(listen=tuple(listen), connect=tuple(connect), zenoh_config=zenoh_config,
                       mode="router", secure=secure, name=name, prefix=prefix)
