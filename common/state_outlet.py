"""Where an estimator's states go out: their publisher, and the answer to a ``get`` (the
estimator service's, and the ROS 2 bridge's for an estimate it imports).

Every state is put through an advanced publisher with a cache (congestion control drop: a
slow subscriber never slows the estimator), and the latest one put is what a ``get`` on the
state key answers (``?header``: only its header, what drivers pace on; docs/protocol.md).

Bursts: the small states of one burst of inputs (at most :data:`BURST_STATES`) are put back
to back when it has been applied, so Zenoh sends them in a few batches instead of one write
each (a put on an idle link costs the publisher several times the CPU of one in a batch,
``benchmarks/bench_put.py``). A state waits at most for the rest of its burst, and only when
inputs queue up — in real time every burst is one input. Large states (a big map's, through
shared memory) go out at once. A ``get`` answers with the state being put or the last one
put: never one older than a subscriber has received, never one still waiting in a burst.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from slamlens.common.bus import BurstPuts, Bus, Payload, joined
from slamlens.common.messages import SlamState

#: at most this many states of one burst of inputs wait to be put back to back
BURST_STATES = 32
#: states of this size and up are put at once (a batch holds 64 kB; a large map's states
#: go through shared memory, and holding them back would only hold their memory)
BURST_BELOW_BYTES = 32 << 10


class StateOutlet:
    """Publishes states on ``key`` and answers a ``get`` on it with the latest put."""

    def __init__(self, bus: Bus, key: str, *, cache: int, cache_bytes: int,
                 header: Callable[[SlamState], bytes]) -> None:
        self._bus = bus
        self._key = key
        self._header_of = header
        self._lock = threading.Lock()
        self._publisher = bus.publisher(key, cache=cache, cache_bytes=cache_bytes)
        #: a burst's small states put back to back; a get answers with the one being put
        self._puts = BurstPuts(self._publisher, limit=BURST_STATES, sent=self._now_gettable,
                               below_bytes=BURST_BELOW_BYTES)
        #: the latest state's encoding in parts (a large map's covariance not copied: it
        #: is joined only when asked for, by a get or a checkpoint), or, once put, what the
        #: publisher sent (a shared-memory buffer or bytes), answered as it is
        self._latest: Any = None
        self._header = b""

    def open(self, first: SlamState) -> None:
        """Answer ``get`` from now on, starting with ``first`` (put at once)."""
        self._latest = first.wire_parts()
        self._header = self._header_of(first)
        self._bus.answer(self._key, self._on_query)
        self._publisher.put(self._latest)

    @property
    def is_open(self) -> bool:
        """Whether :meth:`open` was called: a ``get`` is answered."""
        return self._latest is not None

    @contextmanager
    def burst(self) -> Iterator[None]:
        """States published inside go out back to back at its end (module docstring)."""
        with self._puts.burst():
            yield

    def flush(self) -> None:
        """Put what waits in the current burst now (before a checkpoint that covers it)."""
        self._puts.flush()

    def publish(self, state: SlamState) -> None:
        payload = state.wire_parts()  # the covariance copied once, by the publisher
        sent = self._puts.put(payload, (payload, self._header_of(state)))
        if sent is not None:
            # put at once (a large state): a get answers with what went out — a shared-
            # memory buffer, or bytes — so nothing refers to the covariance's buffer any
            # more and the next predict can patch it in place (Estimator.to_state)
            with self._lock:
                if self._latest is payload:
                    self._latest = sent

    def latest_bytes(self) -> bytes:
        """The latest state put, as bytes (joined once, then kept)."""
        with self._lock:
            latest = self._latest
        if isinstance(latest, list):  # joined once, then kept (it may be asked again)
            whole = joined(latest)
            with self._lock:
                if self._latest is latest:
                    self._latest = whole
            return whole
        if isinstance(latest, bytes):
            return latest
        return latest.to_bytes()  # what the publisher sent (a shared-memory buffer)

    def _on_query(self, key: str, payload: bytes | None, parameters: str) -> Any:
        """The latest state, or with ``?header`` only its header (docs/protocol.md)."""
        if "header" in parameters.split(";"):
            with self._lock:
                return self._header
        with self._lock:
            latest = self._latest
        if isinstance(latest, list):  # parts: joined once, then kept
            return self.latest_bytes()
        return latest  # bytes, or a shared-memory buffer Zenoh answers with, no copy here

    def _now_gettable(self, latest: tuple[Payload, bytes]) -> None:
        """What a ``get`` answers with from now on (a state put, or about to be)."""
        with self._lock:
            self._latest, self._header = latest
