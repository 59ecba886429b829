"""A monitor far behind on a large map checks the newest state and says what it skipped."""

from __future__ import annotations

import numpy as np

from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState
from slamlens.services.monitor.service import MonitorService
from slamlens.services.monitor.settings import MonitorSettings

KEYS = Keys("t")


def _state(seq: int, n: int, shrink: float) -> SlamState:
    N = 3 + 2 * n
    P = np.eye(N) * (0.5 + 0.5 * shrink)  # every variance shrinks: a correct filter
    return SlamState(robot="r1", seq=seq, stamp=0.1 * seq, step="update", pose=np.zeros(3),
                     landmark_ids=np.arange(n), landmarks=np.zeros((n, 2)), covariance=P,
                     epoch=1)


def test_states_beyond_the_budget_are_skipped_counted_and_the_newest_checked() -> None:
    bus = InProcessBus()
    healths: list[Health] = []
    bus.subscribe(KEYS.health("r1"), lambda k, p: healths.append(Health.from_bytes(p)))
    service = MonitorService(bus, keys=KEYS, robot="r1",
                             settings=MonitorSettings(robot="r1", sample_above_mb=2.0))
    n = 200  # a state of ≈ 1.3 MB
    pub = bus.publisher(KEYS.state("r1"))
    for seq in range(1, 11):
        pub.put(_state(seq, n, shrink=1.0 / seq).to_bytes())  # queued: nobody checks yet
    first = service._inputs.recv(timeout=0)
    assert first is not None
    service.handle(first.key, first.payload)
    assert service._inputs.backlog_bytes > 2 << 20
    service._sample()
    assert [h.seq for h in healths] == [1, 10]  # the first, then straight to the newest
    assert healths[-1].statistics["sampled_out"] == 8.0
    assert service.sampled_out == 8 and all(h.ok for h in healths)
    assert service.summary()["sampled_out"] == 8


def test_small_maps_never_reach_the_budget() -> None:
    bus = InProcessBus()
    service = MonitorService(bus, keys=KEYS, robot="r1", settings=MonitorSettings(robot="r1"))
    pub = bus.publisher(KEYS.state("r1"))
    for seq in range(1, 2001):  # 2000 states of a 15-landmark map waiting
        pub.put(_state(seq, 15, shrink=1.0 / seq).to_bytes())
    assert service._inputs.backlog_bytes < 512 << 20


def test_the_rest_after_a_large_state_ends_at_once_on_stop() -> None:
    """large_share: after a large state the checking thread rests (here 999 × the check, seconds),
    and a stop during the rest ends it at once (no signal waits for it)."""
    import threading

    bus = InProcessBus()
    checked = threading.Event()
    bus.subscribe(KEYS.health("r1"), lambda k, p: checked.set())
    service = MonitorService(bus, keys=KEYS, robot="r1",
                             settings=MonitorSettings(robot="r1", newest_above_mb=1.0,
                                                      large_share=0.001))
    stop = threading.Event()
    worker = threading.Thread(target=service.run, args=(stop,), daemon=True)
    worker.start()
    before = service.worker_cpu_s
    bus.publisher(KEYS.state("r1")).put(_state(1, 200, shrink=1.0).to_bytes())  # 1.3 MB
    assert checked.wait(30.0)
    assert service._large_step  # resting now, for ~999 × the check's CPU time
    stop.set()
    worker.join(timeout=5.0)
    assert not worker.is_alive() and service.worker_cpu_s > before
