"""Inputs applied exactly once, in publication order (docs/protocol.md, "Inputs")."""

from __future__ import annotations

import numpy as np

from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam.input_order import Input, InputOrder, Missed, sorted_for_replay


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def odo(seq: int | None, *, source: str | None = "s1", time: int | None = None,
        stamp: float | None = None) -> Input:
    msg = Odometry(robot="r", stamp=float(stamp if stamp is not None else seq or time or 0),
                   dt=0.1, v=0.1, w=0.0, input_seq=seq)
    return Input("odometry", msg, source=source, time=time if time is not None else seq)


def obs(seq: int | None, *, source: str | None = "s1", time: int | None = None,
        stamp: float | None = None) -> Input:
    msg = Observations(robot="r", stamp=float(stamp if stamp is not None else seq or time or 0),
                       ids=np.array([1]), ranges=np.array([1.0]), bearings=np.array([0.0]),
                       input_seq=seq)
    return Input("observations", msg, source=source, time=time if time is not None else seq)


def seqs(items: list[Input]) -> list[int | None]:
    return [i.seq for i in items]


def times(items: list[Input]) -> list[int | None]:
    return [i.time for i in items]


# -- numbered inputs -----------------------------------------------------------------------

def test_in_order_inputs_are_released_at_once() -> None:
    order = InputOrder()
    assert [seqs(order.offer(x)) for x in (odo(1), obs(2), odo(3))] == [[1], [2], [3]]
    assert order.held == 0 and order.stats.released == 3
    assert order.next_deadline() is None  # nothing waits on a clock


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


def test_zenohs_miss_report_gives_up_exactly_the_missing_numbers_without_a_clock() -> None:
    clock = Clock()
    order = InputOrder(gap_wait_s=1e9, clock=clock)
    order.offer(odo(1))
    assert order.offer(obs(3)) == [] and order.offer(obs(5)) == []  # 2 and 4 lost (odometry)
    assert seqs(order.missed(Missed("s1", 1))) == [3]  # one miss: the first gap only
    assert order.held == 1
    assert seqs(order.missed(Missed("s1", 1))) == [5]
    assert order.stats.lost == 2 and order.held == 0
    assert order.offer(odo(2)) == [] and order.stats.late == 1  # came after all: not applied


def test_a_miss_reported_before_the_gap_is_seen_waits_for_it() -> None:
    order = InputOrder()
    order.offer(odo(1))
    assert order.missed(Missed("s1", 1)) == []  # odometry 2 is gone; nothing held yet
    assert seqs(order.offer(obs(3))) == [3]  # the gap shows, the report fills it at once
    assert order.stats.lost == 1


def test_a_gap_nobody_reports_is_given_up_after_the_wait() -> None:
    clock = Clock()
    order = InputOrder(gap_wait_s=2.0, clock=clock)
    order.offer(odo(1))
    assert order.offer(odo(5)) == []
    clock.t = 1.0
    assert order.expire() == [] and order.next_deadline() == 2.0
    clock.t = 2.5
    assert seqs(order.expire()) == [5]
    assert order.stats.lost == 3 and order.held == 0
    assert seqs(order.offer(odo(3))) == [] and order.stats.late == 1


def test_inputs_behind_many_gaps_wait_once_not_once_per_gap() -> None:
    clock = Clock()
    order = InputOrder(gap_wait_s=2.0, clock=clock)
    order.offer(odo(1))
    for seq in range(3, 21, 2):  # 2, 4, … (observations) never come
        assert order.offer(odo(seq)) == []
    clock.t = 2.0
    assert seqs(order.expire()) == list(range(3, 21, 2))
    assert order.stats.lost == 9 and order.held == 0 and order.next_deadline() is None


def test_a_checkpoint_position_makes_everything_before_it_a_duplicate() -> None:
    first = InputOrder()
    for x in (odo(1), obs(2), odo(3)):
        first.offer(x)
    resumed = InputOrder()
    resumed.resume(first.positions())
    replay = [odo(1), obs(2), odo(3), odo(4), obs(5)]  # the drivers' cache, from the start
    assert [s for x in replay for s in seqs(resumed.offer(x))] == [4, 5]
    assert resumed.stats.duplicates == 3 and resumed.stats.late == 0


def test_a_new_source_starts_where_it_is_first_heard() -> None:
    order = InputOrder()
    assert seqs(order.offer(odo(7, source="a"))) == [7]  # joined a driver already running
    assert order.stats.joined_late == 6 and order.stats.lost == 0
    assert seqs(order.offer(odo(8, source="a"))) == [8]


# -- unnumbered inputs ------------------------------------------------------------------------

def test_unnumbered_inputs_go_in_arrival_order_without_waiting() -> None:
    order = InputOrder()
    out = [times(order.offer(x)) for x in (odo(None, time=10), obs(None, time=11),
                                           odo(None, time=12))]
    assert out == [[10], [11], [12]] and order.next_deadline() is None


def test_an_unnumbered_input_older_than_one_applied_is_late_and_not_applied() -> None:
    order = InputOrder()
    order.offer(odo(None, time=10))
    order.offer(obs(None, time=12))
    assert order.offer(odo(None, time=11)) == []  # recovered after 12: its place has passed
    assert order.offer(obs(None, time=12)) == []  # a copy of one applied
    assert order.stats.late == 1 and order.stats.duplicates == 1


def test_unnumbered_replay_after_a_restart_is_known_as_applied() -> None:
    first = InputOrder()
    for t in (10, 11, 12):
        first.offer(odo(None, time=t))
    resumed = InputOrder()
    resumed.resume(first.positions())
    # a publisher's cache replays publisher by publisher; sorted, then offered
    cache = [obs(None, time=11), obs(None, time=14), odo(None, time=10), odo(None, time=12),
             odo(None, time=13)]
    out = [t for x in sorted_for_replay(cache) for t in times(resumed.offer(x))]
    assert out == [13, 14]
    assert resumed.stats.duplicates == 3 and resumed.stats.late == 0


def test_inputs_without_any_timestamp_go_in_arrival_order() -> None:
    order = InputOrder()
    assert len(order.offer(odo(None, source=None, time=None))) == 1
    assert len(order.offer(odo(None, source=None, time=None))) == 1  # nothing to tell apart


# -- several sources ---------------------------------------------------------------------------

def test_two_sources_are_merged_by_stamp_waiting_on_each_others_progress() -> None:
    order = InputOrder(sources=2)
    assert order.offer(odo(None, source="a", time=1, stamp=1.0)) == []  # b not heard yet
    assert times(order.offer(obs(None, source="b", time=5, stamp=0.5))) == [5]  # b's 0.5 first
    assert order.offer(odo(None, source="a", time=2, stamp=2.0)) == []  # b may send 0.7 still
    assert times(order.offer(obs(None, source="b", time=6, stamp=3.0))) == [1, 2]
    assert times(order.offer(odo(None, source="a", time=3, stamp=3.0))) == [3, 6]  # tie: odo
    assert order.offer(odo(None, source="a", time=4, stamp=4.0)) == []
    assert order.stats.waited == 0 and order.stats.late == 0 and order.held == 1


def test_a_quiet_source_holds_the_merge_at_most_the_bounded_wait() -> None:
    clock = Clock()
    order = InputOrder(sources=2, reorder_s=0.5, clock=clock)
    order.offer(odo(None, source="a", time=1, stamp=1.0))
    order.offer(obs(None, source="b", time=1, stamp=1.5))
    assert times(order.offer(odo(None, source="a", time=2, stamp=2.0))) == [1]
    clock.t = 0.4
    assert order.expire() == [] and order.next_deadline() == 0.5
    clock.t = 0.5
    assert times(order.expire()) == [2]  # b quiet for 0.5 s: a's 2.0 goes
    assert order.stats.waited == 1
    # b wakes up with something older than what went: too late for its place
    assert order.offer(obs(None, source="b", time=2, stamp=1.8)) == []
    assert order.stats.late == 1


def test_one_source_is_never_waited_for_even_when_two_are_expected_later() -> None:
    order = InputOrder(sources=1)
    assert len(order.offer(odo(None, source="a", time=1, stamp=5.0))) == 1
    assert order.next_deadline() is None
