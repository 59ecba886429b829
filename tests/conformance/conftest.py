"""Fixtures of the conformance suite: two CPU burners beside every case, and a router.

The suite speaks only docs/protocol.md: it imports no project code (a test holds every
file here to that), starts the services as a user does and talks to them with zenoh,
msgpack and numpy.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest
from kit_procs import LAUNCHED, Burners, Proc, endpoint, free_port, start


@pytest.fixture(autouse=True)
def cpu_burners() -> Iterator[None]:
    """Two processes burning a CPU each for the whole case: the 2-core machine loaded."""
    burners = Burners(2)
    try:
        yield
    finally:
        burners.stop()


#: set on a case whose call failed
FAILED = pytest.StashKey[bool]()


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Iterator[pytest.TestReport]:
    report = yield
    if report.when == "call" and report.failed:
        item.stash[FAILED] = True
    return report


@pytest.fixture(autouse=True)
def no_leftovers(request: pytest.FixtureRequest) -> Iterator[None]:
    """Whatever a case started and did not stop (it failed half-way) is killed after it;
    if the case failed, what its processes said is printed (shown with the failure)."""
    first = len(LAUNCHED)
    yield
    for proc in LAUNCHED[first:]:
        if proc.alive():
            proc.stop(signal.SIGKILL)
    if request.node.stash.get(FAILED, False):
        for proc in LAUNCHED[first:]:
            print(f"=== {' '.join(proc.argv[1:])}\n{proc.tail(40)}")


@pytest.fixture(scope="module")
def router() -> Iterator[int]:
    """``slamlens router`` on a free loopback port (its port); one per test file."""
    port = free_port()
    proc: Proc = start("router", "--listen", endpoint(port), ready="router ready")
    try:
        yield port
    finally:
        proc.stop(signal.SIGTERM)
