"""The EKF-SLAM estimator as a bus service (docs/estimator.md, docs/protocol.md).

Inputs: one advanced subscriber on one key expression covering both input keys
(:meth:`~slamlens.common.keys.Keys.inputs`), so one publishing session's inputs arrive in the
order it published them; what congestion, a link cut or a router restart made it miss comes
back from the drivers' caches, and what cannot come back is reported (sample-miss
detection). Its Zenoh callback only queues the sample; one worker thread decodes, puts the
inputs in publication order exactly once (:mod:`slamlens.services.slam.input_order`) and
applies them. After every event applied it publishes one ``SlamState``
(:mod:`slamlens.common.state_outlet`: an advanced publisher with a cache, the answer to
a ``get``, a burst's states put back to back). A liveliness token announces the estimator.

Epochs: a map started from scratch gets a new ``epoch`` (the wall-clock nanoseconds at its
start: unique in practice and increasing); with ``--checkpoint DIR`` the service saves its
whole state there and, started again, resumes the same epoch and seq numbering
(:mod:`slamlens.services.slam.estimator_checkpoints`), asking the drivers' caches for the
inputs published since: the caches' samples, sorted into each source's order, go first,
what the checkpoint covered counted as duplicates.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from slamlens.common.bus import Bus, Sample
from slamlens.common.drops import DropCounter
from slamlens.common.errors import EstimationError, MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.common.state_header import INPUT_COUNTS, state_header
from slamlens.common.state_outlet import StateOutlet
from slamlens.services.slam.ekf import RefusedStepError
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.estimator_checkpoints import Checkpoints
from slamlens.services.slam.input_order import (
    Input,
    InputOrder,
    Missed,
    sorted_for_replay,
)
from slamlens.services.slam.plausibility import ImplausibleInputError
from slamlens.services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")


@dataclass
class EstimatorStats:
    """Counters the service keeps (and logs at exit)."""

    odometry: int = 0
    observation_batches: int = 0
    states: int = 0
    foreign_robot: int = 0
    refused: int = 0  #: inputs the estimator refused, whatever the reason (no state for them)


def _warm_up(settings: EstimatorSettings) -> None:
    """Run a throwaway estimator through every code path once before serving.

    The first update otherwise pays for lazy imports and BLAS/LAPACK set-up (≈ 0.4 s
    measured), which would stall the first real events and skew their latency.
    """
    est = Estimator(EstimatorSettings(robot=settings.robot))
    est.predict(v=0.1, w=0.1, dt=0.1, stamp=0.1)
    est.observe(ids=[1, 2], ranges=[1.0, 1.5], bearings=[0.3, -0.3], stamp=0.1)
    est.predict(v=0.1, w=0.1, dt=0.1, stamp=0.2)
    report = est.observe(ids=[1, -1], ranges=[0.99, 1.49], bearings=[0.29, -0.31], stamp=0.2)
    state = est.to_state(seq=1, stamp=0.2, step="update", report=report)
    SlamState.from_bytes(state.to_bytes())
    Odometry.from_bytes(Odometry(robot="w", stamp=0.0, dt=0.1, v=0.0, w=0.0).to_bytes())
    Observations.from_bytes(Observations(robot="w", stamp=0.0, ids=np.array([1]),
                                         ranges=np.array([1.0]),
                                         bearings=np.array([0.0])).to_bytes())


def new_epoch() -> int:
    """A new map's epoch: wall-clock nanoseconds (unique in practice, and increasing)."""
    return time.time_ns()


class EstimatorService:
    """Wires an :class:`Estimator` to the bus; ``handle`` is the whole event logic."""

    def __init__(self, bus: Bus, *, keys: Keys, settings: EstimatorSettings) -> None:
        _warm_up(settings)
        self.robot = settings.robot
        self.keys = keys
        self.settings = settings
        self.estimator = Estimator(settings)
        self.stats = EstimatorStats()
        self.drops = DropCounter(log)
        self.order = InputOrder(gap_wait_s=settings.input_gap_wait_s,
                                reorder_s=settings.input_reorder_s,
                                sources=settings.input_sources)
        self._seq = 0
        self._input_stamp = 0.0
        self._said: set[str] = set()  #: refusal reasons already logged (once each)
        self._origin_stamp: float | None = None  #: when the robot stood at the map origin
        self.resumed = False
        self.epoch = new_epoch()
        #: resume and checkpoints (None without ``--checkpoint DIR``)
        self.checkpoints = (Checkpoints(settings, self.estimator, self.order)
                            if settings.checkpoint else None)
        init = None if self.checkpoints is None else \
            self.checkpoints.resume(epoch=self.epoch)
        if init is not None:  # the same epoch and seq numbering go on
            self.epoch, self._seq = init.epoch, init.seq
            self._input_stamp = float(init.input_stamp or init.stamp)
            self._origin_stamp = init.origin_stamp
            self.resumed = True
        self._out = StateOutlet(bus, keys.state(self.robot), cache=settings.state_cache,
                                cache_bytes=int(settings.state_cache_mb * 2 ** 20),
                                header=self._header_of)
        # The input channel is declared before the liveliness token, so a driver that
        # waits for the token never publishes into the void. One subscriber on one key
        # expression for both input keys (and nothing else: not the truth, not our own
        # states): one session's inputs arrive in publication order. After a resume the
        # drivers' caches are asked for what was published meanwhile — after the channel
        # exists, so nothing falls between the two (what both bring is a duplicate).
        self._inputs = bus.channel(keys.inputs(self.robot), recover=True, report_misses=True)
        #: the caches' replay, applied before the channel's first sample (resume only)
        self._replay: list[Sample] = (
            bus.cached(keys.inputs(self.robot), max_age_s=settings.input_history_s)
            if self.resumed else [])
        if init is None:
            init = self.estimator.to_state(seq=0, stamp=0.0, step="init", epoch=self.epoch,
                                           input_stamp=0.0)
        self._out.open(init)
        bus.declare_alive(keys.estimator_alive(self.robot))

    def _maybe_checkpoint(self) -> None:
        if self.checkpoints is not None:
            self.checkpoints.maybe_write(self._out)

    # -- the event logic ----------------------------------------------------------------
    def _header_of(self, state: SlamState) -> bytes:
        """``get state?header``'s answer: what a driver paces on, not the map (and the
        service's counters)."""
        return state_header(state, {"dropped": self.drops.total, **self.input_counts()})

    def latest_bytes(self) -> bytes:
        """The latest state published, as bytes."""
        return self._out.latest_bytes()

    def input_counts(self) -> dict[str, int]:
        """What the input order did, as every report names it (docs/protocol.md)."""
        return {name: getattr(self.order.stats, name) for name in INPUT_COUNTS}

    def handle(self, key: str, payload: bytes) -> SlamState | None:
        """Decode and apply one input now (no ordering); the state published, or None."""
        item = self.decode(Sample(key, payload))
        return self.apply(item) if isinstance(item, Input) else None

    def decode(self, sample: Sample) -> Input | Missed | None:
        """The input a sample carries (or Zenoh's report of missed inputs), or None
        (counted) if it is not one of ours."""
        if sample.missed:
            return Missed(sample.source, sample.missed)
        leaf = self.keys.leaf_of(sample.key)
        if leaf not in ("odometry", "observations"):
            return None  # truth, state, health… share the prefix; not ours to apply
        try:
            message: Odometry | Observations = (
                Odometry.from_bytes(sample.payload) if leaf == "odometry"
                else Observations.from_bytes(sample.payload))
        except MessageError as exc:
            self.drops.drop(exc.message_type, f"on {sample.key}: {exc}")
            return None
        if message.robot != self.robot:
            self.stats.foreign_robot += 1
            self.drops.drop("robot", f"message for robot {message.robot!r} on "
                                     f"{self.robot!r}'s key")
            return None
        return Input(leaf, message, source=sample.source, time=sample.time)

    def apply(self, item: Input) -> SlamState | None:
        """Fold one input into the map and publish the state (None if refused)."""
        message = item.message
        try:
            report = self.estimator.apply(message)
        except (ImplausibleInputError, RefusedStepError) as exc:
            self.stats.refused += 1
            self._say_refused(item.leaf, exc.reason, str(exc))
            return None
        except EstimationError as exc:  # the estimator refused the input (NaN, bad control…)
            self.stats.refused += 1
            self.drops.drop(item.leaf, f"refused: {exc}")
            return None
        odometry = isinstance(message, Odometry)
        if self._origin_stamp is None:  # the map origin: where the first input's step began
            self._origin_stamp = message.stamp - message.dt if odometry else message.stamp
        if odometry:
            self.stats.odometry += 1
        else:
            self.stats.observation_batches += 1
        return self._publish(stamp=message.stamp, step="predict" if odometry else "update",
                             report=report)

    def _say_refused(self, leaf: str, reason: str, detail: str) -> None:
        """One log line per reason (the rest are counted: ``status()``, the final line)."""
        if reason in self._said:
            return
        self._said.add(reason)
        last = self.estimator.last_refusal
        what = f" (the input: {last.input} at stamp {last.stamp!r})" if last else ""
        log.warning("refused %s (%s): %s%s; further %s refusals are counted, not logged",
                    leaf, reason, detail, what, reason)

    def _publish(self, *, stamp: float, step: str, report: object) -> SlamState:
        self._seq += 1
        self._input_stamp = stamp
        counts = {f"inputs.{k}": float(v) for k, v in self.input_counts().items()}
        state = self.estimator.to_state(seq=self._seq, stamp=stamp, step=step,
                                        report=report,  # type: ignore[arg-type]
                                        epoch=self.epoch, input_stamp=stamp,
                                        origin_stamp=self._origin_stamp, counts=counts)
        self._out.publish(state)
        self.stats.states += 1
        return state

    # -- the worker -----------------------------------------------------------------
    def ingest(self, sample: Sample | None) -> list[SlamState]:
        """One arrived sample (or None: only the gap timers) through decoding and the
        ordering; applies what is ready and returns the states published."""
        return self.ingest_burst([] if sample is None else [sample])

    def ingest_burst(self, samples: list[Sample]) -> list[SlamState]:
        """Samples that arrived together, in arrival order, through decoding and the
        ordering (then the gap timers); applies what is ready, puts the burst's states
        back to back (module docstring) and returns them. A checkpoint due in the middle
        is written then, after the states it covers were put."""
        states: list[SlamState] = []
        self._apply_burst(samples, states.append)
        return states

    def _apply_burst(self, samples: list[Sample], each: Callable[[SlamState], None]) -> int:
        """Apply what ``samples`` make ready, handing each state published to ``each``;
        returns how many."""
        return self._apply_items([self.decode(s) for s in samples], each)

    def _apply_items(self, items: Iterable[Input | Missed | None],
                     each: Callable[[SlamState], None]) -> int:
        """Apply what ``items`` make ready, in order, handing each state published to
        ``each``; returns how many. Nothing here holds a state once ``each`` returned: each
        holds its covariance, which the estimator recycles — or, after a predict, patches
        in place — only once nothing holds it (at n = 1000 a burst of 100 states held would
        be 3 GB, each in a new buffer faulted in)."""
        published = 0

        def apply_all(ready: list[Input]) -> None:
            nonlocal published
            for item in ready:
                state = self.apply(item)
                if state is not None:
                    published += 1
                    each(state)
                    del state  # before the next apply: nothing of ours holds it

        with self._out.burst():
            for item in items:
                if isinstance(item, Missed):
                    apply_all(self.order.missed(item))
                elif item is not None:
                    apply_all(self.order.offer(item))
                    self._maybe_checkpoint()
            apply_all(self.order.expire())
        self._maybe_checkpoint()
        return published

    def replay_cached(self) -> int:
        """Apply what the drivers' caches held at a resume, each source in its own order
        (once; :meth:`step` does it first). Returns the number of states published."""
        replay, self._replay = self._replay, []
        ordered = sorted_for_replay(x for x in map(self.decode, replay) if isinstance(x, Input))
        log.info("replaying %d cached inputs of %d publisher sample(s) after the resume",
                 len(ordered), len(replay))
        return self._apply_items(ordered, lambda _state: None)

    def step(self, timeout: float = 0.2) -> int:
        """Take what arrived (waiting up to ``timeout`` s for the first) and apply what is
        in order; returns the number of states published."""
        if self._replay:
            return self.replay_cached()
        deadline = self.order.next_deadline()
        if deadline is not None:
            timeout = max(0.0, min(timeout, deadline - time.monotonic()))
        first = self._inputs.recv(timeout=timeout)
        burst = [] if first is None else [first, *self._inputs.take_all()]
        return self._apply_burst(burst, lambda _state: None)

    @property
    def waiting_for_sources(self) -> str:
        """What the estimator waits for before applying anything, or "" (several input
        sessions expected and not all heard yet)."""
        seen, expected = self.order.sources_seen, self.settings.input_sources
        return (f"waiting for {expected} input sessions, {seen} heard"
                if 1 < expected and seen < expected else "")

    def status_line(self) -> str:
        o = self.order.stats
        refused = ", ".join(f"{k} {v}" for k, v in sorted(self.estimator.refusals.items()))
        return (f"epoch {self.epoch} seq {self._seq}, {self.estimator.n} landmarks, "
                f"{self.stats.odometry} odometry + {self.stats.observation_batches} "
                f"observation batches applied, backlog {self._inputs.backlog}, "
                f"inputs {o.duplicates} duplicates, {o.late} late, {o.lost} lost, "
                f"{o.waited} waited, {o.reordered} reordered, {self.drops.total} dropped, "
                f"{self.stats.refused} refused{f' ({refused})' if refused else ''}, "
                f"{self.estimator.gated} gated")

    def run(self, stop: threading.Event, *, status_every_s: float = 10.0) -> None:
        """Apply events until ``stop`` is set, then write a last checkpoint."""
        last = time.monotonic()
        try:
            while not stop.is_set():
                self.step()
                if time.monotonic() - last >= status_every_s:
                    last = time.monotonic()
                    log.info("%s", self.status_line())
        finally:
            if self.checkpoints is not None:
                self.checkpoints.close(self._out)

    def summary(self) -> dict[str, object]:
        """What the service did (the final line at exit)."""
        est = self.estimator
        return {"epoch": self.epoch, "seq": self._seq, "landmarks": est.n,
                "resumed": self.resumed, **dataclasses.asdict(self.stats),
                "refused_by": dict(sorted(est.refusals.items())), "gated": est.gated,
                **self.input_counts(), "dropped": self.drops.total}

    def status(self) -> dict[str, object]:
        """What ``slamlens status`` (or anyone) can read about this estimator: the
        :meth:`summary` plus the inputs refused by reason, the last refusal and the
        plausibility bounds in force. Thread-safe to call from another thread (a snapshot
        of counters; plain reads)."""
        est = self.estimator
        last = est.last_refusal
        bounds = dataclasses.asdict(est.gates.bounds)
        return {**self.summary(), "input_stamp": self._input_stamp,
                "refused_updates": est.refused_updates, "stamp_resyncs": est.gates.resyncs,
                "last_refused": None if last is None else dataclasses.asdict(last),
                "bounds": bounds}

