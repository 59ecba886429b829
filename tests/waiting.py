"""Waiting on an event a test can only observe by looking: poll until it holds.

The timeout is a bound on a failure, never a pacing: a loaded machine only makes the wait
longer. The predicate is asked once more after the deadline, so a wait never fails on an
event that came while it slept.
"""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(predicate: Callable[[], object], timeout: float = 30.0, *,
               what: str = "condition") -> None:
    """Until ``predicate()`` is true; fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    assert predicate(), f"{what} not met in {timeout:g} s"
