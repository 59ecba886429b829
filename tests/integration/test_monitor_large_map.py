"""The monitor on a 1000-landmark map: far behind, it samples, and still names
the planted faulty feature within one sampling interval.

The real estimator (docs/estimator.md, with the ``map-update`` fault planted on one feature from a
given stamp) builds a map of 1000 landmarks and runs on; its states (32 MB each) go to a
:class:`MonitorService` with the default ``sample_above_mb`` (512 MB). The monitor is made to
fall behind deterministically: it takes a step only after every ``BURST`` states published,
as it does when the estimator publishes faster than it checks (docs/monitor.md, large maps).
"""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Health
from slamlens.services.monitor.service import MonitorService
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings

KEYS = Keys("t")
ROBOT = "r1"
N_LANDMARKS = 1000
FAULTY = 437
ONSET = 2.0  #: s; the fault acts on events from this stamp on (about seq 40 below)
BURST = 20  #: states published between two monitor steps (> 512 MB of states at n = 1000)
#: the stated bound: a fault is named at the next state checked, i.e. within one sampling
#: interval of BURST states, half of them updates
MAX_UPDATES_TO_NAME = BURST // 2 + 1


def _observe(est: Estimator, ids: list[int], rng: np.random.Generator, stamp: float) -> None:
    """Range-bearing observations of ``ids`` consistent with the estimate (small noise)."""
    pose = est.pose
    index = {int(i): k for k, i in enumerate(est.landmark_ids)}
    xy = est.landmarks[[index[i] for i in ids]]
    dx, dy = xy[:, 0] - pose[0], xy[:, 1] - pose[1]
    ranges = np.hypot(dx, dy) + rng.normal(0, 0.01, len(ids))
    bearings = np.arctan2(dy, dx) - pose[2] + rng.normal(0, 0.005, len(ids))
    bearings = (bearings + math.pi) % (2 * math.pi) - math.pi
    est.observe(ids=ids, ranges=ranges, bearings=bearings, stamp=stamp)


def test_faulty_feature_at_n_1000_is_named_within_one_sampling_interval() -> None:
    rng = np.random.default_rng(13)
    est = Estimator(EstimatorSettings(robot=ROBOT, fault="map-update",
                                      faulty_features=(FAULTY,), fault_onset=ONSET))
    # 1000 landmarks around the start, first seen in 20 batches of 50 (ids 1..1000)
    ids = np.arange(1, N_LANDMARKS + 1)
    ranges = 1.0 + 4.0 * rng.random(N_LANDMARKS)
    bearings = rng.uniform(-1.5, 1.5, N_LANDMARKS)
    for k in range(0, N_LANDMARKS, 50):
        est.observe(ids=ids[k:k + 50], ranges=ranges[k:k + 50], bearings=bearings[k:k + 50],
                    stamp=0.05)
    assert est.n == N_LANDMARKS

    bus = InProcessBus()
    healths: list[Health] = []
    bus.subscribe(KEYS.health(ROBOT), lambda _k, p: healths.append(Health.from_bytes(p)))
    service = MonitorService(bus, keys=KEYS, robot=ROBOT,
                             settings=MonitorSettings(robot=ROBOT))  # sample_above_mb 512
    publish = bus.publisher(KEYS.state(ROBOT))
    steps: dict[int, tuple[str, float]] = {}  # seq → (step, stamp)
    stamp, seq = 0.05, 0
    seen = [i for i in ids if i != FAULTY]  # the faulty feature is not observed again
    while seq < 100:
        for _ in range(BURST):  # the estimator runs ahead of the monitor
            seq += 1
            stamp += 0.05
            if seq % 2:
                est.predict(v=0.2, w=0.05, dt=0.05, stamp=stamp)
                step = "predict"
            else:
                _observe(est, [int(i) for i in rng.choice(seen, 4, replace=False)], rng, stamp)
                step = "update"
            steps[seq] = (step, stamp)
            publish.put(est.to_state(seq=seq, stamp=stamp, step=step, epoch=1).wire_parts())
        while service.step(timeout=0):  # what the monitor's loop does when it gets a turn
            pass

    checked = [h.seq for h in healths]
    assert service.sampled_out > 0 and len(checked) < 0.5 * seq  # it did sample
    assert checked == sorted(checked) and checked[-1] == seq  # always up to the newest
    first_faulty = min(s for s, (step, t) in steps.items() if step == "update" and t >= ONSET)
    before = [h for h in healths if h.seq < first_faulty]
    assert before and all(h.ok and h.suspects.size == 0 for h in before)  # no false alarm
    named = next(h.seq for h in healths if FAULTY in h.suspects)
    updates = sum(1 for s in range(first_faulty, named + 1) if steps[s][0] == "update")
    assert updates <= MAX_UPDATES_TO_NAME, (first_faulty, named, checked)
    assert [int(i) for i in healths[-1].suspects] == [FAULTY]  # exactly it, still
    assert healths[-1].statistics["sampled_out"] == service.sampled_out

