"""Shared fixtures: a real Zenoh router on a free loopback port, and clients of it."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from common.bus import ZenohBus
from common.session import BusSettings, free_tcp_endpoint, open_bus, router_settings

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


def slamlens_cmd(*args: str) -> list[str]:
    """Command line running the slamlens CLI with this interpreter (no PATH needed)."""
    return [sys.executable, "-m", "services", *args]


def spawn(*args: str, **kw) -> subprocess.Popen:
    """Start a slamlens service as a real process (stdout/stderr piped)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(slamlens_cmd(*args), cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> tuple[str, str]:
    """SIGTERM a service and collect its output; fail loudly if it will not exit."""
    if proc.poll() is None:
        proc.terminate()
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"{proc.args} did not exit on SIGTERM; stderr:\n{err}") from None
    return out, err
