"""A third-party robot driver, unpaced, in every way docs/protocol.md allows to publish
inputs ("Inputs: order and delivery"): plain publisher with congestion control BLOCK, with
and without the session's timestamping; a zenoh.ext advanced publisher; numbered inputs
(``input_seq``); and two sessions (odometry from one, observations from the other) with
``--input-sources 2``. The estimator's final state must be the dense oracle's after every
input in publication order (docs/estimator.md's models), to 1e-9, and the counts of
"Counts" must be in ``state?header`` and say nothing went wrong.

The advanced publisher is the exception the contract names: its congestion control is
Zenoh's default, *drop*, so on a loaded machine Zenoh may drop an input and recover it
from the cache after later ones of the other key were applied; unnumbered, it is then
counted ``late`` and not applied ("For exact order across losses, number the inputs").
There every input must be applied or counted, and the oracle must hold when none was late
or lost.
"""

from __future__ import annotations

import threading

import kit_wire as wire
import pytest
from kit_driver import Driver, check_accounted, check_final, estimator, stop_line
from kit_run import simulate

VARIANTS = {
    # name: (publisher, session timestamping, numbered)
    "plain-block": ("plain", False, False),
    "plain-timestamped": ("plain", True, False),
    "advanced": ("advanced", True, False),
    "numbered": ("plain", True, True),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_one_session_unpaced(router: int, variant: str) -> None:
    kind, timestamping, numbered = VARIANTS[variant]
    robot = f"drv-{variant}"
    inputs = simulate(seed=11)
    est = estimator(router, robot)
    driver = Driver.open(router, robot, kind=kind, timestamping=timestamping)
    watch = wire.StateWatch(driver.session, robot)
    try:
        driver.publish(robot, inputs, numbered_from=1 if numbered else None)
        if kind != "advanced" or not _late_or_lost(check_accounted(watch, inputs)):
            check_final(watch, inputs, {"late": 0, "lost": 0, "dropped": 0})
    finally:
        watch.close()
        driver.close()
        code = est.stop()
    stop_line(est, code)


def _late_or_lost(head: dict) -> bool:
    return bool(head.get("late") or head.get("lost"))


def test_two_sessions_merged_by_stamp(router: int) -> None:
    """Both sessions publish to the end, so the merge must come from the stamps alone: the
    wait for a silent session (``input_reorder_s``) is set far beyond the run and must not
    be used (``waited`` 0) — on a loaded machine a publishing thread may stall for longer
    than the default wait, which is the case that wait is for, not this one."""
    robot = "drv-two"
    inputs = simulate(seed=12)
    est = estimator(router, robot, "--input-sources", "2", "--input-reorder-s", "120")
    odometry = Driver.open(router, robot, kind="plain", timestamping=True)
    observations = Driver.open(router, robot, kind="plain", timestamping=True)
    watch = wire.StateWatch(odometry.session, robot)
    try:
        threads = [threading.Thread(target=d.publish, args=(robot, inputs),
                                    kwargs={"only": leaf})
                   for d, leaf in ((odometry, "odometry"), (observations, "observations"))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        check_final(watch, inputs, {"late": 0, "lost": 0, "dropped": 0, "waited": 0})
    finally:
        watch.close()
        odometry.close()
        observations.close()
        code = est.stop()
    stop_line(est, code)
