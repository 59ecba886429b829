"""The reliability helpers of common/: the keep-newest slot and the reconnect back-off."""

from __future__ import annotations

import logging
import threading

import pytest

from slamlens.common.backoff import Backoff
from slamlens.common.latest import Latest


# -- Latest -------------------------------------------------------------------------------
def test_latest_keeps_the_newest_gives_it_once_and_counts_what_it_overwrote() -> None:
    wakes: list[int] = []
    slot: Latest[bytes] = Latest(on_put=lambda: wakes.append(1))
    assert slot.take() is None
    slot.put(b"a")
    slot.put(b"b")
    slot.put(b"")  # a falsy item is an item
    assert slot.take() == b""
    assert slot.take() is None  # taken already
    assert (slot.dropped, slot.count, len(wakes)) == (2, 3, 3)
    slot.put(b"c")
    assert slot.take(timeout=5.0) == b"c"  # there is one: no waiting
    assert slot.dropped == 2  # an item taken in time is not a drop


def test_latest_take_wakes_on_put_and_times_out_without_one() -> None:
    slot: Latest[int] = Latest()
    assert slot.take(timeout=0.01) is None
    waiting = threading.Event()
    got: list[int | None] = []

    def consumer() -> None:
        waiting.set()
        got.append(slot.take(timeout=30.0))

    thread = threading.Thread(target=consumer)
    thread.start()
    waiting.wait(5.0)
    slot.put(7)
    thread.join(10.0)
    assert not thread.is_alive() and got == [7]


def test_latest_close_wakes_a_waiter_and_stores_nothing_more() -> None:
    slot: Latest[int] = Latest()
    slot.put(1)
    got: list[int | None] = []
    waiting = threading.Event()

    def consumer() -> None:
        got.append(slot.take())
        waiting.set()
        got.append(slot.take(timeout=None))  # blocks until close

    thread = threading.Thread(target=consumer)
    thread.start()
    waiting.wait(5.0)
    slot.close()
    thread.join(10.0)
    assert not thread.is_alive() and got == [1, None]
    slot.put(2)
    assert slot.take(timeout=None) is None and slot.count == 1


def test_latest_under_concurrent_producers_loses_nothing_but_overwrites() -> None:
    slot: Latest[int] = Latest()
    taken: list[int] = []
    done = threading.Event()

    def consumer() -> None:
        while not done.is_set():
            item = slot.take(timeout=0.01)
            if item is not None:
                taken.append(item)

    def producer(base: int) -> None:
        for k in range(2000):
            slot.put(base + k)

    reader = threading.Thread(target=consumer)
    reader.start()
    writers = [threading.Thread(target=producer, args=(b * 10_000,)) for b in range(3)]
    for w in writers:
        w.start()
    for w in writers:
        w.join()
    done.set()
    reader.join()
    leftover = slot.take()
    received = len(taken) + (leftover is not None)
    assert slot.count == 6000 and received + slot.dropped == 6000
    assert len(set(taken)) == len(taken)  # each item handed out once


# -- Backoff ------------------------------------------------------------------------------
class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_backoff_doubles_to_its_cap_and_starts_over_after_a_success(
        caplog: pytest.LogCaptureFixture) -> None:
    clock = FakeClock()
    log = logging.getLogger("test.backoff")
    backoff = Backoff("camera x", logger=log, initial_s=0.5, max_s=3.0, clock=clock)
    assert backoff.wait_s() == 0.0  # the first attempt is due at once
    with caplog.at_level(logging.DEBUG, logger="test.backoff"):
        waits = []
        for _ in range(5):
            waits.append(backoff.failed("unplugged"))
            assert backoff.wait_s() == waits[-1]
            clock.now += 0.25
            assert backoff.wait_s() == pytest.approx(waits[-1] - 0.25)
            clock.now += waits[-1]
        assert waits == [0.5, 1.0, 2.0, 3.0, 3.0]
        backoff.succeeded()
        assert backoff.failed("unplugged again") == 0.5  # a success starts it over
        backoff.succeeded()
    levels = [(r.levelno, r.getMessage()) for r in caplog.records]
    warnings = [m for lv, m in levels if lv == logging.WARNING]
    infos = [m for lv, m in levels if lv == logging.INFO]
    assert warnings == ["camera x lost: unplugged; retrying with back-off up to 3.0 s",
                        "camera x lost: unplugged again; retrying with back-off up to 3.0 s"]
    assert infos == ["camera x is back after 5 failed attempts",
                     "camera x is back after 6 failed attempts"]
    assert sum(lv == logging.DEBUG for lv, _ in levels) == 4  # the retries of outage one
    assert (backoff.failures, backoff.outages, backoff.recoveries) == (6, 2, 2)
    assert not backoff.in_outage


def test_drop_counter_says_a_flood_in_a_few_lines() -> None:
    import logging

    from slamlens.common.drops import DropCounter

    lines: list[str] = []

    class Capture(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())

    logger = logging.getLogger("test.drops")
    logger.addHandler(Capture())
    logger.propagate = False
    now = [0.0]
    drops = DropCounter(logger, burst=3, interval_s=10.0, clock=lambda: now[0])
    for i in range(150_000):
        now[0] = i * 1e-4  # 150 000 drops in 15 s
        drops.drop("CameraControl", f"bad {i}")
    assert drops.counts["CameraControl"] == 150_000
    assert len(lines) == 3 + 1  # the burst, then one line once 10 s have passed
    assert "more in 10 s" in lines[-1] and "(100003 so far)" in lines[-1]
