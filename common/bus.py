"""The small bus interface every service talks to, over Zenoh or in-process.

Services never touch ``zenoh`` directly: they take a :class:`Bus`. :class:`ZenohBus` is the
real transport; :class:`InProcessBus` exists only for pure unit tests of a service's logic
(integration tests always use real Zenoh sessions on loopback).

Delivery kinds (STYLE: latest-wins for frames, a queryable for the latest state, reliable
in-order delivery for estimator input):

* ``publisher(key)`` is reliable and blocks under congestion (nothing lost);
  ``publisher(key, latest_wins=True)`` drops under congestion (camera frames).
* ``channel(key)`` is one ordered FIFO queue for everything matching ``key``: events are
  received in publication order by whoever calls ``recv`` (no racing callbacks); an
  ``accept(key)`` filter drops unwanted keys before their payload is copied;
  ``channel(key, latest_wins=True)`` keeps only the newest sample, and
  ``channel(key, drop_oldest=True)`` keeps the newest ``capacity`` samples (a consumer
  that tolerates gaps never slows the publisher).
* ``serve_latest(key, provider)`` answers ``get`` with whatever ``provider()`` returns now.
"""

from __future__ import annotations

import atexit
import logging
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

log = logging.getLogger(__name__)

Callback = Callable[[str, bytes], None]


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


class Publisher(Protocol):
    def put(self, payload: bytes) -> None: ...


class Channel(Protocol):
    def recv(self, timeout: float | None = None) -> Sample | None:
        """Next sample, or None after ``timeout`` seconds (or when closed)."""
        ...

    def close(self) -> None: ...


class Bus(Protocol):
    """What a service needs from the transport."""

    def publisher(self, key: str, *, latest_wins: bool = False) -> Publisher: ...

    def subscribe(self, key: str, callback: Callback) -> Any: ...

    def channel(self, key: str, *, latest_wins: bool = False, capacity: int = 4096,
                drop_oldest: bool = False,
                accept: Callable[[str], bool] | None = None) -> Channel: ...

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any: ...

    def get(self, key: str, *, timeout: float = 2.0) -> list[Sample]: ...

    def declare_alive(self, key: str) -> Any: ...

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]: ...

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


class QueueChannel:
    """An in-order queue of samples fed by one subscriber callback.

    ``recv`` wakes the moment a sample arrives (no polling). When full, ``push`` either
    blocks the feeding thread — backpressure through Zenoh to the publisher, nothing lost
    — or, with ``drop_oldest``, discards the oldest sample (capacity 1 = latest wins).
    """

    def __init__(self, *, capacity: int, drop_oldest: bool) -> None:
        self._items: deque[Sample] = deque()
        self._capacity = max(1, capacity)
        self._drop_oldest = drop_oldest
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0
        self._on_close: Callable[[], None] | None = None

    def push(self, sample: Sample) -> None:
        with self._cond:
            while len(self._items) >= self._capacity and not self._closed:
                if self._drop_oldest:
                    self._items.popleft()
                    self.dropped += 1
                else:
                    self._cond.wait(0.5)
            if self._closed:
                return
            self._items.append(sample)
            self._cond.notify_all()

    def recv(self, timeout: float | None = None) -> Sample | None:
        with self._cond:
            if not self._cond.wait_for(lambda: self._items or self._closed, timeout):
                return None
            if not self._items:
                return None
            sample = self._items.popleft()
            self._cond.notify_all()
            return sample

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._items.clear()
            self._cond.notify_all()
        if self._on_close is not None:
            try:
                self._on_close()
            except Exception:  # already gone with the session
                pass


class _ZenohPublisher:
    def __init__(self, publisher: Any) -> None:
        self._pub = publisher

    def put(self, payload: bytes) -> None:
        self._pub.put(payload)


class ZenohBus:
    """A :class:`Bus` on one Zenoh session; closes everything it declared on ``close``."""

    def __init__(self, session: Any) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
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

    def publisher(self, key: str, *, latest_wins: bool = False) -> Publisher:
        z = self._zenoh
        if latest_wins:
            pub = self.session.declare_publisher(
                key, congestion_control=z.CongestionControl.DROP,
                reliability=z.Reliability.BEST_EFFORT, express=True)
        else:
            pub = self.session.declare_publisher(
                key, congestion_control=z.CongestionControl.BLOCK,
                reliability=z.Reliability.RELIABLE)
        self._keep(pub)
        return _ZenohPublisher(pub)

    def subscribe(self, key: str, callback: Callback) -> Any:
        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # never let a callback kill zenoh's thread silently
                log.exception("subscriber callback for %s failed", key)

        return self._keep(self.session.declare_subscriber(key, on_sample))

    def channel(self, key: str, *, latest_wins: bool = False, capacity: int = 4096,
                drop_oldest: bool = False,
                accept: Callable[[str], bool] | None = None) -> Channel:
        ch = QueueChannel(capacity=1 if latest_wins else capacity,
                          drop_oldest=latest_wins or drop_oldest)

        def on_sample(sample: Any) -> None:
            sample_key = str(sample.key_expr)
            if accept is None or accept(sample_key):  # filter before copying the payload
                ch.push(Sample(sample_key, sample.payload.to_bytes()))

        sub = self.session.declare_subscriber(key, on_sample)
        ch._on_close = sub.undeclare
        self._keep(ch)
        return ch

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any:
        def on_query(query: Any) -> None:
            try:
                payload = provider()
                if payload is not None:
                    query.reply(key, payload)
            except Exception:
                log.exception("queryable %s failed", key)

        return self._keep(self.session.declare_queryable(key, on_query))

    def get(self, key: str, *, timeout: float = 2.0) -> list[Sample]:
        out = []
        for reply in self.session.get(key, timeout=timeout):
            if reply.ok is not None:
                out.append(Sample(str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
        return out

    def declare_alive(self, key: str) -> Any:
        return self._keep(self.session.liveliness().declare_token(key))

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]:
        return sorted({str(r.ok.key_expr) for r in self.session.liveliness().get(
            key, timeout=timeout) if r.ok is not None})

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


class InProcessBus:
    """A synchronous bus inside one process: ``put`` delivers before it returns."""

    def __init__(self) -> None:
        self._subs: list[tuple[str, Callable[[Sample], None]]] = []
        self._queryables: list[tuple[str, Callable[[], bytes | None]]] = []
        self._alive: set[str] = set()

    def publisher(self, key: str, *, latest_wins: bool = False) -> Publisher:
        bus = self

        class _Pub:
            def put(self, payload: bytes) -> None:
                bus.put(key, payload)

        return _Pub()

    def put(self, key: str, payload: bytes) -> None:
        for pattern, deliver in list(self._subs):
            if _intersects(pattern, key):
                deliver(Sample(key, bytes(payload)))

    def subscribe(self, key: str, callback: Callback) -> Any:
        entry = (key, lambda s: callback(s.key, s.payload))
        self._subs.append(entry)
        return entry

    def channel(self, key: str, *, latest_wins: bool = False, capacity: int = 4096,
                drop_oldest: bool = False,
                accept: Callable[[str], bool] | None = None) -> Channel:
        ch = QueueChannel(capacity=1 if latest_wins else capacity,
                          drop_oldest=latest_wins or drop_oldest)

        def push(sample: Sample) -> None:
            if accept is None or accept(sample.key):
                ch.push(sample)

        self._subs.append((key, push))
        return ch

    def serve_latest(self, key: str, provider: Callable[[], bytes | None]) -> Any:
        entry = (key, provider)
        self._queryables.append(entry)
        return entry

    def get(self, key: str, *, timeout: float = 2.0) -> list[Sample]:
        out = []
        for pattern, provider in self._queryables:
            if _intersects(pattern, key):
                payload = provider()
                if payload is not None:
                    out.append(Sample(pattern, payload))
        return out

    def declare_alive(self, key: str) -> Any:
        self._alive.add(key)
        return key

    def alive(self, key: str, *, timeout: float = 2.0) -> list[str]:
        return sorted(k for k in self._alive if _intersects(key, k))

    def close(self) -> None:
        self._subs.clear()
        self._queryables.clear()
