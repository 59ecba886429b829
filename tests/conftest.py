"""Shared fixtures: a real Zenoh router on a free loopback port, and clients of it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus, router_settings
from slamlens.common.zenoh_bus import ZenohBus
from slamlens.services.harness.netns import available, make_hosts

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """An in-process Zenoh router listening on a free 127.0.0.1 port."""
    endpoint = free_tcp_endpoint()
    router = open_bus(router_settings([endpoint]))
    try:
        yield endpoint
    finally:
        router.close()


@pytest.fixture
def make_client(router_endpoint: str) -> Iterator:
    """Factory of client buses connected to the router; all closed at teardown."""
    buses: list[ZenohBus] = []

    def make() -> ZenohBus:
        bus = open_bus(BusSettings(connect=(router_endpoint,)))
        buses.append(bus)
        return bus

    yield make
    for bus in buses:
        bus.close()


@pytest.fixture
def two_hosts():
    why = available()
    if why is not None:
        pytest.skip(f"two-host tests need network namespaces: {why}")
    hosts = make_hosts()
    try:
        yield hosts
    finally:
        hosts.remove()
