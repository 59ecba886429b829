"""The estimator service with hostile inputs, gated observations and the init state's stamp,
in-process (InProcessBus): what it publishes, counts and says."""

from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np

from slamlens.common.bus import Sample
from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Observations, Odometry, SlamState
from slamlens.services.slam.estimator_service import EstimatorService
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

KEYS = Keys("t")
ROBOT = "r1"
T0 = 1.248e9  # a dataset's own clock (MRCLAM)


def paper_inputs(limit: int = 200, t0: float = T0) -> list[Odometry | Observations]:
    sim = Simulator(load_world("paper"), robot=ROBOT, seed=3)
    out: list[Odometry | Observations] = []
    for m in sim.events():
        if isinstance(m, (Odometry, Observations)):
            out.append(dataclasses.replace(m, stamp=m.stamp + t0))
        if len(out) == limit:
            break
    return out


def numbered(messages: list[Odometry | Observations]) -> list[Sample]:
    seq = itertools.count(1)
    out = []
    for t, m in enumerate(messages):
        m = dataclasses.replace(m, input_seq=next(seq))
        key = KEYS.odometry(ROBOT) if isinstance(m, Odometry) else KEYS.observations(ROBOT)
        out.append(Sample(key, m.to_bytes(), source="driver", time=t))
    return out


def service(settings: EstimatorSettings | None = None) -> tuple[EstimatorService,
                                                                 list[SlamState]]:
    bus = InProcessBus()
    states: list[SlamState] = []
    bus.subscribe(KEYS.state(ROBOT), lambda k, p: states.append(SlamState.from_bytes(p)))
    return EstimatorService(bus, keys=KEYS, settings=settings or EstimatorSettings(
        robot=ROBOT)), states


def hostile(stamp: float) -> list[Odometry | Observations]:
    """One input per plausibility gate, each absurd in its own way."""
    def odo(**kw) -> Odometry:
        return Odometry(robot=ROBOT, **{"stamp": stamp, "dt": 0.05, "v": 0.1, "w": 0.0, **kw})

    def obs(ids, ranges, bearings, t: float = stamp) -> Observations:
        return Observations(robot=ROBOT, stamp=t, ids=np.asarray(ids, np.int64),
                            ranges=np.asarray(ranges, float), bearings=np.asarray(bearings,
                                                                                  float))
    k = 1000
    return [odo(dt=1e200), odo(v=1e6), odo(w=-1e4), obs([900], [1e300], [0.0]),
            obs([901], [1.0], [1e6]), odo(stamp=stamp + 1e7),
            obs(np.arange(2000, 2000 + k), np.ones(k), np.zeros(k))]


def test_hostile_inputs_publish_no_state_are_counted_and_logged_once(caplog) -> None:
    clean = paper_inputs()
    mixed = clean[:100] + hostile(clean[99].stamp) + hostile(clean[99].stamp) + clean[100:]
    reference, ref_states = service()
    for sample in numbered(clean):
        reference.ingest(sample)
    svc, states = service()
    with caplog.at_level(logging.WARNING, logger="slamlens.estimator"):
        for sample in numbered(mixed):
            svc.ingest(sample)
    assert len(states) == len(ref_states) == len(clean) + 1  # init + one per applied input
    final, expected = states[-1], ref_states[-1]
    assert np.array_equal(final.covariance, expected.covariance)
    assert np.array_equal(final.pose, expected.pose)
    assert np.array_equal(final.landmark_ids, expected.landmark_ids)
    status = svc.status()
    reasons = {"dt": 2, "speed": 2, "turn_rate": 2, "range": 2, "bearing": 2,
               "stamp_jump": 2, "batch_size": 2}
    assert status["refused_by"] == reasons and status["refused"] == 14
    assert status["last_refused"]["reason"] == "batch_size"
    assert status["bounds"]["max_dt_s"] == 10.0
    assert final.diagnostics is not None and all(
        final.diagnostics[f"refused.{r}"] == n for r, n in reasons.items())
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(lines) == len(reasons)  # once per reason, the rest counted
    assert any("dt 1e+200 s above the bound 10 s" in line and "the input: odometry" in line
               for line in lines)
    assert "14 refused (batch_size 2, bearing 2, dt 2" in svc.status_line()


def test_the_init_state_has_no_time_and_every_later_state_the_data_time() -> None:
    """The decision of docs/protocol.md: the init state is published at start-up, before any
    input (the registration service registers a new epoch from it while the robot stands at
    the origin), so it carries no data time (stamp 0.0); the first input's state and every
    later one carry the data's own clock, and the map origin's time as origin_stamp."""
    svc, states = service()
    assert [s.step for s in states] == ["init"] and states[0].stamp == 0.0
    assert states[0].origin_stamp is None
    inputs = paper_inputs(5)
    for sample in numbered(inputs):
        svc.ingest(sample)
    first = inputs[0]
    assert isinstance(first, Odometry)
    assert [s.seq for s in states] == list(range(len(inputs) + 1))
    assert states[1].step == "predict" and states[1].stamp == first.stamp > T0
    assert all(s.origin_stamp == first.stamp - first.dt for s in states[1:])


def test_gated_observations_are_published_in_the_state_diagnostics() -> None:
    settings = EstimatorSettings(robot=ROBOT, innovation_gate_chi2=13.82)
    svc, states = service(settings)
    inputs = paper_inputs(60)
    batches = [i for i, m in enumerate(inputs) if isinstance(m, Observations) and
               m.ids.size >= 2 and i > 30]
    i = batches[0]
    b = inputs[i]
    assert isinstance(b, Observations)
    ranges = np.array(b.ranges)
    ranges[1] += 1.5  # a gross outlier on a known landmark
    inputs[i] = dataclasses.replace(b, ranges=ranges)
    for sample in numbered(inputs):
        svc.ingest(sample)
    gated_states = [s for s in states if s.gated_ids is not None]
    assert len(gated_states) == 1
    s = gated_states[0]
    assert list(s.gated_ids) == [int(b.ids[1])]
    assert s.gated_observations[0, 0] == ranges[1] and s.gated_nis[0] > 13.82
    assert int(b.ids[1]) not in [int(j) for j in s.innovation_ids]
    assert states[-1].diagnostics["gated"] == 1.0 and svc.status()["gated"] == 1
    decoded = SlamState.from_bytes(s.to_bytes())
    assert decoded == s


def test_a_state_without_the_optional_fields_still_decodes() -> None:
    svc, states = service()
    for sample in numbered(paper_inputs(3)):
        svc.ingest(sample)
    raw = states[-1].to_dict()
    for name in ("gated_ids", "gated_observations", "gated_nis", "diagnostics"):
        raw.pop(name, None)
    decoded = SlamState.from_dict(raw)
    assert decoded.diagnostics is None and decoded.gated_ids is None
