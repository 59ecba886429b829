"""The small bus interface every service talks to, over Zenoh or in-process.

Services never touch ``zenoh`` directly: they take a :class:`Bus`. :class:`ZenohBus` is the
real transport; :class:`InProcessBus` runs a service's logic inside one process for unit
tests (integration tests always use real Zenoh sessions on loopback).

Delivery (SPEC §7a: producers never wait for consumers, and nothing is lost):

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

import atexit
import logging
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

log = logging.getLogger(__name__)

Callback = Callable[[str, bytes], None]
#: a lazy subscriber's callback: (key, a function returning the payload's bytes when called)
LazyCallback = Callable[[str, Callable[[], bytes]], None]
#: a queryable's handler: (key, query payload or None, selector parameters) → reply or None;
#: the reply is bytes or, on a Zenoh bus, what one of its publishers' ``put`` returned (a
#: shared-memory ZBytes, answered without a copy)
Answer = Callable[[str, "bytes | None", str], Any]

DEFAULT_QUEUE_BYTES = 1 << 30  #: 1 GiB of payloads waiting in one channel, then drop oldest
_LOST_LOG_EVERY = 1000
#: period of an advanced publisher's heartbeat (s): how soon a subscriber notices that the
#: newest samples went missing (after a link cut) and asks the cache for them
HEARTBEAT_S = 0.5
#: payloads at least this large go through Zenoh shared memory when a subscriber shares the
#: host (a state of ≈ 180 landmarks and more); smaller ones are not worth the allocation
SHM_MIN_BYTES = 1 << 20
#: the shared-memory pool of one session (it must also hold what the caches keep)
SHM_POOL_BYTES = 1 << 30


def _at_shutdown(fn: Callable[[], object]) -> None:
    """Run ``fn`` at interpreter exit *before* non-daemon threads are joined.

    zenoh-python runs callback subscribers on a non-daemon Python thread, so a session
    left open makes the interpreter wait forever at exit; plain ``atexit`` runs too late
    (after that join). ``threading._register_atexit`` runs first; fall back to atexit.
    """
    register = getattr(threading, "_register_atexit", None)
    try:
        if register is not None:
            register(fn)
            return
    except RuntimeError:  # already shutting down
        pass
    atexit.register(fn)


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
    waits, then itself. ``sent(tag)`` says which payload is out: before its own put for one
    sent at once, after the group's puts (with the group's last tag) for held ones, so
    whatever ``sent`` publishes (the answer to a ``get``) never runs ahead of the puts.
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
            for payload, _tag in held:
                self._publisher.put(payload)
            self._sent(held[-1][1])
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
                also: tuple[str, ...] = (), newest_above: int | None = None) -> Channel: ...

    def wait_for_subscriber(self, key: str, *, timeout: float = 10.0) -> bool: ...

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any: ...

    def answer(self, key: str, handler: Answer) -> Any: ...

    def answer_later(self, key: str, handler: LaterAnswer) -> Any: ...

    def subscribe_lazy(self, key: str, callback: LazyCallback) -> Any: ...

    def get(self, key: str, *, timeout: float = 2.0, payload: bytes | None = None,
            errors: list[bytes] | None = None) -> list[Sample]: ...

    def declare_alive(self, key: str) -> Any: ...

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]: ...

    def release(self, entity: Any) -> None: ...

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


# ---------------------------------------------------------------------------------
# Zenoh
# ---------------------------------------------------------------------------------


@dataclass(eq=False)
class _Deferred:
    """A large sample left in Zenoh's buffer until it is taken (``newest_above``)."""

    sample: Sample  #: key and timestamp; the payload is fetched when taken
    fetch: Callable[[], bytes]
    size: int

    def resolve(self) -> Sample:
        s = self.sample
        return Sample(s.key, self.fetch(), source=s.source, time=s.time)


def _size(item: Sample | _Deferred) -> int:
    return item.size if isinstance(item, _Deferred) else len(item.payload)


class QueueChannel:
    """An in-order queue of samples fed by a subscriber callback; ``push`` never blocks.

    ``recv`` wakes the moment a sample arrives (no polling). With ``capacity`` (1 = latest
    wins) the oldest samples beyond it are dropped; otherwise the queue grows until its
    payloads hold ``max_bytes``, then drops its oldest — counted in ``dropped`` and logged —
    rather than ever making the feeding (Zenoh) thread wait. A sample pushed with
    :meth:`push_newest` (a large one) is copied only when taken, and replaces an older one of
    its key still waiting (counted in ``superseded``): the queue holds at most one such
    payload per key, so it pins at most that much of the publisher's shared memory.
    """

    def __init__(self, *, name: str = "", capacity: int | None = None,
                 max_bytes: int = DEFAULT_QUEUE_BYTES) -> None:
        self.name = name
        self._items: deque[Sample | _Deferred] = deque()
        self._newest: dict[str, _Deferred] = {}  #: the deferred sample waiting, per key
        self._superseded = 0
        self._capacity = None if capacity is None else max(1, capacity)
        self._max_bytes = max(1, max_bytes)
        self._bytes = 0
        self._cond = threading.Condition()
        self._closed = False
        self._dropped = 0
        self._lost = 0
        self.received = 0  #: samples pushed in all
        self.high_water = 0  #: the largest backlog seen
        self._on_close: list[Callable[[], None]] = []

    @property
    def backlog(self) -> int:
        return len(self._items)

    @property
    def backlog_bytes(self) -> int:
        """Payload bytes received and not yet taken."""
        return self._bytes

    def take_all(self) -> list[Sample]:
        """Everything queued now, oldest first, without waiting."""
        with self._cond:
            items, self._items = list(self._items), deque()
            self._bytes = 0
            self._newest.clear()
        return [x.resolve() if isinstance(x, _Deferred) else x for x in items]

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def lost(self) -> int:
        return self._lost

    @property
    def superseded(self) -> int:
        return self._superseded

    def count_lost(self, n: int) -> None:
        """Record ``n`` samples known to be missed for good (sample-miss detection)."""
        with self._cond:
            self._lost += n
            total = self._lost
        if total == n or total // _LOST_LOG_EVERY != (total - n) // _LOST_LOG_EVERY:
            log.warning("%s: %d sample(s) missed and not recoverable (%d so far)",
                        self.name or "channel", n, total)

    def push_newest(self, sample: Sample, fetch: Callable[[], bytes], size: int) -> None:
        """Queue a large sample whose payload (``size`` bytes) ``fetch`` copies when it is
        taken; an older one of its key still waiting is dropped, uncopied (``superseded``)."""
        self.push(_Deferred(sample, fetch, size))

    def push(self, sample: Sample | _Deferred) -> None:
        overflow = False
        with self._cond:
            if self._closed:
                return
            if isinstance(sample, _Deferred):
                older = self._newest.pop(sample.sample.key, None)
                if older is not None:
                    self._items.remove(older)
                    self._bytes -= older.size
                    self._superseded += 1
                self._newest[sample.sample.key] = sample
            self._items.append(sample)
            self._bytes += _size(sample)
            self.received += 1
            if self._capacity is not None:
                while len(self._items) > self._capacity:
                    self._forget(self._items.popleft())
                    self._dropped += 1
            else:
                while self._bytes > self._max_bytes and len(self._items) > 1:
                    self._forget(self._items.popleft())
                    self._dropped += 1
                    overflow = True
            if len(self._items) > self.high_water:
                self.high_water = len(self._items)
            dropped = self._dropped
            self._cond.notify()
        if overflow and (dropped == 1 or dropped % _LOST_LOG_EVERY == 0):
            log.warning("%s: queue over %d MB, oldest samples dropped (%d so far)",
                        self.name or "channel", self._max_bytes >> 20, dropped)

    def _forget(self, item: Sample | _Deferred) -> None:
        """Account for ``item`` leaving the queue (under the lock)."""
        self._bytes -= _size(item)
        if isinstance(item, _Deferred) and self._newest.get(item.sample.key) is item:
            del self._newest[item.sample.key]

    def recv(self, timeout: float | None = None) -> Sample | None:
        with self._cond:
            if not self._cond.wait_for(lambda: self._items or self._closed, timeout):
                return None
            if not self._items:
                return None
            item = self._items.popleft()
            self._forget(item)
        return item.resolve() if isinstance(item, _Deferred) else item

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._items.clear()
            self._newest.clear()
            self._bytes = 0
            self._cond.notify_all()
        for undeclare in reversed(self._on_close):
            try:
                undeclare()
            except Exception:  # already gone with the session
                pass


def _wait_matching(pub: Any, timeout: float) -> bool:
    """Wait (event-driven) until a zenoh publisher's matching status is true."""
    if pub.matching_status:
        return True
    matched = threading.Event()
    listener = pub.declare_matching_listener(
        lambda status: matched.set() if status.matching else None)
    try:
        return matched.wait(timeout) or bool(pub.matching_status)
    finally:
        listener.undeclare()


def _sample_of(zsample: Any, key: str | None = None, *, copy: bool = True) -> Sample:
    """A :class:`Sample` from a ``zenoh.Sample`` (payload copied out of Zenoh's buffer;
    left empty with ``copy=False``)."""
    payload = zsample.payload.to_bytes() if copy else b""
    ts = zsample.timestamp
    if ts is None:
        return Sample(key or str(zsample.key_expr), payload)
    return Sample(key or str(zsample.key_expr), payload,
                  source=str(ts.get_id()), time=int(str(ts.get_time_as_ntp64())))  # raw u64


class ShmPool:
    """Large payloads copied once into Zenoh shared memory (zenoh.shm), else plain bytes.

    Zenoh hands a shared-memory payload to subscribers on the same host by reference and
    sends its bytes to the others, so the publisher need not know who is where. The pool is
    made on first use; if the host cannot give it (a small /dev/shm) or it is full (caches
    hold their samples), the payload goes as plain bytes — counted, never waited for.
    """

    def __init__(self, *, pool_bytes: int = SHM_POOL_BYTES,
                 min_bytes: int = SHM_MIN_BYTES) -> None:
        self.pool_bytes = pool_bytes
        self.min_bytes = min_bytes
        self._provider: Any = None
        self._unavailable = False
        self._lock = threading.Lock()
        self.shared = 0  #: payloads sent through shared memory
        self.plain = 0  #: large payloads sent as bytes (pool full or unavailable)

    def wrap(self, payload: Payload) -> Any:
        """``payload`` as a shared-memory ZBytes if it is large and there is room (parts
        are written one after the other: one copy in all), else as bytes."""
        size = payload_length(payload)
        if size < self.min_bytes or self._unavailable:
            return joined(payload) if isinstance(payload, list) else payload
        import zenoh
        from zenoh import shm

        with self._lock:
            if self._provider is None:
                try:
                    self._provider = shm.ShmProvider.default_backend(self.pool_bytes)
                except zenoh.ZError as exc:
                    self._unavailable = True
                    log.warning("no shared memory for large payloads (%s): they go as bytes",
                                exc)
                    return joined(payload) if isinstance(payload, list) else payload
            try:  # never block: garbage-collect what subscribers released, else give up
                buf = self._provider.alloc(size, shm.GarbageCollect())
            except zenoh.ZError:
                self.plain += 1
                return joined(payload) if isinstance(payload, list) else payload
        offset = 0
        for part in payload if isinstance(payload, list) else (payload,):
            end = offset + len(part)
            # ZShmMut takes bytes or bytearray only
            buf[offset:end] = part if isinstance(part, (bytes, bytearray)) else bytes(part)
            offset = end
        self.shared += 1
        return zenoh.ZBytes(buf)


def _put_wrapped(pub: Any, payload: Payload, pool: ShmPool | None) -> Any:
    """Put ``payload`` on the Zenoh publisher ``pub`` (a large one through ``pool``'s
    shared memory); what went out if it is not ``payload`` itself (:meth:`Publisher.put`)."""
    out = joined(payload) if pool is None else pool.wrap(payload)
    pub.put(out)
    return None if out is payload else out


class _ZenohPublisher:
    def __init__(self, publisher: Any, pool: ShmPool | None = None) -> None:
        self._pub = publisher
        self._pool = pool

    def put(self, payload: Payload) -> Any:
        return _put_wrapped(self._pub, payload, self._pool)

    def wait_matched(self, timeout: float = 10.0) -> bool:
        """Wait until this publisher itself knows a matching subscriber (its own matching
        status: a *new* publisher may drop its first put even when another publisher of
        the same session already matches)."""
        return _wait_matching(self._pub, timeout)

    def undeclare(self) -> None:
        self._pub.undeclare()


class _CachingPublisher:
    """An advanced publisher whose cache holds at most ``cache_bytes`` of payloads.

    A cache is sized in samples when declared; as payloads grow (a map's state grows with
    its landmarks) the publisher is declared again with fewer samples, so the cache never
    outgrows its byte budget. Subscribers see a new publisher then (nothing is missed:
    the new one publishes the next sample).
    """

    MIN_SAMPLES = 4

    def __init__(self, declare: Callable[[int], Any], *, samples: int,
                 cache_bytes: int | None, pool: ShmPool | None = None) -> None:
        self._declare = declare
        self._pool = pool
        self._samples = max(1, int(samples))
        self._budget = cache_bytes
        self._pub = declare(self._samples)
        self.redeclared = 0

    def put(self, payload: Payload) -> None:
        budget = self._budget
        size = payload_length(payload)
        if budget is not None and self._samples > self.MIN_SAMPLES \
                and size * self._samples > budget:
            samples = max(self.MIN_SAMPLES, budget // max(1, size) // 2)
            if samples < self._samples:
                old, self._samples = self._pub, samples
                self._pub = self._declare(samples)
                self.redeclared += 1
                try:
                    old.undeclare()
                except Exception:
                    pass
        return _put_wrapped(self._pub, payload, self._pool)

    def undeclare(self) -> None:
        self._pub.undeclare()


class _ZenohReply:
    """A :class:`Reply` holding a Zenoh query until it is answered (then dropped: the
    final reply goes out)."""

    def __init__(self, query: Any, key: str) -> None:
        self._query: Any = query
        self._key = key
        self._lock = threading.Lock()

    @property
    def done(self) -> bool:
        return self._query is None

    def _finish(self, send: Callable[[Any], None]) -> None:
        with self._lock:
            query, self._query = self._query, None
        if query is None:
            return
        try:
            send(query)
        except Exception as exc:  # the client gave up, or the session closed
            log.debug("reply on %s not sent: %s", self._key, exc)
        finally:
            try:
                query.drop()
            except Exception:
                pass

    def ok(self, payload: bytes) -> None:
        self._finish(lambda q: q.reply(self._key, payload))

    def error(self, payload: bytes) -> None:
        self._finish(lambda q: q.reply_err(payload))


class ZenohBus:
    """A :class:`Bus` on one Zenoh session; closes everything it declared on ``close``."""

    def __init__(self, session: Any) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.shm = ShmPool()  #: large payloads through shared memory (same host)
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False
        ref = weakref.ref(self)

        def close_if_alive() -> None:
            bus = ref()
            if bus is not None:
                bus.close()

        _at_shutdown(close_if_alive)

    def _keep(self, entity: Any) -> Any:
        with self._lock:
            self._entities.append(entity)
        return entity

    def publisher(self, key: str, *, latest_wins: bool = False, cache: int = 0,
                  cache_bytes: int | None = None) -> Publisher:
        """A publisher that never blocks (module docstring): best effort and express with
        ``latest_wins``; an advanced publisher caching its last ``cache`` samples (and at
        most ``cache_bytes`` of them), with heartbeats and publisher detection, when
        ``cache`` > 0; else plain reliable."""
        z = self._zenoh
        out: Any
        if latest_wins:
            out = _ZenohPublisher(self.session.declare_publisher(
                key, congestion_control=z.CongestionControl.DROP,
                reliability=z.Reliability.BEST_EFFORT, express=True))
        elif cache > 0:
            import zenoh.ext as zext

            def declare(samples: int) -> Any:
                return zext.declare_advanced_publisher(
                    self.session, key, congestion_control=z.CongestionControl.DROP,
                    reliability=z.Reliability.RELIABLE,
                    cache=zext.CacheConfig(int(samples)),
                    sample_miss_detection=zext.MissDetectionConfig(
                        heartbeat=HEARTBEAT_S, sporadic_heartbeat=None),
                    publisher_detection=True)

            out = _CachingPublisher(declare, samples=cache, cache_bytes=cache_bytes,
                                    pool=self.shm)
        else:
            out = _ZenohPublisher(self.session.declare_publisher(
                key, congestion_control=z.CongestionControl.DROP,
                reliability=z.Reliability.RELIABLE), self.shm)
        self._keep(out)
        return out

    def subscribe(self, key: str, callback: Callback) -> Any:
        """Call ``callback(key, payload)`` on Zenoh's thread for every sample: it must
        return at once (store and wake a worker), never wait."""
        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # never let a callback kill zenoh's thread silently
                log.exception("subscriber callback for %s failed", key)

        return self._keep(self.session.declare_subscriber(key, on_sample))

    def subscribe_lazy(self, key: str, callback: LazyCallback) -> Any:
        """As :meth:`subscribe`, but the callback gets a function that copies the payload
        only when called: a consumer that keeps only the newest of large payloads (a
        32 MB state at 100 per second) pays for the ones it uses."""
        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes)
            except Exception:
                log.exception("subscriber callback for %s failed", key)

        return self._keep(self.session.declare_subscriber(key, on_sample))

    def channel(self, key: str, *, latest_wins: bool = False, recover: bool = False,
                history_s: float = 0.0, max_bytes: int = DEFAULT_QUEUE_BYTES,
                accept: Callable[[str], bool] | None = None,
                also: tuple[str, ...] = (), newest_above: int | None = None) -> Channel:
        """One ordered queue for ``key`` and the key expressions ``also`` (module
        docstring); ``accept(key)`` filters samples before their payload is copied. A
        payload of at least ``newest_above`` bytes stays in Zenoh's buffer until taken, and
        only the newest of its key waits (:meth:`QueueChannel.push_newest`)."""
        ch = QueueChannel(name=key, capacity=1 if latest_wins else None, max_bytes=max_bytes)

        def on_sample(sample: Any) -> None:
            sample_key = str(sample.key_expr)
            if accept is None or accept(sample_key):  # filter before copying the payload
                size = len(sample.payload)
                if newest_above is not None and size >= newest_above:
                    ch.push_newest(_sample_of(sample, sample_key, copy=False),
                                   sample.payload.to_bytes, size)
                else:
                    ch.push(_sample_of(sample, sample_key))

        for expr in (key, *also):
            if recover or history_s > 0:
                import zenoh.ext as zext

                history = (zext.HistoryConfig(detect_late_publishers=True,
                                              max_age=float(history_s))
                           if history_s > 0 else None)
                sub = zext.declare_advanced_subscriber(
                    self.session, expr, on_sample, history=history,
                    recovery=zext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                    subscriber_detection=True)
                misses = sub.sample_miss_listener(lambda miss: ch.count_lost(int(miss.nb)))
                ch._on_close.append(sub.undeclare)
                ch._on_close.append(misses.undeclare)
            else:
                sub = self.session.declare_subscriber(expr, on_sample)
                ch._on_close.append(sub.undeclare)
        self._keep(ch)
        return ch

    def wait_for_subscriber(self, key: str, *, timeout: float = 10.0) -> bool:
        """Wait until some subscriber matches ``key`` (Zenoh matching status): what a
        publisher that must not publish into the void waits on."""
        import zenoh

        probe = self.session.declare_publisher(key)
        try:
            return _wait_matching(probe, timeout)
        except zenoh.ZError:  # the session closed while waiting
            return False
        finally:
            probe.undeclare()

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any:
        def on_query(query: Any) -> None:
            try:
                payload = provider()
                if payload is not None:
                    query.reply(key, payload)
            except Exception:
                log.exception("queryable %s failed", key)

        return self._keep(self.session.declare_queryable(key, on_query))

    def answer(self, key: str, handler: Answer) -> Any:
        """Answer a ``get`` on ``key`` with ``handler(key, query payload, parameters)`` (a
        request, e.g. a re-registration, from a client that may query but not publish; or
        a selector such as ``state?header``). The handler runs on Zenoh's thread: it must
        only decide and store, never wait."""
        def on_query(query: Any) -> None:
            try:
                payload = query.payload.to_bytes() if query.payload is not None else None
                reply = handler(str(query.key_expr), payload, str(query.parameters))
                if reply is not None:
                    query.reply(key, reply)
            except Exception:
                log.exception("queryable %s failed", key)

        return self._keep(self.session.declare_queryable(key, on_query))

    def answer_later(self, key: str, handler: LaterAnswer) -> Any:
        """Hand every ``get`` on ``key`` to ``handler(key, payload, parameters, reply)``
        on Zenoh's thread; whoever holds ``reply`` completes it later, from any thread
        (the query stays open until then, or until the client's timeout). A handler that
        raises answers an error with its text."""
        def on_query(query: Any) -> None:
            reply = _ZenohReply(query, key)
            try:
                payload = query.payload.to_bytes() if query.payload is not None else None
                handler(str(query.key_expr), payload, str(query.parameters), reply)
            except Exception as exc:
                log.exception("queryable %s failed", key)
                reply.error(str(exc).encode())

        return self._keep(self.session.declare_queryable(key, on_query))

    def get(self, key: str, *, timeout: float = 2.0, payload: bytes | None = None,
            errors: list[bytes] | None = None) -> list[Sample]:
        """The replies to a query; error replies are appended to ``errors`` if given."""
        out = []
        replies = (self.session.get(key, timeout=timeout) if payload is None
                   else self.session.get(key, payload=payload, timeout=timeout))
        for reply in replies:
            if reply.ok is not None:
                out.append(Sample(str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            elif errors is not None and reply.err is not None:
                errors.append(reply.err.payload.to_bytes())
        return out

    def declare_alive(self, key: str) -> Any:
        return self._keep(self.session.liveliness().declare_token(key))

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]:
        return sorted({str(r.ok.key_expr) for r in self.session.liveliness().get(
            key, timeout=timeout) if r.ok is not None})

    def release(self, entity: Any) -> None:
        """Undeclare one thing this bus declared (a publisher, subscriber, channel,
        queryable or liveliness token) before the bus closes: what a service that adds
        and drops parts while it runs (a browser camera that comes and goes) gives back."""
        with self._lock:
            try:
                self._entities.remove(entity)
            except ValueError:
                return  # released already, or the bus closed
        try:
            if isinstance(entity, QueueChannel):
                entity.close()
            else:
                entity.undeclare()
        except Exception:  # the session may be closing
            log.debug("releasing %r failed", entity, exc_info=True)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities, self._entities = self._entities, []
        for entity in reversed(entities):
            try:
                if isinstance(entity, QueueChannel):
                    entity.close()
                else:
                    entity.undeclare()
            except Exception:  # session may already be closing
                pass
        try:
            self.session.close()
        except Exception:
            pass

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------
# In-process (unit tests of service logic only)
# ---------------------------------------------------------------------------------


def _intersects(a: str, b: str) -> bool:
    import zenoh

    return bool(zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)))


class _InProcessReply:
    """A :class:`Reply` that the in-process ``get`` waits on."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.ok_payload: bytes | None = None
        self.err_payload: bytes | None = None

    @property
    def done(self) -> bool:
        return self._event.is_set()

    def ok(self, payload: bytes) -> None:
        if not self._event.is_set():
            self.ok_payload = bytes(payload)
            self._event.set()

    def error(self, payload: bytes) -> None:
        if not self._event.is_set():
            self.err_payload = bytes(payload)
            self._event.set()

    def wait(self, timeout: float) -> bool:
        return self._event.wait(timeout)


class InProcessBus:
    """A synchronous bus inside one process: ``put`` delivers before it returns.

    Samples get a timestamp like Zenoh's (one source, a counter for a clock), so services
    that order or de-duplicate by publication time behave as they do over Zenoh.
    """

    SOURCE = "inprocess"

    def __init__(self) -> None:
        self._subs: list[tuple[str, Callable[[Sample], None]]] = []
        self._queryables: list[tuple[str, Callable[[], bytes | None]]] = []
        self._answerers: list[tuple[str, Answer]] = []
        self._later: list[tuple[str, LaterAnswer]] = []
        self._alive: set[str] = set()
        self._clock = 0
        self._lock = threading.Lock()

    def publisher(self, key: str, *, latest_wins: bool = False, cache: int = 0,
                  cache_bytes: int | None = None) -> Publisher:
        bus = self

        class _Pub:
            def put(self, payload: Payload) -> None:
                bus.put(key, joined(payload))

        return _Pub()

    def put(self, key: str, payload: bytes) -> None:
        with self._lock:
            self._clock += 1
            now = self._clock
        for pattern, deliver in list(self._subs):
            if _intersects(pattern, key):
                deliver(Sample(key, bytes(payload), source=self.SOURCE, time=now))

    def subscribe(self, key: str, callback: Callback) -> Any:
        entry = (key, lambda s: callback(s.key, s.payload))
        self._subs.append(entry)
        return entry

    def subscribe_lazy(self, key: str, callback: LazyCallback) -> Any:
        entry = (key, lambda s: callback(s.key, lambda: s.payload))
        self._subs.append(entry)
        return entry

    def channel(self, key: str, *, latest_wins: bool = False, recover: bool = False,
                history_s: float = 0.0, max_bytes: int = DEFAULT_QUEUE_BYTES,
                accept: Callable[[str], bool] | None = None,
                also: tuple[str, ...] = (), newest_above: int | None = None) -> Channel:
        ch = QueueChannel(name=key, capacity=1 if latest_wins else None, max_bytes=max_bytes)

        def push(sample: Sample) -> None:
            if accept is None or accept(sample.key):
                size = len(sample.payload)
                if newest_above is not None and size >= newest_above:
                    ch.push_newest(sample, lambda: sample.payload, size)
                else:
                    ch.push(sample)

        for expr in (key, *also):
            self._subs.append((expr, push))
        return ch

    def wait_for_subscriber(self, key: str, *, timeout: float = 10.0) -> bool:
        return any(_intersects(pattern, key) for pattern, _ in self._subs)

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any:
        entry = (key, provider)
        self._queryables.append(entry)
        return entry

    def answer(self, key: str, handler: Answer) -> Any:
        entry = (key, handler)
        self._answerers.append(entry)
        return entry

    def answer_later(self, key: str, handler: LaterAnswer) -> Any:
        entry = (key, handler)
        self._later.append(entry)
        return entry

    def get(self, key: str, *, timeout: float = 2.0, payload: bytes | None = None,
            errors: list[bytes] | None = None) -> list[Sample]:
        out = []
        for pattern, provider in self._queryables:
            if _intersects(pattern, key.partition("?")[0]):
                reply = provider()
                if reply is not None:
                    out.append(Sample(pattern, reply))
        base, _, parameters = key.partition("?")
        for pattern, handler in self._answerers:
            if _intersects(pattern, base):
                reply = handler(base, payload, parameters)
                if reply is not None:
                    out.append(Sample(pattern, reply))
        deadline = time.monotonic() + timeout
        for pattern, later in self._later:
            if _intersects(pattern, base):
                pending = _InProcessReply()
                try:
                    later(base, payload, parameters, pending)
                except Exception as exc:
                    pending.error(str(exc).encode())
                if pending.wait(max(0.0, deadline - time.monotonic())):
                    if pending.ok_payload is not None:
                        out.append(Sample(pattern, pending.ok_payload))
                    elif errors is not None and pending.err_payload is not None:
                        errors.append(pending.err_payload)
        return out

    def declare_alive(self, key: str) -> Any:
        self._alive.add(key)
        return key

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]:
        return sorted(k for k in self._alive if _intersects(key, k))

    def release(self, entity: Any) -> None:
        for entries in (self._subs, self._queryables, self._answerers, self._later):
            if entity in entries:
                entries.remove(entity)  # type: ignore[arg-type]
        if isinstance(entity, str):
            self._alive.discard(entity)

    def close(self) -> None:
        self._subs.clear()
        self._queryables.clear()
