"""``slamlens.common.pacer.Pacer.drain``: a driver at its end waits for the estimator while it makes
progress (its cache holds the inputs the estimator may still recover), and gives up only when
it applied nothing for ``timeout_s``.

The estimator is an answer on ``state?header`` (InProcessBus) whose ``input_stamp`` moves on
by one input per query while it is "slow", and not at all when it is stuck.
"""

from __future__ import annotations

import threading
import time

import msgpack

from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.pacer import Pacer

KEYS = Keys("t")


class SlowEstimator:
    """Applies one input per query (the pacer polls every ``poll_s``) until ``stuck_at``."""

    def __init__(self, bus: InProcessBus, *, stuck_at: float = float("inf")) -> None:
        self.input_stamp = 0.0
        self.stuck_at = stuck_at
        bus.answer(KEYS.state("r1"), self._header)

    def _header(self, key: str, payload: bytes | None, parameters: str) -> bytes:
        if self.input_stamp < self.stuck_at:
            self.input_stamp += 1.0
        return msgpack.packb({"schema": 1, "epoch": 1, "input_stamp": self.input_stamp,
                              "stamp": self.input_stamp})


def _pacer(bus: InProcessBus, inputs: int, poll_s: float) -> Pacer:
    pacer = Pacer(bus, keys=KEYS, robot="r1", window=10_000, poll_s=poll_s)
    stop = threading.Event()
    for stamp in range(1, inputs + 1):
        pacer.before(float(stamp), stop)
    return pacer


def test_drain_waits_longer_than_its_timeout_while_the_estimator_makes_progress() -> None:
    bus = InProcessBus()
    estimator = SlowEstimator(bus)
    pacer = _pacer(bus, inputs=40, poll_s=0.02)  # ≥ 0.8 s to apply them all
    started = time.monotonic()
    assert pacer.drain(threading.Event(), timeout_s=0.1)
    assert time.monotonic() - started >= 0.1 * 4  # well beyond one timeout
    assert estimator.input_stamp == 40.0


def test_drain_gives_up_when_the_estimator_applies_nothing_for_its_timeout() -> None:
    bus = InProcessBus()
    SlowEstimator(bus, stuck_at=5.0)
    pacer = _pacer(bus, inputs=40, poll_s=0.005)
    started = time.monotonic()
    assert not pacer.drain(threading.Event(), timeout_s=0.3)
    took = time.monotonic() - started
    assert took >= 0.3  # it waited one whole timeout without progress before giving up


def test_drain_ends_at_once_on_stop() -> None:
    bus = InProcessBus()
    SlowEstimator(bus, stuck_at=0.0)
    pacer = _pacer(bus, inputs=3, poll_s=0.005)
    stop = threading.Event()
    stop.set()
    assert not pacer.drain(stop, timeout_s=60.0)
