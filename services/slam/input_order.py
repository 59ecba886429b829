"""The estimator's inputs in publication order, each folded in exactly once (SPEC §7a).

Odometry and observations travel on two keys. Zenoh keeps each publisher's samples in
order (the advanced subscriber holds later samples back while it recovers a missed one
from the publisher's cache), but nothing orders one key against the other: a recovered
odometry sample can arrive after a later observation batch. Drivers therefore number
their inputs with one counter over both keys (``input_seq``, docs/protocol.md), and this
module releases them strictly in that order:

* the next number of a source is released at once (the common case: no added latency);
* a later number is held until the missing ones arrive (recovered from the cache), or
  until it has waited ``gap_wait_s`` — then the missing numbers before it are counted as
  lost and it is released (with whatever follows it in order); each held input waits at
  most ``gap_wait_s`` in all, however many gaps are in front of it (a recovery that missed
  every observation but no odometry costs 2 s, not 2 s per observation);
* a number already released (a duplicate: a recovered copy, a cache replayed after an
  estimator restart) is discarded.

Drivers count from 1, so a new source is expected from 1: an estimator that joins a
driver already running waits ``gap_wait_s`` once for numbers it will never see, and those
are counted as ``joined_late``, not lost.

A *source* is one publishing Zenoh session (the id in the sample's timestamp). Inputs
without ``input_seq`` — a third-party driver — are put in the order of their Zenoh
timestamps (one session's clock strictly increases over all its publications, on every
key): an input is released once a later-stamped input of the same source has arrived on
each other input key (Zenoh keeps each key's order, so nothing earlier can still come),
or ``reorder_s`` after it arrived, whichever is first — so a third-party driver whose other
key is quiet pays up to ``reorder_s`` of latency (Zenoh was seen to deliver the first put
of one key before an earlier one of the other). One with the very timestamp of an input
already released is a duplicate. Inputs with no timestamp at all go in arrival order.
"""

from __future__ import annotations

import heapq
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

#: how long an input that arrived out of order waits for the ones before it (s)
DEFAULT_GAP_WAIT_S = 2.0
#: how long an unnumbered input waits for earlier-stamped ones on the other key (s)
DEFAULT_REORDER_S = 0.02
#: publication times remembered per source to tell an unnumbered duplicate
_RECENT = 4096


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


FIRST_SEQ = 1  #: where a driver's ``input_seq`` starts


@dataclass
class _Source:
    next_seq: int | None = None  #: the number released next
    started: bool = False  #: released anything yet
    last_time: int | None = None  #: publication time of the newest input released
    held: dict[int, Input] = field(default_factory=dict)
    held_at: dict[int, float] = field(default_factory=dict)  #: when each held one arrived
    held_since: float | None = None  #: when the first input after the gap arrived
    # unnumbered inputs: waiting in timestamp order, the newest time seen per key, and
    # the times already released (duplicates are told by their exact timestamp)
    waiting: list[tuple[int, float, int, Input]] = field(default_factory=list)
    newest: dict[str, int] = field(default_factory=dict)
    released: set[int] = field(default_factory=set)
    released_order: deque[int] = field(default_factory=deque)


@dataclass
class OrderStats:
    """What the ordering did (counters, reported by the estimator)."""

    released: int = 0
    duplicates: int = 0  #: inputs already folded in, discarded
    reordered: int = 0  #: inputs that arrived early and were held
    lost: int = 0  #: input numbers never seen, skipped after ``gap_wait_s``
    late: int = 0  #: unnumbered inputs that arrived after a later-stamped one was applied
    joined_late: int = 0  #: numbers a new source had published before we saw it


class InputOrder:
    """Releases inputs in publication order, exactly once (module docstring)."""

    def __init__(self, *, gap_wait_s: float = DEFAULT_GAP_WAIT_S,
                 reorder_s: float = DEFAULT_REORDER_S,
                 leaves: tuple[str, ...] = ("odometry", "observations"),
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._gap_wait_s = float(gap_wait_s)
        self._reorder_s = float(reorder_s)
        self._leaves = leaves
        self._arrivals = 0
        self._clock = clock
        self._sources: dict[str | None, _Source] = {}
        self.stats = OrderStats()

    # -- positions (what a checkpoint keeps) ---------------------------------------------
    def positions(self) -> dict[str, dict[str, int | None]]:
        """Per source, the next input number and the newest publication time released."""
        return {src or "": {"next_seq": s.next_seq, "last_time": s.last_time}
                for src, s in self._sources.items()}

    def resume(self, positions: Mapping[str, Mapping[str, Any]]) -> None:
        """Continue after ``positions`` (from :meth:`positions`): anything at or before
        them is a duplicate."""
        for src, pos in positions.items():
            self._sources[src or None] = _Source(next_seq=pos.get("next_seq"),
                                                 last_time=pos.get("last_time"),
                                                 started=True)

    @property
    def held(self) -> int:
        """Inputs waiting for an earlier one."""
        return sum(len(s.held) + len(s.waiting) for s in self._sources.values())

    # -- the ordering -----------------------------------------------------------------
    def offer(self, item: Input) -> list[Input]:
        """Take one arrived input; return what can be applied now, in order."""
        src = self._sources.setdefault(item.source, _Source())
        seq = item.seq
        if seq is None:  # no number: the order of the Zenoh clock
            if item.time is None:
                self._advance(src, item)
                return [item]
            if item.time in src.released or any(w[0] == item.time for w in src.waiting):
                self.stats.duplicates += 1
                return []
            src.newest[item.leaf] = max(src.newest.get(item.leaf, item.time), item.time)
            self._arrivals += 1
            heapq.heappush(src.waiting, (item.time, self._clock(), self._arrivals, item))
            return self._release_waiting(src)
        if src.next_seq is None:
            src.next_seq = FIRST_SEQ
        if seq < src.next_seq or seq in src.held:
            self.stats.duplicates += 1
            return []
        if seq > src.next_seq:
            src.held[seq] = item
            src.held_at[seq] = self._clock()
            self.stats.reordered += 1
            if src.held_since is None:
                src.held_since = src.held_at[seq]
            return []
        out = [item]
        self._advance(src, item)
        self._drain(src, out)
        return out

    def next_deadline(self) -> float | None:
        """When the oldest gap gives up or the oldest unnumbered input stops waiting
        (monotonic s), or None if nothing is held."""
        times = [s.held_since + self._gap_wait_s for s in self._sources.values()
                 if s.held and s.held_since is not None]
        times += [min(w[1] for w in s.waiting) + self._reorder_s
                  for s in self._sources.values() if s.waiting]
        return min(times) if times else None

    def _release_waiting(self, src: _Source) -> list[Input]:
        """Unnumbered inputs that nothing earlier can precede any more, in time order."""
        now = self._clock()
        out: list[Input] = []
        while src.waiting:
            t, arrived, _, item = src.waiting[0]
            others = [src.newest.get(k) for k in self._leaves if k != item.leaf]
            if not (all(v is not None and v > t for v in others)
                    or now - arrived >= self._reorder_s):
                break
            heapq.heappop(src.waiting)
            if src.last_time is not None and t < src.last_time:
                self.stats.late += 1  # later than the window: applied, but out of order
            self._advance(src, item)
            src.released.add(t)
            src.released_order.append(t)
            if len(src.released_order) > _RECENT:
                src.released.discard(src.released_order.popleft())
            out.append(item)
        return out

    def expire(self) -> list[Input]:
        """Give up on gaps older than ``gap_wait_s``: count them lost, release what
        waited behind them."""
        now = self._clock()
        out: list[Input] = []
        for src in self._sources.values():
            if src.waiting:
                out += self._release_waiting(src)
            while src.held and src.held_since is not None \
                    and now - src.held_since >= self._gap_wait_s:
                first = min(src.held)
                assert src.next_seq is not None
                if src.started:
                    self.stats.lost += first - src.next_seq
                else:
                    self.stats.joined_late += first - src.next_seq
                src.next_seq = first
                src.held_since = None
                self._drain(src, out)
        return out

    def _advance(self, src: _Source, item: Input) -> None:
        src.started = True
        if item.seq is not None:
            src.next_seq = item.seq + 1
        if item.time is not None:
            src.last_time = item.time if src.last_time is None else max(src.last_time,
                                                                         item.time)
        self.stats.released += 1

    def _drain(self, src: _Source, out: list[Input]) -> None:
        while src.next_seq in src.held:
            del src.held_at[src.next_seq]
            item = src.held.pop(src.next_seq)
            self._advance(src, item)
            out.append(item)
        # the next gap's clock started when the input just after it arrived: inputs held
        # behind several gaps wait gap_wait_s once, not once per gap
        src.held_since = src.held_at[min(src.held)] if src.held else None
