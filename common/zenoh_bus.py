"""The bus on a Zenoh session (:class:`~slamlens.common.bus.Bus`, docs/delivery.md)."""

from __future__ import annotations

import atexit
import logging
import threading
import weakref
from collections.abc import Callable, Sequence
from typing import Any

from slamlens.common.bus import (
    DEFAULT_QUEUE_BYTES,
    Answer,
    Callback,
    Channel,
    LaterAnswer,
    LazyCallback,
    Publisher,
    Sample,
)
from slamlens.common.channel import QueueChannel
from slamlens.common.zenoh_publishing import (
    HEARTBEAT_S,
    CachingPublisher,
    ShmPool,
    ZenohPublisher,
    wait_matching,
)

log = logging.getLogger("slamlens.common.bus")


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


def _sample_of(zsample: Any, key: str | None = None, *, copy: bool = True) -> Sample:
    """A :class:`Sample` from a ``zenoh.Sample`` (payload copied out of Zenoh's buffer;
    left empty with ``copy=False``)."""
    payload = zsample.payload.to_bytes() if copy else b""
    ts = zsample.timestamp
    if ts is None:
        return Sample(key or str(zsample.key_expr), payload)
    return Sample(key or str(zsample.key_expr), payload,
                  source=str(ts.get_id()), time=int(str(ts.get_time_as_ntp64())))  # raw u64


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


def _let_go(entity: Any) -> None:
    """Close a queue channel or undeclare a Zenoh entity; a failure (the session may be
    closing) is logged at debug level, never raised: letting go is best effort."""
    try:
        if isinstance(entity, QueueChannel):
            entity.close()
        else:
            entity.undeclare()
    except Exception:
        log.debug("letting go of %r failed", entity, exc_info=True)


class ZenohBus:
    """A :class:`Bus` on one Zenoh session; closes everything it declared on ``close``."""

    def __init__(self, session: Any, *, off_host: Sequence[str] = ()) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        #: the session's connect endpoints that leave this host (a cache's warning)
        self._off_host = tuple(off_host)
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
            out = ZenohPublisher(self.session.declare_publisher(
                key, congestion_control=z.CongestionControl.DROP,
                reliability=z.Reliability.BEST_EFFORT, express=True))
        elif cache > 0:
            import zenoh.ext as zext

            self._warn_off_host(key)

            def declare(samples: int) -> Any:
                return zext.declare_advanced_publisher(
                    self.session, key, congestion_control=z.CongestionControl.DROP,
                    reliability=z.Reliability.RELIABLE,
                    cache=zext.CacheConfig(int(samples)),
                    sample_miss_detection=zext.MissDetectionConfig(
                        heartbeat=HEARTBEAT_S, sporadic_heartbeat=None),
                    publisher_detection=True)

            out = CachingPublisher(declare, samples=cache, cache_bytes=cache_bytes,
                                    pool=self.shm)
        else:
            out = ZenohPublisher(self.session.declare_publisher(
                key, congestion_control=z.CongestionControl.DROP,
                reliability=z.Reliability.RELIABLE), self.shm)
        self._keep(out)
        return out

    def _warn_off_host(self, key: str) -> None:
        """One warning, at the first cache, for a session connected straight off this host."""
        if not self._off_host:
            return
        log.warning("%s: this session connects straight to %s, off this host: a publisher "
                    "with a cache then waits while a subscriber recovers across a slow link "
                    "(zenoh-ext answers under the cache's lock); connect to a router on this "
                    "host and link that router instead (docs/delivery.md)",
                    key, ", ".join(self._off_host))
        self._off_host = ()

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
                also: tuple[str, ...] = (), newest_above: int | None = None,
                report_misses: bool = False) -> Channel:
        """One ordered queue for ``key`` and the key expressions ``also`` (module
        docstring); ``accept(key)`` filters samples before their payload is copied. A
        payload of at least ``newest_above`` bytes stays in Zenoh's buffer until taken, and
        only the newest of its key waits (:meth:`QueueChannel.push_newest`). With
        ``report_misses`` (and ``recover``) Zenoh's reports of samples missed for good are
        queued among the samples, as :attr:`Sample.missed`.

        Only samples of one subscriber arrive in the order they were published: a
        consumer that needs two keys in publication order asks for one key expression
        covering both, not ``also`` (each of its subscribers has its own thread)."""
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
                misses = sub.sample_miss_listener(
                    lambda miss: self._missed(ch, miss, report_misses))
                ch._on_close.append(sub.undeclare)
                ch._on_close.append(misses.undeclare)
            else:
                sub = self.session.declare_subscriber(expr, on_sample)
                ch._on_close.append(sub.undeclare)
        self._keep(ch)
        return ch

    @staticmethod
    def _missed(ch: QueueChannel, miss: Any, report: bool) -> None:
        """A sample-miss report of an advanced subscriber (on Zenoh's thread)."""
        ch.count_lost(int(miss.nb))
        if report:
            ch.push(Sample("", b"", source=str(miss.source.zid), missed=int(miss.nb)))

    def cached(self, key: str, *, max_age_s: float | None = None,
               timeout: float = 10.0) -> list[Sample]:
        """What the advanced publishers on ``key`` still hold in their caches (the
        queryables ``zenoh.ext`` declares under ``KEY/@adv/**``), each sample with its
        timestamp, publisher by publisher; only those published in the last ``max_age_s``
        seconds if given. Returns when every cache answered (or after ``timeout``)."""
        import zenoh

        selector = f"{key}/@adv/**"
        if max_age_s is not None:
            selector += f"?_time=[now(-{float(max_age_s)}s)..]"
        out = []
        for reply in self.session.get(selector, target=zenoh.QueryTarget.ALL,
                                      consolidation=zenoh.ConsolidationMode.NONE,
                                      accept_replies=zenoh.ReplyKeyExpr.ANY,
                                      timeout=timeout):
            if reply.ok is not None:
                out.append(_sample_of(reply.ok))
        return out

    def wait_for_subscriber(self, key: str, *, timeout: float = 10.0) -> bool:
        """Wait until some subscriber matches ``key`` (Zenoh matching status): what a
        publisher that must not publish into the void waits on."""
        import zenoh

        probe = self.session.declare_publisher(key)
        try:
            return wait_matching(probe, timeout)
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
        with self._lock:
            try:
                self._entities.remove(entity)
            except ValueError:
                return  # released already, or the bus closed
        _let_go(entity)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities, self._entities = self._entities, []
        for entity in reversed(entities):
            _let_go(entity)
        try:
            self.session.close()
        except Exception:
            pass

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
