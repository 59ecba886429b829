"""The estimator's inputs, each applied exactly once, in the order they were published.

Odometry and observations travel on two keys. The estimator subscribes to both with one
subscriber (one key expression, :meth:`slamlens.common.keys.Keys.inputs`), so Zenoh hands
over one publishing session's inputs in the order that session published them: a session's
publications travel in order on reliable links, and one subscriber's callbacks run one at a
time. Nothing here waits for that order to appear; it only has to mend what Zenoh's
recovery and a restart can do to it (docs/protocol.md, "Inputs: order and delivery").

A *source* is one publishing session, told apart by the id of the sample's Zenoh
timestamp. Within a source:

* **Numbered inputs** (``input_seq``: one counter over both keys, from 1) are released in
  that order, each number once. A number beyond the next one is held until the missing ones
  arrive (recovered from the publisher's cache), or Zenoh reports them missed for good
  (:class:`Missed`, the advanced subscriber's sample-miss detection), or — the last resort,
  for a publisher without a cache — ``gap_wait_s`` after the first input behind the gap
  arrived; the numbers given up are counted ``lost``, and one that still arrives later is
  counted ``late`` and not applied. A new source starts at the first number it sends (the
  numbers before it are ``joined_late``).
* **Unnumbered inputs** are released as they arrive. One with the timestamp of an input
  already applied is a duplicate; one older than the newest applied of its source can only
  be a sample Zenoh recovered after a loss, too late to be applied in order: it is counted
  ``late`` and not applied. Inputs with no timestamp at all (no router, no timestamping) are
  released as they arrive.

Across sources (odometry from one process, observations from another) there is no
publication order: they are merged by ``stamp`` (odometry first at equal stamps). With
``sources`` = N the order releases nothing until N sources have sent something; then the
input with the smallest stamp goes once every other source has sent one at least as late,
or has been silent for ``reorder_s`` (counted ``waited`` when that wait held an input back).
One source alone is never waited for.

Where each source stood is what a checkpoint keeps (:meth:`InputOrder.positions`), so that
after a restart the inputs a publisher's cache replays are known as applied
(:meth:`InputOrder.resume`).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

#: how long a numbered input waits behind a gap that Zenoh neither fills nor reports (s)
DEFAULT_GAP_WAIT_S = 10.0
#: how long the merge of several sources waits for one that has gone quiet (s)
DEFAULT_REORDER_S = 0.5
#: applied publication times remembered per source, to tell a duplicate from a late input
_RECENT = 4096
#: number ranges given up remembered per source, to tell a late input from a duplicate
_GIVEN_UP = 256
FIRST_SEQ = 1  #: where a driver's ``input_seq`` starts
_LEAF_RANK = {"odometry": 0, "observations": 1}


@dataclass(frozen=True)
class Input:
    """One decoded input and where it came from."""

    leaf: str  #: "odometry" or "observations"
    message: Any  #: the decoded Odometry / Observations
    source: str | None = None  #: publishing session (timestamp id), if stamped
    time: int | None = None  #: publication time (NTP64 of ``source``), if stamped

    @property
    def seq(self) -> int | None:
        return getattr(self.message, "input_seq", None)

    @property
    def stamp(self) -> float:
        return float(self.message.stamp)


@dataclass(frozen=True)
class Missed:
    """Zenoh's report that ``count`` samples of ``source`` are missed for good."""

    source: str | None
    count: int


@dataclass
class OrderStats:
    """What the ordering did (counters the estimator reports everywhere; all but
    ``released`` by the names of :data:`slamlens.common.state_header.INPUT_COUNTS`)."""

    released: int = 0
    duplicates: int = 0  #: inputs already applied, discarded
    reordered: int = 0  #: inputs that arrived before an earlier one and were held for it
    lost: int = 0  #: inputs known to be missed for good (numbers given up, Zenoh's reports)
    late: int = 0  #: inputs that arrived after their place in the order had passed
    waited: int = 0  #: inputs the merge of several sources released after a quiet source
    joined_late: int = 0  #: numbers a new source had published before we saw it


@dataclass
class _Source:
    """One publishing session's place in the order."""

    seen: bool = False
    # numbered inputs
    next_seq: int | None = None  #: the number released next by this source's own order
    held: dict[int, tuple[Input, float]] = field(default_factory=dict)  #: seq → (input, when)
    misses: int = 0  #: missed samples Zenoh reported, not yet matched to a gap
    given_up: deque[tuple[int, int]] = field(default_factory=deque)  #: [lo, hi) given up
    # unnumbered inputs
    newest_time: int | None = None  #: publication time of the newest input released
    resumed_time: int | None = None  #: at or before this, applied before a restart
    recent: set[int] = field(default_factory=set)
    recent_order: deque[int] = field(default_factory=deque)
    # what the merge of several sources needs
    ready: deque[tuple[int, Input]] = field(default_factory=deque)  #: (arrival no., input)
    newest_stamp: float | None = None  #: stamp of the newest input released by its order
    heard: float = 0.0  #: when it last sent anything (monotonic s)
    # what was applied (a checkpoint's position)
    applied_seq: int | None = None  #: next number after the newest applied
    applied_time: int | None = None  #: publication time of the newest applied


class InputOrder:
    """Releases inputs in publication order, exactly once (module docstring)."""

    def __init__(self, *, gap_wait_s: float = DEFAULT_GAP_WAIT_S,
                 reorder_s: float = DEFAULT_REORDER_S, sources: int = 1,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._gap_wait_s = float(gap_wait_s)
        self._reorder_s = float(reorder_s)
        self._sources_expected = max(1, int(sources))
        self._clock = clock
        self._sources: dict[str | None, _Source] = {}
        self._arrivals = 0
        self._blocked: set[int] = set()  #: arrival numbers the merge has held back
        self._merged_stamp: float | None = None  #: stamp of the newest the merge released
        self.stats = OrderStats()

    # -- positions (what a checkpoint keeps) ---------------------------------------------
    def positions(self) -> dict[str, dict[str, int | None]]:
        """Per source, the next input number and the newest publication time applied."""
        return {src or "": {"next_seq": s.applied_seq, "last_time": s.applied_time}
                for src, s in self._sources.items()
                if s.applied_seq is not None or s.applied_time is not None}

    def resume(self, positions: Mapping[str, Mapping[str, Any]]) -> None:
        """Continue after ``positions`` (from :meth:`positions`): anything at or before
        them is a duplicate."""
        for src, pos in positions.items():
            next_seq, last_time = pos.get("next_seq"), pos.get("last_time")
            self._sources[src or None] = _Source(
                next_seq=next_seq, applied_seq=next_seq, newest_time=last_time,
                resumed_time=last_time, applied_time=last_time)

    @property
    def held(self) -> int:
        """Inputs waiting: behind a gap, or for the merge of several sources."""
        return sum(len(s.held) + len(s.ready) for s in self._sources.values())

    @property
    def sources_seen(self) -> int:
        return sum(1 for s in self._sources.values() if s.seen)

    # -- arrivals -------------------------------------------------------------------------
    def offer(self, item: Input) -> list[Input]:
        """Take one arrived input; return what can be applied now, in order."""
        src = self._source(item.source)
        if item.seq is not None:
            self._offer_numbered(src, item)
        else:
            self._offer_unnumbered(src, item)
        return self._merge()

    def missed(self, report: Missed) -> list[Input]:
        """Zenoh says ``report.count`` samples of a source are gone for good."""
        src = self._source(report.source)
        if src.next_seq is None:  # an unnumbered source: nothing to wait for, only count
            self.stats.lost += report.count
            return []
        src.misses += report.count
        self._fill_gaps_with_misses(src)
        return self._merge()

    def expire(self) -> list[Input]:
        """Give up gaps older than ``gap_wait_s``; release what a quiet source held back."""
        now = self._clock()
        for src in self._sources.values():
            while src.held:
                first = min(src.held)
                if now - src.held[first][1] < self._gap_wait_s:
                    break
                assert src.next_seq is not None
                self._give_up(src, first - src.next_seq)
        return self._merge()

    def next_deadline(self) -> float | None:
        """When :meth:`expire` may release something (monotonic s), or None."""
        times = [min(t for _, t in s.held.values()) + self._gap_wait_s
                 for s in self._sources.values() if s.held]
        if self._blocked:
            times += [s.heard + self._reorder_s for s in self._sources.values() if s.seen]
        return min(times) if times else None

    # -- one source's own order -------------------------------------------------------------
    def _source(self, source: str | None) -> _Source:
        src = self._sources.setdefault(source, _Source())
        src.seen = True
        src.heard = self._clock()
        return src

    def _offer_numbered(self, src: _Source, item: Input) -> None:
        seq = item.seq
        assert seq is not None
        if src.next_seq is None:  # a new source starts where it is first heard
            self.stats.joined_late += max(0, seq - FIRST_SEQ)
            src.next_seq = seq
        if seq < src.next_seq:
            if any(lo <= seq < hi for lo, hi in src.given_up):
                self.stats.late += 1
            else:
                self.stats.duplicates += 1
            return
        if seq > src.next_seq:
            if seq in src.held:
                self.stats.duplicates += 1
                return
            src.held[seq] = (item, self._clock())
            self.stats.reordered += 1
            self._fill_gaps_with_misses(src)
            return
        self._release(src, item)
        self._drain(src)

    def _offer_unnumbered(self, src: _Source, item: Input) -> None:
        t = item.time
        if t is None:
            self._release(src, item)
            return
        if t in src.recent or (src.resumed_time is not None and t <= src.resumed_time):
            self.stats.duplicates += 1
            return
        if src.newest_time is not None and t < src.newest_time:
            self.stats.late += 1
            return
        src.recent.add(t)
        src.recent_order.append(t)
        if len(src.recent_order) > _RECENT:
            src.recent.discard(src.recent_order.popleft())
        self._release(src, item)

    def _fill_gaps_with_misses(self, src: _Source) -> None:
        """Match Zenoh's miss reports to the gaps in front of held inputs, in order."""
        while src.held and src.misses > 0:
            assert src.next_seq is not None
            take = min(src.misses, min(src.held) - src.next_seq)
            src.misses -= take
            self._give_up(src, take)

    def _give_up(self, src: _Source, count: int) -> None:
        """The next ``count`` numbers of ``src`` will not come: count them lost, go on."""
        assert src.next_seq is not None
        if count > 0:
            self.stats.lost += count
            src.given_up.append((src.next_seq, src.next_seq + count))
            if len(src.given_up) > _GIVEN_UP:
                src.given_up.popleft()
            src.next_seq += count
        self._drain(src)

    def _drain(self, src: _Source) -> None:
        while src.next_seq in src.held:
            item, _ = src.held.pop(src.next_seq)
            self._release(src, item)

    def _release(self, src: _Source, item: Input) -> None:
        """``item`` is next in its source's own order: on to the merge."""
        if item.seq is not None:
            src.next_seq = item.seq + 1
        if item.time is not None:
            src.newest_time = item.time if src.newest_time is None else max(src.newest_time,
                                                                             item.time)
        src.newest_stamp = item.stamp if src.newest_stamp is None else max(src.newest_stamp,
                                                                           item.stamp)
        self._arrivals += 1
        src.ready.append((self._arrivals, item))

    # -- the merge of several sources -------------------------------------------------------
    def _merge(self) -> list[Input]:
        seen = [s for s in self._sources.values() if s.seen]
        if len(seen) < self._sources_expected:
            return []  # nothing goes before every source the settings expect was heard
        out: list[Input] = []
        if len(seen) == 1:
            src = seen[0]
            while src.ready:
                out.append(self._applied(src, src.ready.popleft()[1]))
            return out
        now = self._clock()
        while True:
            heads = [(s.ready[0][1].stamp, _LEAF_RANK.get(s.ready[0][1].leaf, 2),
                      s.ready[0][0], s) for s in seen if s.ready]
            if not heads:
                return out
            stamp, _, arrival, src = min(heads, key=lambda h: h[:3])
            if self._merged_stamp is not None and stamp < self._merged_stamp:
                src.ready.popleft()  # a quiet source woke up behind what already went
                self.stats.late += 1
                continue
            waited_for_quiet = False
            for other in seen:
                if other is src or other.ready or (other.newest_stamp is not None
                                                   and other.newest_stamp >= stamp):
                    continue
                if now - other.heard >= self._reorder_s:
                    waited_for_quiet = True
                    continue
                self._blocked.add(arrival)
                return out
            if arrival in self._blocked:
                self._blocked.discard(arrival)
                if waited_for_quiet:
                    self.stats.waited += 1
            self._merged_stamp = stamp
            out.append(self._applied(src, src.ready.popleft()[1]))

    def _applied(self, src: _Source, item: Input) -> Input:
        """``item`` leaves the order to be applied: it is now part of the position."""
        if item.seq is not None:
            src.applied_seq = item.seq + 1
        if item.time is not None:
            src.applied_time = item.time if src.applied_time is None else max(
                src.applied_time, item.time)
        self.stats.released += 1
        return item


def sorted_for_replay(items: Iterable[Input]) -> list[Input]:
    """A publisher cache's replay (it comes publisher by publisher) in each source's order:
    by input number where there is one, else by publication time."""
    def key(item: Input) -> tuple[str, int, int]:
        return (item.source or "", item.seq if item.seq is not None else -1,
                item.time if item.time is not None else -1)
    return sorted(items, key=key)
