"""The estimator service's logic in-process (InProcessBus): order, exactly once, checkpoints.

What crosses a real network is tested in tests/integration and tests/system; here the
service's decisions are checked against an estimator fed the same inputs directly.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable

import numpy as np
import pytest

from slamlens.common.bus import Sample
from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.common.state_outlet import BURST_STATES
from slamlens.services.slam import checkpoint as ckpt
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.estimator_service import EstimatorService
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

KEYS = Keys("t")
ROBOT = "r1"


def _inputs(limit: int = 400) -> list[tuple[str, bytes]]:
    """The paper run's first ``limit`` inputs as (key, payload), numbered like a driver."""
    sim = Simulator(load_world("paper"), robot=ROBOT, seed=3)
    out = []
    seq = itertools.count(1)
    for m in sim.events():
        if isinstance(m, Odometry):
            out.append((KEYS.odometry(ROBOT), dataclasses.replace(m, input_seq=next(seq))))
        elif isinstance(m, Observations):
            out.append((KEYS.observations(ROBOT), dataclasses.replace(m, input_seq=next(seq))))
        if len(out) == limit:
            break
    return [(k, m.to_bytes()) for k, m in out]


def _sample(key: str, payload: bytes, t: int) -> Sample:
    return Sample(key, payload, source="driver", time=t)


def _direct(inputs: list[tuple[str, bytes]], settings: EstimatorSettings,
            after_each: Callable[[Estimator], None] | None = None) -> Estimator:
    """An estimator fed ``inputs`` straight, in order (``after_each`` sees it after each)."""
    est = Estimator(settings)
    for key, payload in inputs:
        if key.endswith("odometry"):
            o = Odometry.from_bytes(payload)
            est.predict(v=o.v, w=o.w, dt=o.dt, stamp=o.stamp)
        else:
            b = Observations.from_bytes(payload)
            est.observe(ids=b.ids, ranges=b.ranges, bearings=b.bearings, stamp=b.stamp)
        if after_each is not None:
            after_each(est)
    return est


def _service(settings: EstimatorSettings) -> tuple[InProcessBus, EstimatorService, list]:
    bus = InProcessBus()
    states: list[SlamState] = []
    bus.subscribe(KEYS.state(ROBOT), lambda k, p: states.append(SlamState.from_bytes(p)))
    return bus, EstimatorService(bus, keys=KEYS, settings=settings), states


def test_shuffled_and_repeated_inputs_give_the_in_order_result() -> None:
    settings = EstimatorSettings(robot=ROBOT)
    inputs = _inputs(300)
    _, service, states = _service(settings)
    rng = np.random.default_rng(0)
    # deliver in blocks whose order is scrambled (as recoveries from the drivers' caches
    # would), and every sample twice; the driver's first input arrives first (a source
    # starts where it is first heard)
    arrivals = []
    for start in range(0, len(inputs), 10):
        block = list(enumerate(inputs[start:start + 10], start))
        rng.shuffle(block)
        if start == 0:
            block.sort(key=lambda b: b[0] != 0)
        arrivals += block + block[:3]
    for t, (key, payload) in arrivals:
        service.ingest(_sample(key, payload, t))
    final = states[-1]
    expected = _direct(inputs, settings)
    assert final.seq == len(inputs) and service.order.stats.duplicates == 3 * 30
    assert [s.seq for s in states] == list(range(len(inputs) + 1))  # init, then one each
    np.testing.assert_array_equal(final.covariance, expected.covariance)
    np.testing.assert_array_equal(final.pose, expected.pose)


def test_a_burst_is_put_back_to_back_in_order_and_get_answers_the_state_seen() -> None:
    """A get made by a subscriber as it receives state N answers N: never an older state
    (a third-party client that saw N and then asked must not get less), never a state of
    the burst still waiting to be put."""
    settings = EstimatorSettings(robot=ROBOT)
    inputs = _inputs(100)
    bus = InProcessBus()
    service = EstimatorService(bus, keys=KEYS, settings=settings)
    put: list[int] = []
    answered: list[tuple[int, int]] = []  # (seq being put, seq a get answers with then)
    made_by_then: list[int] = []  # the newest state made when each state was put

    def on_state(_key: str, payload: bytes) -> None:
        seq = SlamState.from_bytes(payload).seq
        put.append(seq)
        made_by_then.append(service._seq)
        replies = bus.get(KEYS.state(ROBOT))
        answered.append((seq, SlamState.from_bytes(replies[0].payload).seq))

    bus.subscribe(KEYS.state(ROBOT), on_state)
    made = service.ingest_burst([_sample(k, p, t) for t, (k, p) in enumerate(inputs)])
    assert [s.seq for s in made] == list(range(1, 101))
    assert put == list(range(1, 101))  # every state once, in order
    assert answered == [(seq, seq) for seq in range(1, 101)]
    # held for the burst: each state went out once its group of BURST_STATES was made
    assert made_by_then == [min(100, -(-seq // BURST_STATES) * BURST_STATES)
                            for seq in range(1, 101)]
    assert SlamState.from_bytes(bus.get(KEYS.state(ROBOT))[0].payload).seq == 100
    expected = _direct(inputs, settings)
    np.testing.assert_array_equal(made[-1].covariance, expected.covariance)


@pytest.mark.parametrize("linearisation", ["standard", "fej"])
def test_checkpoint_resume_continues_the_same_map_bit_for_bit(tmp_path,
                                                              linearisation: str) -> None:
    # FEJ needs its linearisation points after the restart: the checkpoint keeps them
    settings = EstimatorSettings(robot=ROBOT, checkpoint=str(tmp_path),
                                 checkpoint_interval_s=1e-3, linearisation=linearisation)
    inputs = _inputs(400)
    _, first, first_states = _service(settings)
    for t, (key, payload) in enumerate(inputs[:250]):
        first.ingest(_sample(key, payload, t))
    # "SIGKILL": no clean exit; what is on disk is whatever the writer last wrote
    assert first.checkpoints is not None and first.checkpoints.writer is not None
    first.checkpoints.writer.close()
    saved = ckpt.load(tmp_path, ROBOT)
    assert saved is not None
    at = SlamState.from_bytes(saved.state)
    assert 0 < at.seq <= 250

    _, second, states = _service(settings)
    assert second.resumed and second.epoch == first.epoch
    for t, (key, payload) in enumerate(inputs):  # the drivers' cache, from the start
        second.ingest(_sample(key, payload, t))
    assert [s.seq for s in states] == list(range(at.seq, len(inputs) + 1))
    assert states[0].epoch == first.epoch and states[-1].epoch == first.epoch
    expected = _direct(inputs, EstimatorSettings(robot=ROBOT, linearisation=linearisation))
    np.testing.assert_array_equal(states[-1].covariance, expected.covariance)
    np.testing.assert_array_equal(states[-1].landmarks, expected.landmarks)
    assert second.order.stats.duplicates == at.seq
    assert (saved.linearisation is None) == (linearisation == "standard")


def test_without_a_checkpoint_a_restart_is_a_new_epoch() -> None:
    settings = EstimatorSettings(robot=ROBOT)
    _, a, _ = _service(settings)
    _, b, _ = _service(settings)
    assert b.epoch > a.epoch and not b.resumed


def test_an_unreadable_checkpoint_is_one_clear_error(tmp_path) -> None:
    ckpt.checkpoint_path(tmp_path, ROBOT).write_bytes(b"not msgpack at all \xff")
    with pytest.raises(ckpt.CheckpointError, match="unreadable"):
        _service(EstimatorSettings(robot=ROBOT, checkpoint=str(tmp_path)))


@pytest.mark.parametrize("payload", [
    b"\x93\x01\x02",  # a msgpack list
    b"\xc1",  # never valid msgpack
    b"",
])
def test_garbage_is_counted_and_the_service_goes_on(payload: bytes) -> None:
    _, service, states = _service(EstimatorSettings(robot=ROBOT))
    assert service.ingest(_sample(KEYS.odometry(ROBOT), payload, 1)) == []
    assert service.drops.total == 1
    good = Odometry(robot=ROBOT, stamp=0.1, dt=0.1, v=0.1, w=0.0, input_seq=1)
    assert len(service.ingest(_sample(KEYS.odometry(ROBOT), good.to_bytes(), 2))) == 1


def test_the_worker_holds_no_state_of_a_burst_so_covariance_buffers_are_recycled() -> None:
    """At n = 1000 each state holds a 32 MB covariance, recycled only once nothing holds
    it: a worker that kept a burst's states would hold them all, each in a new buffer."""
    settings = EstimatorSettings(robot=ROBOT)
    bus = InProcessBus()
    service = EstimatorService(bus, keys=KEYS, settings=settings)
    sizes: list[int] = []  # a map that grows needs a buffer of a new size
    bus.subscribe(KEYS.state(ROBOT), lambda k, p: sizes.append(SlamState.from_bytes(p).n))
    inputs = _inputs(120)
    publishers = {key: bus.publisher(key) for key, _ in inputs}
    for key, payload in inputs:  # one burst: all queued before the worker's turn
        publishers[key].put(payload)
    published = 0
    while (made := service.step(timeout=0)) or published < len(inputs):
        published += made
        assert made or published == len(inputs), "the worker stopped short"
    assert published == len(inputs)
    assert len(sizes) == len(inputs)
    # per map size at most two new buffers (the first state's, and one while the last
    # published state's is still held as the base of the next); every other one reused
    fresh = 2 * len(set(sizes))
    assert service.estimator.published.buffers.reused >= len(inputs) - fresh, (fresh, sizes)


def _dense(est: Estimator) -> np.ndarray:
    """The textbook symmetric P from the estimator's lower-triangle storage (an oracle
    independent of ``ekf.symmetric``: numpy's own triangles)."""
    N = 3 + 2 * est.n
    lower = np.tril(est.store.L[:N, :N])
    return lower + np.tril(lower, -1).T


def _dense_after_each(inputs: list[tuple[str, bytes]],
                      settings: EstimatorSettings) -> list[np.ndarray]:
    """The dense P after each input, from an estimator of its own fed them directly."""
    out: list[np.ndarray] = []
    _direct(inputs, settings, lambda est: out.append(_dense(est)))
    return out


@pytest.mark.parametrize("burst", [False, True])
def test_predict_states_patched_in_place_equal_the_dense_matrix_every_one(burst) -> None:
    """A predict's state reuses the last state's matrix in place (its robot rows and
    columns patched) once nothing holds that matrix: every state a subscriber gets is
    still exactly the dense P of its moment — none was changed after it went out — one
    input a turn, or all of them in one burst (the worker at full speed)."""
    settings = EstimatorSettings(robot=ROBOT)
    bus, service, states = _service(settings)
    inputs = _inputs(300)
    publishers = {key: bus.publisher(key) for key, _ in inputs}
    if burst:
        for key, payload in inputs:
            publishers[key].put(payload)
        assert service.step(timeout=0) == len(inputs)
    else:
        for key, payload in inputs:
            publishers[key].put(payload)
            assert service.step(timeout=0) == 1
    assert service.estimator.predicts_in_place > 100  # about half the states are predicts
    assert [s.seq for s in states] == list(range(0, len(inputs) + 1))
    for state, P in zip(states[1:], _dense_after_each(inputs, settings), strict=True):
        np.testing.assert_array_equal(state.covariance, P, err_msg=f"seq {state.seq}")


def test_a_state_still_held_is_never_patched_in_place() -> None:
    """States returned to a caller who keeps them (here: all of them) keep their own
    matrices: the next predict copies instead of patching."""
    settings = EstimatorSettings(robot=ROBOT)
    bus, service, _ = _service(settings)
    inputs = _inputs(120)
    publishers = {key: bus.publisher(key) for key, _ in inputs}
    kept: list[tuple[SlamState, np.ndarray]] = []
    for key, payload in inputs:
        publishers[key].put(payload)
        for state in service.ingest(service._inputs.recv(timeout=1.0)):
            kept.append((state, state.covariance.copy()))
    # only the first predict patched in place: the init state's matrix, which nobody kept
    assert service.estimator.predicts_in_place == 1
    assert len(kept) == len(inputs)
    for state, copy in kept:
        np.testing.assert_array_equal(state.covariance, copy, err_msg=f"seq {state.seq}")
