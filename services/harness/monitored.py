"""An Estimator and a Monitor in one process, as the processes chain them: each input into
the estimator, each state it makes into the monitor, in order, with every state checked
(the benchmarks that count verdicts over a whole dataset: mrclam_verdict.py,
victoria_park.py)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from slamlens.common.errors import EstimationError
from slamlens.common.messages import Health, Observations, Odometry, Truth
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.observe_report import ObserveReport

Input = Odometry | Observations


def monitored(est: Estimator, monitor: Monitor, events: Iterable[Input | Truth]
              ) -> Iterator[tuple[Input, ObserveReport | None, Health]]:
    """(input, its update report or None, the Health of its state) for each input applied.
    The init state is checked first; a Truth goes to the monitor; an input the estimator
    refuses makes no state (as in the service)."""
    monitor.check(est.to_state(seq=0, stamp=0.0, step="init"))
    seq = 0
    for message in events:
        if isinstance(message, Truth):
            monitor.add_truth(message)
            continue
        try:
            report = est.apply(message)
        except EstimationError:
            continue  # refused (counted by the estimator): no state
        seq += 1
        state = est.to_state(seq=seq, stamp=message.stamp, report=report,
                             step="predict" if report is None else "update")
        yield message, report, monitor.check(state)
