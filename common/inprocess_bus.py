"""The bus inside one process, for unit tests of a service's logic (never across a
network: integration tests use real Zenoh sessions on loopback)."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from slamlens.common.bus import (
    DEFAULT_QUEUE_BYTES,
    Answer,
    Callback,
    Channel,
    LaterAnswer,
    LazyCallback,
    Payload,
    Publisher,
    Sample,
    joined,
)
from slamlens.common.channel import QueueChannel


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
        self._caches: list[deque[Sample]] = []
        self._clock = 0
        self._lock = threading.Lock()

    def publisher(self, key: str, *, latest_wins: bool = False, cache: int = 0,
                  cache_bytes: int | None = None) -> Publisher:
        bus = self
        kept: deque[Sample] | None = deque(maxlen=cache) if cache > 0 else None
        if kept is not None:
            self._caches.append(kept)

        class _Pub:
            def put(self, payload: Payload) -> None:
                sample = bus.put(key, joined(payload))
                if kept is not None:
                    kept.append(sample)

        return _Pub()

    def put(self, key: str, payload: bytes) -> Sample:
        with self._lock:
            self._clock += 1
            now = self._clock
        sample = Sample(key, bytes(payload), source=self.SOURCE, time=now)
        for pattern, deliver in list(self._subs):
            if _intersects(pattern, key):
                deliver(sample)
        return sample

    def cached(self, key: str, *, max_age_s: float | None = None,
               timeout: float = 10.0) -> list[Sample]:
        """What the publishers declared with a cache still hold (every age)."""
        return [s for kept in self._caches for s in kept if _intersects(key, s.key)]

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
                also: tuple[str, ...] = (), newest_above: int | None = None,
                report_misses: bool = False) -> Channel:
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
