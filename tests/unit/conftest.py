"""The unit tests' shared fixture: the monitor's correct dense-EKF run."""

from __future__ import annotations

import pytest

from slamlens.common.messages import SlamState, Truth
from tests.unit.monitor_runs import run


@pytest.fixture(scope="module")
def correct_run() -> tuple[list[SlamState], list[Truth]]:
    """A correct run of the dense textbook EKF (tests/unit/monitor_runs.py), seed 1."""
    return run(seed=1)
