"""Which connect endpoints leave the host (common.endpoints.off_host): the warning of a
cache on a session connected straight off its host (docs/delivery.md)."""

from __future__ import annotations

import pytest

from slamlens.common.endpoints import off_host


@pytest.mark.parametrize("endpoint", [
    "tcp/127.0.0.1:7447", "tcp/127.8.9.10:7447", "tls/localhost:7447", "tcp/[::1]:7447",
    "udp/127.0.0.1:7447#iface=lo", "unixsock-stream//tmp/zenoh.sock",
])
def test_loopback_and_unix_sockets_stay_on_the_host(endpoint: str) -> None:
    assert off_host([endpoint]) == []


@pytest.mark.parametrize("endpoint", [
    "tcp/10.200.1.2:7447", "tls/192.168.1.20:7447", "tcp/[fe80::1]:7447",
    "quic/workstation.lab:7447", "tcp/10.0.0.2:7447?prio=1-7",
])
def test_any_other_address_or_name_leaves_it(endpoint: str) -> None:
    assert off_host([endpoint]) == [endpoint]


def test_only_those_that_leave_are_named_in_their_order() -> None:
    given = ["tcp/10.0.0.3:7447", "tcp/127.0.0.1:7447", "tls/10.0.0.2:7447"]
    assert off_host(given) == ["tcp/10.0.0.3:7447", "tls/10.0.0.2:7447"]
