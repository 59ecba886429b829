"""``slamlens summary``: what remote viewers draw of the newest state, on request.

It runs beside the estimator (on the robot, where states arrive through shared memory)
and answers the queryable ``robot/R/summary`` with a :class:`~slamlens.common.messages.StateSummary`
of the newest state (``slamlens.common.summary``: the map's blocks, the clustered min / mean / max
of the relative covariances, or the pairs of one cluster or feature, in float32). A viewer
pulls: it asks again when the previous answer arrived, with ``after=SEQ`` — the query is
held until a newer state exists (at most ``hold_s``) — so the rate adapts to its link and
the newest state always wins; nothing queues anywhere (docs/remote_viewers.md).

Nothing heavy runs on a Zenoh thread: the state subscriber only keeps a handle on the
newest sample (its 32 MB are copied only when a summary needs them); the queryable only
parses the parameters (a bad one is answered with an error at once, logged and counted)
and hands the query to the ``summary`` worker, which decodes the newest state, makes (or
takes from its cache) the summary and replies. The estimator never waits for any of it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import msgpack

from slamlens.common.bus import Bus, Reply
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import SCHEMA, SlamState
from slamlens.common.summary import Summariser, SummaryQuery, SummaryQueryError, parse_query
from slamlens.services.slam.settings import SummarySettings

log = logging.getLogger("slamlens.summary")


def error_payload(text: str) -> bytes:
    """The payload of an error reply: ``{"schema": 1, "error": text}`` (docs/protocol.md)."""
    return msgpack.packb({"schema": SCHEMA, "error": text}, use_bin_type=True)


@dataclass
class _Pending:
    query: SummaryQuery
    reply: Reply
    deadline: float  #: time.monotonic() after which it is answered with what there is


class SummaryService:
    """Answers summary queries of one robot from its newest state (module docstring)."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str, settings: SummarySettings) -> None:
        self.robot = robot
        self.settings = settings
        self.summariser = Summariser(cache=settings.cache,
                                     max_group_pairs=settings.max_group_pairs,
                                     max_pairs=settings.max_pairs)
        self.drops = DropCounter(log)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._newest: Callable[[], bytes] | None = None  #: the newest sample, not copied yet
        self._pending: list[_Pending] = []
        self._state: SlamState | None = None
        self._state_bytes = 0
        self.received = 0  #: states seen
        self.decoded = 0  #: states decoded (only those a query needed)
        self.answered = 0  #: summaries replied
        self.refused = 0  #: queries answered with an error
        bus.subscribe_lazy(keys.state(robot), self._on_state)
        bus.answer_later(keys.summary(robot), self._on_query)

    # -- Zenoh threads: store and wake, nothing else -------------------------------------
    def _on_state(self, _key: str, payload: Callable[[], bytes]) -> None:
        with self._lock:
            self._newest = payload
            self.received += 1
        self._wake.set()

    def _on_query(self, _key: str, _payload: bytes | None, parameters: str,
                  reply: Reply) -> None:
        try:
            query = parse_query(parameters)
        except SummaryQueryError as exc:
            self._refuse(reply, str(exc))
            return
        with self._lock:
            if len(self._pending) >= self.settings.max_pending:
                busy = True
            else:
                busy = False
                self._pending.append(_Pending(query, reply,
                                              time.monotonic() + self.settings.hold_s))
        if busy:
            self._refuse(reply, f"summary: busy ({self.settings.max_pending} queries held)")
            return
        self._wake.set()

    def _refuse(self, reply: Reply, text: str) -> None:
        with self._lock:
            self.refused += 1
        self.drops.drop("query", text)
        reply.error(error_payload(text))

    # -- the worker ------------------------------------------------------------------------
    def run(self, stop: threading.Event, *, status_every_s: float = 10.0) -> None:
        """Answer queries until ``stop`` is set."""
        last = time.monotonic()
        while not stop.is_set():
            self._wake.wait(self._next_wait())
            self._wake.clear()
            self.step()
            if time.monotonic() - last >= status_every_s:
                last = time.monotonic()
                log.info("%s", self.status_line())
        with self._lock:
            pending, self._pending = self._pending, []
        for p in pending:
            p.reply.error(error_payload("summary: the service is stopping"))

    def _next_wait(self) -> float:
        with self._lock:
            if not self._pending:
                return 0.5
            return max(0.0, min(0.5, min(p.deadline for p in self._pending)
                                - time.monotonic()))

    def step(self) -> int:
        """Answer every held query that can be answered now; how many were."""
        with self._lock:
            if not self._pending:
                return 0
            newest, self._newest = self._newest, None
        if newest is not None:
            self._decode(newest)
        now = time.monotonic()
        state = self._state
        with self._lock:
            ready = [p for p in self._pending
                     if (state is not None and p.query.newer(state.epoch, state.seq))
                     or now >= p.deadline]
            self._pending = [p for p in self._pending if p not in ready]
        for p in ready:
            if state is None:
                self._refuse(p.reply, f"summary: no state of robot {self.robot} yet")
                continue
            try:
                payload = self.summariser.summary(state, p.query,
                                                  state_bytes=self._state_bytes)
            except SummaryQueryError as exc:
                self._refuse(p.reply, str(exc))
                continue
            except Exception as exc:  # a state the summary cannot handle: say so, go on
                log.exception("summary of seq %d for %s failed", state.seq,
                              p.query.selector())
                self._refuse(p.reply, f"summary: seq {state.seq} could not be summarised "
                                      f"({type(exc).__name__}: {exc})")
                continue
            p.reply.ok(payload)
            with self._lock:
                self.answered += 1
        return len(ready)

    def _decode(self, newest: Callable[[], bytes]) -> None:
        try:
            payload = newest()
            # symmetry is the monitor's business; a summary shows what the estimator sent
            state = SlamState.from_bytes(payload, check_symmetry=False)
        except MessageError as exc:
            self.drops.drop(exc.message_type, str(exc))
            return
        except Exception as exc:  # the sample's buffer went away (session closing)
            self.drops.drop("state", f"unreadable sample: {exc}")
            return
        if state.robot != self.robot:
            self.drops.drop("robot", f"state of robot {state.robot!r} on {self.robot!r}'s key")
            return
        self._state, self._state_bytes = state, len(payload)
        self.decoded += 1

    # -- reporting ---------------------------------------------------------------------
    def status_line(self) -> str:
        s = self._state
        return (f"{self.answered} summaries answered ({self.summariser.made} made, "
                f"{self.summariser.shared} shared), {self.refused} refused; states "
                f"{self.received} received, {self.decoded} decoded; newest seq "
                f"{'-' if s is None else s.seq}")

    def summary(self) -> dict[str, object]:
        return {"answered": self.answered, "made": self.summariser.made,
                "shared": self.summariser.shared, "refused": self.refused,
                "received": self.received, "decoded": self.decoded,
                "dropped": self.drops.total}
