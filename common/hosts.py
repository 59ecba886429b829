"""Host names and addresses: ``HOST[:PORT]`` split, and whether a host is this machine
only (the viewer's access rules, the bus's warning for a cache connected off its host)."""

from __future__ import annotations

import ipaddress
import socket


def split_host(value: str) -> tuple[str, int | None] | None:
    """``"Example.COM:8080"`` → ("example.com", 8080); ``"[::1]"`` → ("::1", None);
    None if it is not HOST[:PORT]."""
    value = value.strip().lower()
    if value.startswith("["):
        host, sep, rest = value[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            return None
        port = rest[1:]
    else:
        host, _, port = value.partition(":")
        if ":" in port:
            return None
    if not host or (port and not (port.isdigit() and 0 < int(port) < 65536)):
        return None
    return host.rstrip("."), int(port) if port else None


def is_loopback(host: str) -> bool:
    """True when ``host`` (an address or a name) is reachable from this machine only."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False  # unknown: treat as beyond loopback (the safe side)
    return bool(infos) and all(ipaddress.ip_address(str(i[4][0]).split("%")[0]).is_loopback
                               for i in infos)
