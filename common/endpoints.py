"""Zenoh endpoints: checking one, and reading those a Zenoh configuration uses."""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from slamlens.common.errors import ConfigError
from slamlens.common.hosts import is_loopback, split_host


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it is a Zenoh endpoint (``PROTO/ADDRESS``), else ConfigError."""
    proto, sep, rest = endpoint.partition("/")
    if not sep or proto not in {"tcp", "udp", "tls", "quic", "ws", "unixsock-stream"} or not rest:
        raise ConfigError(f"endpoint {endpoint!r} is not of the form tcp/HOST:PORT")
    return endpoint


def effective_endpoints(conf: Any, section: str, mode: str | None) -> list[str]:
    """The ``connect``/``listen`` endpoints ``conf`` would use in ``mode`` (Zenoh allows a
    list or a map from mode to list)."""
    raw = json.loads(conf.get_json(f"{section}/endpoints") or "[]")
    if isinstance(raw, dict):
        raw = raw.get(mode or "peer", [])
    return [str(e) for e in raw or []]


def off_host(endpoints: Iterable[str]) -> list[str]:
    """The endpoints among ``endpoints`` that lead off this host: neither a Unix socket nor
    a host that is this machine only (:func:`slamlens.common.hosts.is_loopback`)."""
    out = []
    for endpoint in endpoints:
        proto, _, rest = endpoint.partition("/")
        if proto.startswith("unixsock"):
            continue
        parsed = split_host(rest.split("#", 1)[0].split("?", 1)[0])
        if parsed is None or not is_loopback(parsed[0]):
            out.append(endpoint)
    return out
