"""The remote viewer's side of the summary stream: pull, one query at a time.

:class:`SummaryPuller` asks the robot's ``summary`` queryable, and asks again as soon as
the answer arrived, with ``after=SEQ;epoch=E`` of the summary it has: the robot holds
that query until a newer state exists (docs/remote_viewers.md). One query is in flight at
a time, so the rate is what the link and the robot sustain, each answer is the newest
state there was when the robot replied, and nothing queues anywhere — no publisher cache,
no socket backlog. An error reply (bad parameters, no state yet) is logged (the first few,
then one in a hundred), counted and retried after ``retry_s``; so is silence (no summary
service, a link cut).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import msgpack

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.messages import peek_fields
from slamlens.common.summary import SummaryQuery

log = logging.getLogger("slamlens.summary")


def error_text(payload: bytes) -> str:
    """The text of an error reply (``{"schema": 1, "error": …}``, or raw bytes)."""
    try:
        raw = msgpack.unpackb(payload, raw=False)
        if isinstance(raw, dict) and isinstance(raw.get("error"), str):
            return raw["error"]
    except Exception:
        pass
    return payload.decode("utf-8", "replace")[:300]


class SummaryPuller:
    """Pulls summaries of ``key`` on its own thread; ``on_summary(payload, received)`` is
    called with each answer (``received``: time.monotonic() when it arrived)."""

    def __init__(self, bus: Bus, key: str, query: SummaryQuery,
                 on_summary: Callable[[bytes, float], None], *, timeout_s: float = 5.0,
                 retry_s: float = 0.5, name: str = "summary-pull") -> None:
        self.bus = bus
        self.key = key
        self._query = query
        self._on_summary = on_summary
        self.timeout_s = timeout_s
        self.retry_s = retry_s
        self._name = name
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._have: tuple[int, int] | None = None  #: (epoch, seq) of the last answer
        self.drops = DropCounter(log)
        self.received = 0  #: answers received
        self.errors = 0  #: error replies
        self.silent = 0  #: queries nobody answered within the timeout
        self.bytes = 0  #: payload bytes received
        self.repeated = 0  #: answers of a state already given (no newer one in the hold)

    @property
    def query(self) -> SummaryQuery:
        with self._lock:
            return self._query

    def set_query(self, query: SummaryQuery) -> None:
        """Ask for something else from the next query on (the current one finishes)."""
        with self._lock:
            if query.answer_key() != self._query.answer_key():
                self._have = None  # another answer: the first one at once, not "after"
            self._query = query

    def selector(self) -> str:
        return self._request()[0]

    def _request(self) -> tuple[str, SummaryQuery, tuple[int, int] | None]:
        """(selector, the answer asked for, the (epoch, seq) it waits to be newer than)."""
        with self._lock:
            q, have = self._query, self._have
        if have is not None:
            q = replace(q, epoch=have[0], after=have[1])
        else:
            q = replace(q, epoch=None, after=None)
        return f"{self.key}?{q.selector()}", q.answer_key(), have

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        """Stop pulling; waits at most ``timeout`` s for a query in flight (the thread is
        a daemon, and closing the bus ends the query)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)

    def pull_once(self) -> bytes | None:
        """One query: the answer's payload (also given to ``on_summary``), or None."""
        errors: list[bytes] = []
        selector, asked, had = self._request()
        try:
            replies = self.bus.get(selector, timeout=self.timeout_s, errors=errors)
        except Exception as exc:  # the session closing, a router away: try again
            self.drops.drop("query", f"get on {self.key} failed: {exc}")
            return None
        if not replies:
            if errors:
                self.errors += 1
                self.drops.drop("summary error", error_text(errors[-1]))
            else:
                self.silent += 1
            return None
        payload = replies[-1].payload
        received = time.monotonic()
        try:
            head = peek_fields(payload, ("epoch", "seq"))
            have = (int(head.get("epoch", 0)), int(head["seq"]))
        except (MessageError, KeyError, TypeError, ValueError) as exc:
            self.drops.drop("summary", f"no seq in the answer: {exc}")
            return None
        with self._lock:
            again = had is not None and have == had  # the hold ran out: the same state
            if self._query.answer_key() == asked:  # (else: asked again at once, anew)
                self._have = have
        self.received += 1
        self.bytes += len(payload)
        if again:  # the hold ran out without a newer state: the robot is idle
            self.repeated += 1
        else:
            self._on_summary(payload, received)
        return payload

    def _loop(self) -> None:
        while not self._stop.is_set():
            if self.pull_once() is None:
                self._stop.wait(self.retry_s)
