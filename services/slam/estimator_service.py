"""The EKF-SLAM estimator as a bus service (SPEC §4, §7, §7a).

Inputs: one recovering channel on the robot's odometry and observations keys (advanced subscribers:
what congestion, a link cut or a router restart made it miss comes back from the drivers'
caches). Its Zenoh callback only queues the sample; one worker thread decodes, puts the
inputs in publication order exactly once (:mod:`slamlens.services.slam.input_order`) and applies
them. After every event applied it publishes one ``SlamState`` through an advanced
publisher with a cache (congestion control drop: a slow subscriber never slows it) and
keeps its bytes as the answer to a ``get``. A liveliness token announces the estimator.

Bursts: the worker takes everything queued at once. The small states of one burst (at most
:data:`BURST_STATES`) are put back to back when it is applied, so Zenoh sends them in a few
batches instead of one write each; a put on an idle link costs the publisher ~6× the CPU
of one in a batch (``benchmarks/bench_put.py``). A state waits at most for the rest of its
burst (≤ ``BURST_STATES`` events), and only when inputs queue up — in real time every burst
is one input. Large states (a big map's, through shared memory) go out at once.

Epochs: a map started from scratch gets a new ``epoch`` (the wall-clock nanoseconds at its
start: unique in practice and increasing); with ``--checkpoint DIR`` the service saves its
whole state there and, started again, resumes the same epoch and seq numbering, asking the
drivers' caches for the inputs published since (:mod:`slamlens.services.slam.checkpoint`).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from slamlens.common.bus import BurstPuts, Bus, Payload, Sample, joined
from slamlens.common.drops import DropCounter
from slamlens.common.errors import EstimationError, MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.services.slam import checkpoint as ckpt
from slamlens.services.slam.ekf import RefusedStepError
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.input_order import Input, InputOrder
from slamlens.services.slam.plausibility import ImplausibleInputError
from slamlens.services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")

_NOISE = ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing")
#: at most this many states of one burst of inputs wait to be put back to back
BURST_STATES = 32
#: states of this size and up are put at once (a batch holds 64 kB; a large map's states
#: go through shared memory, and holding them back would only hold their memory)
BURST_BELOW_BYTES = 32 << 10


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
                                reorder_s=settings.input_reorder_s)
        self._seq = 0
        self._input_stamp = 0.0
        self._said: set[str] = set()  #: refusal reasons already logged (once each)
        self._origin_stamp: float | None = None  #: when the robot stood at the map origin
        self._lock = threading.Lock()
        self._writer: ckpt.CheckpointWriter | None = None
        self._last_checkpoint = time.monotonic()
        self.resumed = False
        self.epoch = new_epoch()
        init: SlamState | None = None
        if settings.checkpoint:
            init = self._resume(settings.checkpoint)
            self._writer = ckpt.CheckpointWriter(settings.checkpoint)
        self._publisher = bus.publisher(keys.state(self.robot), cache=settings.state_cache,
                                        cache_bytes=int(settings.state_cache_mb * 2 ** 20))
        #: a burst's small states put back to back; a get answers with the last one put
        self._puts = BurstPuts(self._publisher, limit=BURST_STATES, sent=self._now_gettable,
                               below_bytes=BURST_BELOW_BYTES)
        # The input channel is declared before the liveliness token, so a driver that
        # waits for the token never publishes into the void; after a resume it also asks
        # the drivers' caches for what was published while the estimator was down.
        # One queue for both input keys (each subscribed on its own, so the router sends
        # nothing else: not the truth, not our own states).
        self._inputs = bus.channel(
            keys.odometry(self.robot), also=(keys.observations(self.robot),), recover=True,
            history_s=settings.input_history_s if self.resumed else 0.0)
        if init is None:
            init = self.estimator.to_state(seq=0, stamp=0.0, step="init", epoch=self.epoch,
                                           input_stamp=0.0)
        #: the latest state's encoding in parts (a large map's covariance not copied: it
        #: is joined only when asked for, by a get or a checkpoint)
        #: (a large state's, once put: what the publisher sent, answered as it is)
        self._latest: Any = init.wire_parts()
        self._header = self._header_of(init)
        bus.answer(keys.state(self.robot), self._on_query)
        self._publisher.put(self._latest)
        bus.declare_alive(keys.estimator_alive(self.robot))

    # -- checkpoints ------------------------------------------------------------------
    def _resume(self, directory: str) -> SlamState | None:
        cp = ckpt.load(directory, self.robot)
        if cp is None:
            log.info("no checkpoint in %s yet: a new map, epoch %d", directory, self.epoch)
            return None
        state = SlamState.from_bytes(cp.state)
        noise = {k: float(getattr(self.settings, k)) for k in _NOISE}
        if cp.noise != noise:
            log.warning("the checkpoint was made with %s, now %s: the map continues with the "
                        "new settings", cp.noise, noise)
        self.estimator.restore(state, next_anonymous_id=cp.next_anonymous_id,
                               linearisation=cp.linearisation)
        self.order.resume(cp.positions)
        self.epoch, self._seq = state.epoch, state.seq
        self._input_stamp = float(state.input_stamp or state.stamp)
        self._origin_stamp = state.origin_stamp
        self.resumed = True
        log.info("resumed epoch %d at seq %d (input stamp %.3f, %d landmarks) from %s",
                 state.epoch, state.seq, state.input_stamp, state.n,
                 ckpt.checkpoint_path(directory, self.robot))
        return state

    def _checkpoint(self) -> ckpt.Checkpoint:
        return ckpt.Checkpoint(
            robot=self.robot, state=self.latest_bytes(), positions=self.order.positions(),
            next_anonymous_id=self.estimator.next_anonymous_id,
            noise={k: float(getattr(self.settings, k)) for k in _NOISE},
            linearisation=self.estimator.linearisation_points())

    def _maybe_checkpoint(self) -> None:
        """A checkpoint if one is due — after the states it covers were put."""
        if self._writer is not None and \
                time.monotonic() - self._last_checkpoint >= self.settings.checkpoint_interval_s:
            self._puts.flush()
            self._last_checkpoint = time.monotonic()
            self._writer.submit(self._checkpoint())

    # -- the event logic ----------------------------------------------------------------
    def latest_bytes(self) -> bytes:
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

    def _header_of(self, state: SlamState) -> bytes:
        """``get state?header``'s answer: what a driver paces on, not the map (and the
        service's counters)."""
        return msgpack.packb({"schema": 1, "robot": state.robot, "seq": state.seq,
                              "stamp": state.stamp, "step": state.step,
                              "epoch": state.epoch, "input_stamp": state.input_stamp,
                              "n": state.n,
                              "origin_stamp": state.origin_stamp,
                              "dropped": self.drops.total, "lost": self.order.stats.lost},
                             use_bin_type=True)

    def _on_query(self, key: str, payload: bytes | None, parameters: str) -> Any:
        """The latest state, or with ``?header`` only its header (SPEC §7: a ``get`` on
        the state key answers the latest state; the header is ours, docs/protocol.md)."""
        if "header" in parameters.split(";"):
            with self._lock:
                return self._header
        with self._lock:
            latest = self._latest
        if isinstance(latest, list):  # parts: joined once, then kept
            return self.latest_bytes()
        return latest  # bytes, or a shared-memory buffer Zenoh answers with, no copy here

    def handle(self, key: str, payload: bytes) -> SlamState | None:
        """Decode and apply one input now (no ordering); the state published, or None."""
        item = self.decode(Sample(key, payload))
        return None if item is None else self.apply(item)

    def decode(self, sample: Sample) -> Input | None:
        """The input a sample carries, or None (counted) if it is not one of ours."""
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
            if isinstance(message, Odometry):
                self.estimator.predict(v=message.v, w=message.w, dt=message.dt,
                                       stamp=message.stamp)
                if self._origin_stamp is None:  # the map origin: where this step began
                    self._origin_stamp = message.stamp - message.dt
                self.stats.odometry += 1
                return self._publish(stamp=message.stamp, step="predict", report=None)
            report = self.estimator.observe(ids=message.ids, ranges=message.ranges,
                                            bearings=message.bearings, stamp=message.stamp)
            if self._origin_stamp is None:
                self._origin_stamp = message.stamp
            self.stats.observation_batches += 1
            return self._publish(stamp=message.stamp, step="update", report=report)
        except (ImplausibleInputError, RefusedStepError) as exc:
            self.stats.refused += 1
            self._say_refused(item.leaf, exc.reason, str(exc))
        except EstimationError as exc:  # the estimator refused the input (NaN, bad control…)
            self.stats.refused += 1
            self.drops.drop(item.leaf, f"refused: {exc}")
        return None

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
        state = self.estimator.to_state(seq=self._seq, stamp=stamp, step=step,
                                        report=report,  # type: ignore[arg-type]
                                        epoch=self.epoch, input_stamp=stamp,
                                        origin_stamp=self._origin_stamp)
        payload = state.wire_parts()  # the covariance copied once, by the publisher
        sent = self._puts.put(payload, (payload, self._header_of(state)))
        if sent is not None:
            # put at once (a large state): a get answers with what went out — a shared-
            # memory buffer, or bytes — so nothing refers to the covariance's buffer any
            # more and the next predict can patch it in place (Estimator.to_state)
            with self._lock:
                if self._latest is payload:
                    self._latest = sent
        self.stats.states += 1
        return state

    def _now_gettable(self, latest: tuple[Payload, bytes]) -> None:
        """What a ``get`` answers with from now on (a state put, or about to be)."""
        with self._lock:
            self._latest, self._header = latest

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
        returns how many. Nothing here holds a state once ``each`` returned: each holds its
        covariance, which the estimator recycles — or, after a predict, patches in place —
        only once nothing holds it (at n = 1000 a burst of 100 states held would be 3 GB,
        each in a new buffer faulted in)."""
        published = 0

        def apply_all(items: list[Input]) -> None:
            nonlocal published
            for item in items:
                state = self.apply(item)
                if state is not None:
                    published += 1
                    each(state)
                    del state  # before the next apply: nothing of ours holds it

        with self._puts.burst():
            for sample in samples:
                item = self.decode(sample)
                if item is not None:
                    apply_all(self.order.offer(item))
                    self._maybe_checkpoint()
            apply_all(self.order.expire())
        self._maybe_checkpoint()
        return published

    def step(self, timeout: float = 0.2) -> int:
        """Take what arrived (waiting up to ``timeout`` s for the first) and apply what is
        in order; returns the number of states published."""
        deadline = self.order.next_deadline()
        if deadline is not None:
            timeout = max(0.0, min(timeout, deadline - time.monotonic()))
        first = self._inputs.recv(timeout=timeout)
        burst = [] if first is None else [first, *self._inputs.take_all()]
        return self._apply_burst(burst, lambda _state: None)

    def status_line(self) -> str:
        o = self.order.stats
        refused = ", ".join(f"{k} {v}" for k, v in sorted(self.estimator.refusals.items()))
        return (f"epoch {self.epoch} seq {self._seq}, {self.estimator.n} landmarks, "
                f"{self.stats.odometry} odometry + {self.stats.observation_batches} "
                f"observation batches applied, backlog {self._inputs.backlog}, "
                f"{o.duplicates} duplicates, {o.lost} lost, {self.drops.total} dropped, "
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
            if self._writer is not None:
                self._writer.close(final=self._checkpoint())

    def summary(self) -> dict[str, object]:
        """What the service did (the final line at exit)."""
        est = self.estimator
        return {"epoch": self.epoch, "seq": self._seq, "landmarks": est.n,
                "resumed": self.resumed, **dataclasses.asdict(self.stats),
                "refused_by": dict(sorted(est.refusals.items())), "gated": est.gated,
                "duplicates": self.order.stats.duplicates, "lost": self.order.stats.lost,
                "dropped": self.drops.total}

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
