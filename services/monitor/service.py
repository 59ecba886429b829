"""The behaviour monitor as a bus service (docs/monitor.md).

It listens to one robot's keys through a single ordered, recovering channel — states,
simulator truth and the camera-tracked pose, in the order they arrive; a state missed under
congestion or a link cut comes back from the estimator's cache — and publishes one
``Health`` per state through an advanced publisher (a viewer that joins late or missed one
recovers it). The channel's callback only queues: the monitor never slows the estimator.
The Healths of a burst of states are put back to back, at most :data:`BURST_HEALTHS` at a
time (one Zenoh batch for many; docs/delivery.md, "Bursts").

Every state is checked, in order. If the monitor ever falls behind, the states waiting
are counted and said in every Health (statistic ``behind``) and in the log, never
skipped silently; states the estimator's cache could no longer give back are counted
(statistic ``lost``), and the checks stay valid across the gap (the Loewner order is
transitive). A state already checked (the same epoch and seq: an estimator that resumed
from a checkpoint publishes again what it published before it died) is skipped. A new
epoch is a new map: the monitor drops the old one and says "map restarted".

States from any estimator are accepted, ours or a third party's; the symmetry check is
the monitor's own (decoding does not reject an asymmetric covariance).
"""

from __future__ import annotations

import logging
import threading
import time

from slamlens.common.bus import BurstPuts, Bus, Sample
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState, Truth
from slamlens.common.verdict import conservative
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.verdict import WORDS

log = logging.getLogger("slamlens.monitor")

#: Health caches this many (docs/delivery.md: at least the last 10 s)
HEALTH_CACHE = 10_000
#: from this many states waiting, the monitor says it is behind
BEHIND_REPORT = 50
#: samples decoded and screened together (a burst taken from the queue, in pieces)
BURST = 256
#: at most this many Healths of a burst wait to be put back to back (one Zenoh batch for
#: many instead of a write each: benchmarks/bench_put.py, docs/delivery.md "Bursts")
BURST_HEALTHS = 32


class MonitorService:
    """Wires a :class:`Monitor` to the bus."""

    def __init__(self, bus: Bus, *, keys: Keys, robot: str,
                 settings: MonitorSettings) -> None:
        self.robot = robot
        self.keys = keys
        self.monitor = Monitor(settings)
        self.drops = DropCounter(log)
        self.checked = 0
        self.violations = 0
        self.duplicates = 0
        self.restarts = 0
        self._skipped = 0  #: states skipped by the burst rule (``sample_above_mb``)
        self._said_sampled = 0.0
        self._said_count = 0  #: sampled_out when it was last logged
        self._sample_above = int(settings.sample_above_mb * 2 ** 20)
        self._position: tuple[int, int] | None = None  #: (epoch, seq) of the last state
        self.verdict = ""  #: the latest Health's verdict ("" before the first state)
        self.verdict_states = {v: 0 for v in WORDS}  #: states checked under each verdict
        #: states "ok" with a NIS window below its band standing (docs/monitor.md)
        self.conservative_states = 0
        self.fault_seen = False  #: the verdict was "fault" at some point
        self._latest: bytes | None = None
        self._lock = threading.Lock()
        self._said_behind = 0.0
        self._waiting = 0  #: samples of the burst being checked still to come
        #: CPU seconds of the checking thread (decode, check, Health) in :meth:`run`; the
        #: rest of the process's CPU is Zenoh's (receiving, queueing, publishing)
        self.worker_cpu_s = 0.0
        self._publisher = bus.publisher(keys.health(robot), cache=HEALTH_CACHE)
        #: a burst's Healths put back to back; a get answers with the one being put, or the last
        self._puts = BurstPuts(self._publisher, limit=BURST_HEALTHS, sent=self._now_gettable)
        # one ordered queue for what it checks, each key subscribed on its own (the router
        # sends nothing else: not the estimator's inputs, not our own health)
        self._newest_above = int(settings.newest_above_mb * 2 ** 20)
        self._large_share = settings.large_share
        self._large_step = False  #: the last step checked a large state
        self._inputs = bus.channel(keys.state(robot), recover=True,
                                   also=(keys.truth(robot), keys.tracked(robot)),
                                   newest_above=self._newest_above)
        bus.serve_latest(keys.health(robot), self.latest_bytes)

    def latest_bytes(self) -> bytes | None:
        with self._lock:
            return self._latest

    @property
    def epoch(self) -> int | None:
        """The epoch of the last state checked (None before the first)."""
        return None if self._position is None else self._position[0]

    @property
    def sampled_out(self) -> int:
        """States skipped to keep up with a large map (never those of a small one): a large
        state replaced by a newer one before its turn (``newest_above_mb``), or skipped
        when the states waiting held more than ``sample_above_mb``."""
        return self._skipped + self._inputs.superseded

    @property
    def behind(self) -> int:
        """Samples received and not yet checked (in the queue, or in the burst taken)."""
        return self._inputs.backlog + self._waiting

    def handle(self, key: str, payload: bytes) -> Health | None:
        """Decode and check (or keep, a truth) one sample."""
        return self._apply(key, self._decode(key, payload))

    def _decode(self, key: str, payload: bytes) -> SlamState | Truth | MessageError | None:
        """The message of one sample; a rejection is returned, to be counted in its turn."""
        leaf = "tracked" if "/tracked/" in key else self.keys.leaf_of(key)
        try:
            if leaf in ("truth", "tracked"):
                return Truth.from_bytes(payload)
            if leaf != "state":
                return None
            return SlamState.from_bytes(payload, check_symmetry=False)
        except MessageError as exc:
            return exc

    def _apply(self, key: str, item: SlamState | Truth | MessageError | None
               ) -> Health | None:
        if item is None:
            return None
        if isinstance(item, MessageError):
            self.drops.drop(item.message_type, f"on {key}: {item}")
            return None
        if isinstance(item, Truth):
            self.monitor.add_truth(item)
            return None
        state = item
        if state.robot != self.robot:
            self.drops.drop("robot", f"state of robot {state.robot!r} on {self.robot!r}'s key")
            return None
        if self._position is not None:
            epoch, seq = self._position
            if state.epoch == epoch and 0 < state.seq <= seq and state.epoch:
                self.duplicates += 1  # already checked (a resumed estimator's replay)
                return None
            if state.epoch != epoch:
                self.restarts += 1
                log.warning("map restarted: epoch %d → %d (seq %d); the old map's baseline "
                            "and evidence are dropped", epoch, state.epoch, state.seq)
                self.monitor.new_map()
        self._position = (state.epoch, state.seq)
        health = self.monitor.check(state, extra_statistics=self._service_statistics())
        self.checked += 1
        self.verdict_states[health.verdict] += 1
        self.conservative_states += conservative(health)
        if health.verdict != self.verdict:
            standing = sorted({v.kind for v in health.standing})
            log.log(logging.INFO if health.verdict == "ok" else logging.WARNING,
                    "verdict %s at seq %d%s%s", WORDS[health.verdict].upper(), health.seq,
                    f" ({', '.join(standing)} standing)" if standing else "",
                    f", suspects {[int(i) for i in health.suspects]}"
                    if health.suspects.size else "")
            self.verdict = health.verdict
            self.fault_seen |= health.verdict == "fault"
        if not health.ok:
            self.violations += len(health.violations)
            if self.violations == len(health.violations):
                log.warning("first violation at seq %d: %s; suspects %s", health.seq,
                            "; ".join(v.detail or v.kind for v in health.violations[:3]),
                            [int(i) for i in health.suspects])
        payload_out = health.to_bytes()
        self._puts.put(payload_out, payload_out)
        return health

    def _now_gettable(self, payload: bytes) -> None:
        """What a ``get`` answers with from now on (a Health put, or about to be)."""
        with self._lock:
            self._latest = payload

    def _service_statistics(self) -> dict[str, float]:
        """What the service knows and the core does not: backlog, losses, restarts."""
        behind = self.behind
        if behind >= BEHIND_REPORT and time.monotonic() - self._said_behind >= 10.0:
            self._said_behind = time.monotonic()
            log.warning("monitor %d states behind the estimator", behind)
        return {"behind": float(behind), "lost": float(self._inputs.lost),
                "restarts": float(self.restarts), "dropped": float(self.drops.total),
                "sampled_out": float(self.sampled_out)}

    def status_line(self) -> str:
        verdict = WORDS[self.verdict] if self.verdict else "no verdict yet"
        return (f"{verdict}: {self.checked} states checked, {self.violations} violations, "
                f"suspects {[int(i) for i in self.monitor.summary.suspects]}, behind "
                f"{self.behind}, lost "
                f"{self._inputs.lost}, {self.duplicates} duplicates, {self.drops.total} "
                "dropped")

    def run(self, stop: threading.Event, *, status_every_s: float = 10.0) -> None:
        """Check states until ``stop`` is set."""
        last = time.monotonic()
        cpu = time.thread_time()
        try:
            while not stop.is_set():
                before = time.thread_time()
                self.step(timeout=0.2)
                if self._large_step:  # a large map: at most large_share of a core
                    spent = time.thread_time() - before
                    stop.wait(spent * (1.0 / self._large_share - 1.0))
                if time.monotonic() - last >= status_every_s:
                    last = time.monotonic()
                    log.info("%s", self.status_line())
        finally:
            self.worker_cpu_s += time.thread_time() - cpu

    def step(self, timeout: float = 0.2) -> int:
        """Check what waits (up to ``timeout`` s for a first sample): everything queued is
        taken as one burst and checked in order, BURST samples at a time, their states
        screened together (:meth:`Monitor.prepare`: the same Health as one by one). If
        what waits is beyond ``sample_above_mb``, jump to the newest state. Returns the
        number of samples handled (0: nothing came)."""
        first = self._inputs.recv(timeout=timeout)
        if first is None:
            self._large_step = False
            return 0
        burst = [first, *self._inputs.take_all()]
        self._large_step = any(len(s.payload) >= self._newest_above for s in burst)
        self._say_sampled()  # large states superseded while waiting
        if sum(len(s.payload) for s in burst[1:]) > self._sample_above:
            self.handle(first.key, first.payload)
            return 1 + self._sample(burst[1:])
        for start in range(0, len(burst), BURST):
            self._check_burst(burst[start:start + BURST], after=len(burst) - start)
        return len(burst)

    def _check_burst(self, samples: list[Sample], *, after: int) -> None:
        """Decode ``samples``, screen their states at once, apply each in order (``after``:
        samples of the whole burst from the first of these on, for ``behind``)."""
        items = [self._decode(s.key, s.payload) for s in samples]
        self.monitor.prepare([x for x in items
                              if isinstance(x, SlamState) and x.robot == self.robot])
        try:
            with self._puts.burst():
                for k, (sample, item) in enumerate(zip(samples, items, strict=True)):
                    self._waiting = after - k - 1
                    self._apply(sample.key, item)
        finally:
            self._waiting = 0

    def _say_sampled(self) -> None:
        """Log the states skipped so far, at the first and then at most once per 10 s."""
        total = self.sampled_out
        if total > self._said_count and (self._said_count == 0
                                         or time.monotonic() - self._said_sampled >= 10.0):
            log.warning("monitor behind on a large map: checking the newest state, skipped "
                        "%d (%d so far); the checks compare across the gap",
                        total - self._said_count, total)
            self._said_sampled, self._said_count = time.monotonic(), total

    def _sample(self, waiting: list[Sample] | None = None) -> int:
        """Too far behind on a large map: take everything waiting, keep the truths, check
        only the newest state (the comparison with the last one checked stays valid)."""
        if waiting is None:
            waiting = self._inputs.take_all()
        states = [s for s in waiting if s.key.endswith("/state")]
        skipped = max(0, len(states) - 1)
        self._skipped += skipped
        self._say_sampled()
        for s in waiting:
            if not s.key.endswith("/state") or s is states[-1]:
                self.handle(s.key, s.payload)
        return len(waiting)

    def summary(self) -> dict[str, object]:
        s = self.monitor.summary
        return {"verdict": self.verdict or "none",
                "verdict_words": WORDS[self.verdict] if self.verdict else "no state checked",
                "states_by_verdict": dict(self.verdict_states),
                "states_ok_with_timid_nis": self.conservative_states,
                "estimator_fault_seen": self.fault_seen, "checked": self.checked,
                "violations": self.violations,
                "suspects": [int(i) for i in s.suspects], "lost": self._inputs.lost,
                "sampled_out": self.sampled_out,
                "duplicates": self.duplicates, "restarts": self.restarts,
                "dropped": self.drops.total, "worker_cpu_s": round(self.worker_cpu_s, 2)}
