"""The small bus interface every service talks to, over Zenoh or in-process.

Services never touch ``zenoh`` directly: they take a :class:`Bus` (this module: the
interface, the sample, the burst of puts). :class:`~slamlens.common.zenoh_bus.ZenohBus` is
the real transport; :class:`~slamlens.common.inprocess_bus.InProcessBus` runs a service's
logic inside one process for unit tests (integration tests always use real Zenoh sessions on
loopback); :class:`~slamlens.common.channel.QueueChannel` is the queue behind both buses'
channels.

Delivery (docs/delivery.md: producers never wait for consumers, nothing is lost):

* Every publisher uses congestion control *drop*: a slow or stalled consumer never blocks
  ``put``. ``publisher(key, cache=N)`` is a ``zenoh.ext`` advanced publisher that keeps its
  last ``N`` samples, sends heartbeats (sample-miss detection) and announces itself
  (publisher detection), so a consumer that needs everything can recover what congestion,
  a link cut or a restart made it miss. ``publisher(key, latest_wins=True)`` is best
  effort and express (camera frames).
* ``channel(key)`` is one ordered queue for everything matching ``key``: events are
  received in arrival order by whoever calls ``recv`` (no racing callbacks). Its Zenoh
  callback only appends to the queue and returns: it never waits. The queue is bounded by
  memory (``max_bytes``), counted and reported, never by making Zenoh wait.
  ``channel(key, recover=True)`` is an advanced subscriber: samples missed from an
  advanced publisher come back from its cache, in order per publisher, and what could not
  be recovered is counted in ``lost``; ``history_s`` also fetches what the publishers
  cached before the subscriber existed. ``channel(key, latest_wins=True)`` keeps only the
  newest sample (a consumer that only draws the present).
* ``serve_latest(key, provider)`` answers ``get`` with whatever ``provider()`` returns now.
  ``answer(key, handler)`` answers with what the handler decides on Zenoh's thread;
  ``answer_later(key, handler)`` hands the query to the handler with a :class:`Reply` that
  any thread may complete later (a long poll, or work too heavy for a Zenoh callback).
* Each :class:`Sample` carries its Zenoh timestamp (``source``: the publishing session,
  ``time``: its hybrid logical clock, NTP64), which orders one session's publications.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

Callback = Callable[[str, bytes], None]
#: a lazy subscriber's callback: (key, a function returning the payload's bytes when called)
LazyCallback = Callable[[str, Callable[[], bytes]], None]
#: a queryable's handler: (key, query payload or None, selector parameters) → reply or None;
#: the reply is bytes or, on a Zenoh bus, what one of its publishers' ``put`` returned (a
#: shared-memory ZBytes, answered without a copy)
Answer = Callable[[str, "bytes | None", str], Any]

DEFAULT_QUEUE_BYTES = 1 << 30  #: 1 GiB of payloads waiting in one channel, then drop oldest


@dataclass(frozen=True)
class Sample:
    """One received payload and the key it was published on."""

    key: str
    payload: bytes
    #: the publishing session's timestamp id (hex), when the sample carries a timestamp
    source: str | None = None
    #: the publication time as NTP64 (hybrid logical clock of ``source``: strictly
    #: increasing over that session's publications, on every key)
    time: int | None = None
    #: > 0: not a publication but Zenoh's report that this many samples of ``source`` are
    #: missed for good (``channel(..., report_misses=True)``; key and payload empty)
    missed: int = 0


#: a payload, whole or as consecutive parts (``Message.wire_parts``: a large one is then
#: copied once, into shared memory or into the joined bytes)
Payload = bytes | bytearray | list[bytes | bytearray | memoryview]


def joined(payload: Payload) -> bytes:
    """A payload as one bytes object."""
    return b"".join(payload) if isinstance(payload, list) else bytes(payload)


def payload_length(payload: Payload) -> int:
    return sum(len(p) for p in payload) if isinstance(payload, list) else len(payload)


class Publisher(Protocol):
    def put(self, payload: Payload) -> Any:
        """Publish ``payload``. Returns what went out when it can be answered or put again
        without a copy and holds none of ``payload``'s memory (a shared-memory buffer, or
        the payload joined into bytes of its own), else None (it may be ``payload``)."""
        ...


class BurstPuts:
    """Puts held for the length of a burst and then made back to back, so Zenoh sends many
    small payloads in a few batches instead of one write each (a put that finds the link
    idle costs its publisher several times the CPU of one that joins a batch:
    ``benchmarks/bench_put.py``; docs/delivery.md, "Bursts").

    Outside :meth:`burst` every :meth:`put` goes out at once. Inside it, payloads under
    ``below_bytes`` wait — at most ``limit`` of them — and go out in order when the limit
    is reached, at :meth:`flush`, or when the burst ends; a larger one first sends what
    waits, then itself. ``sent(tag)`` says which payload is going out, just before its
    put, for every payload: whatever ``sent`` publishes (the answer to a ``get``) is the
    payload being put or the last one put — never older than one a subscriber has
    received (a client that saw state N and then asks gets N or later), never one still
    waiting in the burst.
    """

    def __init__(self, publisher: Publisher, *, limit: int, sent: Callable[[Any], None],
                 below_bytes: int | None = None) -> None:
        self._publisher = publisher
        self._limit = max(1, limit)
        self._sent = sent
        self._below = below_bytes
        self._held: list[tuple[Payload, Any]] | None = None  #: None: not in a burst

    @contextmanager
    def burst(self) -> Iterator[None]:
        self._held = []
        try:
            yield
        finally:
            self.flush()
            self._held = None

    def put(self, payload: Payload, tag: Any) -> Any:
        """Put or hold ``payload``; for one sent at once, what the publisher's ``put``
        returned (:meth:`Publisher.put`), else None."""
        held = self._held
        if held is not None and (self._below is None or payload_length(payload) < self._below):
            held.append((payload, tag))
            if len(held) >= self._limit:
                self.flush()
            return None
        self.flush()
        self._sent(tag)
        return self._publisher.put(payload)

    def flush(self) -> None:
        """Put what waits, back to back, in order."""
        held = self._held
        if held:
            for payload, tag in held:
                self._sent(tag)
                self._publisher.put(payload)
            held.clear()


class Reply(Protocol):
    """The answer to one query, given once, from any thread (``answer_later``)."""

    def ok(self, payload: bytes) -> None:
        """Answer with ``payload`` and end the query."""
        ...

    def error(self, payload: bytes) -> None:
        """Answer with an error (Zenoh's ``reply_err``) and end the query."""
        ...

    @property
    def done(self) -> bool: ...


#: a deferred queryable's handler: (key, query payload or None, parameters, reply); it runs
#: on Zenoh's thread, so it only stores the reply for a worker (or completes it at once)
LaterAnswer = Callable[[str, "bytes | None", str, Reply], None]


class Channel(Protocol):
    def recv(self, timeout: float | None = None) -> Sample | None:
        """Next sample, or None after ``timeout`` seconds (or when closed)."""
        ...

    @property
    def backlog(self) -> int:
        """Samples received and not yet taken."""
        ...

    @property
    def backlog_bytes(self) -> int:
        """Payload bytes received and not yet taken."""
        ...

    def take_all(self) -> list[Sample]:
        """Everything queued now, oldest first, without waiting."""
        ...

    @property
    def dropped(self) -> int:
        """Samples discarded on purpose (latest wins) or for lack of memory."""
        ...

    @property
    def lost(self) -> int:
        """Samples a recovering channel knows it missed and could not get back."""
        ...

    @property
    def superseded(self) -> int:
        """Large samples (``newest_above``) replaced, uncopied, by a newer one of their key
        before they were taken."""
        ...

    def close(self) -> None: ...


class Bus(Protocol):
    """What a service needs from the transport."""

    def publisher(self, key: str, *, latest_wins: bool = False, cache: int = 0,
                  cache_bytes: int | None = None) -> Publisher: ...

    def subscribe(self, key: str, callback: Callback) -> Any: ...

    def channel(self, key: str, *, latest_wins: bool = False, recover: bool = False,
                history_s: float = 0.0, max_bytes: int = DEFAULT_QUEUE_BYTES,
                accept: Callable[[str], bool] | None = None,
                also: tuple[str, ...] = (), newest_above: int | None = None,
                report_misses: bool = False) -> Channel: ...

    def cached(self, key: str, *, max_age_s: float | None = None,
               timeout: float = 10.0) -> list[Sample]: ...

    def wait_for_subscriber(self, key: str, *, timeout: float = 10.0) -> bool: ...

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any: ...

    def answer(self, key: str, handler: Answer) -> Any: ...

    def answer_later(self, key: str, handler: LaterAnswer) -> Any: ...

    def subscribe_lazy(self, key: str, callback: LazyCallback) -> Any: ...

    def get(self, key: str, *, timeout: float = 2.0, payload: bytes | None = None,
            errors: list[bytes] | None = None) -> list[Sample]: ...

    def declare_alive(self, key: str) -> Any: ...

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]: ...

    def release(self, entity: Any) -> None:
        """Undeclare one thing this bus declared (a publisher, subscriber, channel,
        queryable or liveliness token) before the bus closes: what a service that adds
        and drops parts while it runs (a browser camera that comes and goes) gives back."""
        ...

    def close(self) -> None: ...


def pump(channel: Channel, handle: Callable[[str, bytes], object], stop: threading.Event, *,
         status: Callable[[], None] | None = None, status_every_s: float = 10.0) -> None:
    """Feed every sample of ``channel`` to ``handle`` in order until ``stop`` is set,
    calling ``status`` (e.g. a log line) every ``status_every_s`` seconds."""
    last = time.monotonic()
    while not stop.is_set():
        sample = channel.recv(timeout=0.2)
        if sample is not None:
            handle(sample.key, sample.payload)
        if status is not None and time.monotonic() - last >= status_every_s:
            last = time.monotonic()
            status()
