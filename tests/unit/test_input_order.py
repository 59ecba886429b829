"""Publication order, exactly once, across the two input keys (SPEC §7a)."""

from __future__ import annotations

import numpy as np

from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam.input_order import Input, InputOrder


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def odo(seq: int | None, *, source: str | None = "s1", time: int | None = None) -> Input:
    msg = Odometry(robot="r", stamp=float(seq or 0), dt=0.1, v=0.1, w=0.0, input_seq=seq)
    return Input("odometry", msg, source=source, time=time if time is not None else seq)


def obs(seq: int, *, source: str = "s1") -> Input:
    msg = Observations(robot="r", stamp=float(seq), ids=np.array([1]), ranges=np.array([1.0]),
                       bearings=np.array([0.0]), input_seq=seq)
    return Input("observations", msg, source=source, time=seq)


def seqs(items: list[Input]) -> list[int | None]:
    return [i.seq for i in items]


def test_in_order_inputs_are_released_at_once() -> None:
    order = InputOrder()
    assert [seqs(order.offer(x)) for x in (odo(1), obs(2), odo(3))] == [[1], [2], [3]]
    assert order.held == 0 and order.stats.released == 3


def test_a_later_input_waits_for_the_recovered_one_and_both_go_in_order() -> None:
    order = InputOrder()
    order.offer(odo(1))
    assert order.offer(obs(3)) == []  # 2 (odometry) is still being recovered
    assert order.offer(odo(4)) == []
    assert seqs(order.offer(odo(2))) == [2, 3, 4]
    assert order.stats.reordered == 2 and order.stats.lost == 0


def test_duplicates_are_discarded_exactly_once_semantics() -> None:
    order = InputOrder()
    for x in (odo(1), obs(2)):
        order.offer(x)
    assert order.offer(odo(1)) == [] and order.offer(obs(2)) == []
    order.offer(odo(4))
    assert order.offer(odo(4)) == []  # held twice is still one
    assert order.stats.duplicates == 3


def test_a_gap_that_never_fills_is_counted_lost_after_the_wait() -> None:
    clock = Clock()
    order = InputOrder(gap_wait_s=2.0, clock=clock)
    order.offer(odo(1))
    assert order.offer(odo(5)) == []
    clock.t = 1.0
    assert order.expire() == [] and order.next_deadline() == 2.0
    clock.t = 2.5
    assert seqs(order.expire()) == [5]
    assert order.stats.lost == 3 and order.held == 0
    assert seqs(order.offer(odo(3))) == []  # too late: already given up on


def test_inputs_behind_many_gaps_wait_once_not_once_per_gap() -> None:
    """A recovery that brought every odometry but no observation: the odometry behind the
    alternating gaps is released after one wait, not one wait per missing batch."""
    clock = Clock()
    order = InputOrder(gap_wait_s=2.0, clock=clock)
    order.offer(odo(1))
    for seq in range(3, 21, 2):  # 2, 4, … (observations) never come
        assert order.offer(odo(seq)) == []
    clock.t = 1.9
    assert order.expire() == []
    clock.t = 2.0
    assert seqs(order.expire()) == list(range(3, 21, 2))
    assert order.stats.lost == 9 and order.held == 0 and order.next_deadline() is None


def test_a_later_gap_keeps_the_clock_of_the_input_behind_it() -> None:
    clock = Clock()
    order = InputOrder(gap_wait_s=2.0, clock=clock)
    order.offer(odo(1))
    order.offer(odo(3))  # held at t = 0
    clock.t = 1.5
    order.offer(odo(5))  # held at t = 1.5
    assert seqs(order.offer(odo(2))) == [2, 3]  # the first gap filled in time
    assert order.next_deadline() == 3.5  # 5 has waited since 1.5, not since now
    clock.t = 3.5
    assert seqs(order.expire()) == [5] and order.stats.lost == 1


def test_a_checkpoint_position_makes_everything_before_it_a_duplicate() -> None:
    first = InputOrder()
    for x in (odo(1), obs(2), odo(3)):
        first.offer(x)
    resumed = InputOrder()
    resumed.resume(first.positions())
    replay = [odo(1), obs(2), odo(3), odo(4), obs(5)]  # the drivers' cache, from the start
    assert [s for x in replay for s in seqs(resumed.offer(x))] == [4, 5]
    assert resumed.stats.duplicates == 3


def test_sources_are_numbered_independently_and_a_late_join_waits_once() -> None:
    clock = Clock()
    order = InputOrder(gap_wait_s=2.0, clock=clock)
    assert order.offer(odo(7, source="a")) == []  # 1…6 may still be on their way
    assert seqs(order.offer(odo(1, source="b"))) == [1]  # a second driver session
    assert order.offer(odo(8, source="a")) == []
    clock.t = 2.0  # joined a driver already running: 1…6 were never ours to see
    assert seqs(order.expire()) == [7, 8]
    assert order.stats.joined_late == 6 and order.stats.lost == 0
    assert seqs(order.offer(odo(9, source="a"))) == [9]


def test_unnumbered_inputs_go_in_zenoh_time_order_across_keys() -> None:
    clock = Clock()
    order = InputOrder(reorder_s=0.02, clock=clock)
    # observations stamped 11 arrive before odometry stamped 10 (a reorder between keys)
    assert order.offer(obs_unnumbered(11)) == []  # odometry 10 may still come
    assert [i.time for i in order.offer(odo(None, time=10))] == [10]  # obs 11 > 10: it goes
    clock.t = 0.03
    assert [i.time for i in order.expire()] == [11]  # no odometry > 11 came: the window
    clock.t = 0.0
    order = InputOrder(reorder_s=0.02, clock=clock)
    order.offer(obs_unnumbered(11))
    # each input goes once the other key has shown a later stamp: never out of time order
    assert [i.time for i in order.offer(odo(None, time=12))] == [11]
    assert [i.time for i in order.offer(obs_unnumbered(13))] == [12]
    assert [i.time for i in order.offer(odo(None, time=14))] == [13]  # 14 still waiting
    clock.t = 0.03
    assert [i.time for i in order.expire()] == [14]  # nothing on the other key: the window
    assert order.stats.duplicates == 0 and order.stats.late == 0


def test_unnumbered_duplicates_are_told_by_their_exact_timestamp() -> None:
    clock = Clock()
    order = InputOrder(reorder_s=0.02, clock=clock)
    order.offer(odo(None, time=10))
    assert order.offer(odo(None, time=10)) == []
    clock.t = 0.05
    assert len(order.expire()) == 1
    assert order.offer(odo(None, time=10)) == []  # a recovered copy, after release
    assert order.stats.duplicates == 2 and order.stats.released == 1
    # without any timestamp nothing can be told apart: everything goes, in arrival order
    assert len(order.offer(odo(None, source=None, time=None))) == 1


def obs_unnumbered(t: int) -> Input:
    msg = Observations(robot="r", stamp=float(t), ids=np.array([1]), ranges=np.array([1.0]),
                       bearings=np.array([0.0]))
    return Input("observations", msg, source="s1", time=t)
