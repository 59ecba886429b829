"""The invariant EKF through the contract (docs/protocol.md, ``diagnostics`` and its flag
``linearisation.invariant``; docs/estimator.md, "The invariant EKF"):

* ``slamlens estimator --linearisation invariant``, fed a third party's run unpaced, ends
  where an independent dense invariant EKF (kit_inekf.py) ends, to 1e-9, and its states
  carry the flag;
* ``slamlens monitor`` holds a third party's invariant EKF, whose states carry the flag, to
  that filter's theorems: no violation on any state, and its unobservable directions
  checked on nearly every one; the very same states without the flag break the growth
  theorem of the standard error (so the flag, as the contract says, is what decides).

The third party publishes its states in lock step with the monitor's Health of each seq:
nothing waits on time.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import kit_wire as wire
import numpy as np
from kit_driver import Driver, estimator, last_state, stop_line
from kit_ekf import assert_state_equals
from kit_inekf import DenseInvariantEkf
from kit_procs import endpoint, start
from kit_run import SIGMA, apply, oracle, simulate

FLAG = "linearisation.invariant"
THEOREMS = {"feature", "pair", "prediction", "unobservable", "psd", "symmetry", "correlation"}


def test_the_estimator_is_the_invariant_oracle(router: int) -> None:
    robot = "inv-estimator"
    inputs = simulate(seed=14)
    est = estimator(router, robot, "--linearisation", "invariant")
    driver = Driver.open(router, robot, kind="plain", timestamping=True)
    watch = wire.StateWatch(driver.session, robot)
    try:
        driver.publish(robot, inputs)
        state = last_state(watch, inputs)
        assert_state_equals(state, oracle(inputs, DenseInvariantEkf))
        assert state["diagnostics"].get(FLAG) == 1.0, state["diagnostics"]
    finally:
        watch.close()
        driver.close()
        code = est.stop()
    stop_line(est, code)


class ThirdParty:
    """Publishes states of ``robot`` and hears its Healths."""

    def __init__(self, port: int, robot: str) -> None:
        self.robot = robot
        self.session = wire.session(port)
        self.lockstep = wire.LockStep(self.session, robot)

    def publish(self, seq: int, step: str, ekf: DenseInvariantEkf, flag: bool
                ) -> dict[str, Any]:
        """The state of ``ekf`` as seq ``seq``; the monitor's Health of it."""
        n = len(ekf.ids)
        state = wire.pack({
            "robot": self.robot, "seq": seq, "stamp": 0.1 * seq, "step": step,
            "pose": wire.array(ekf.pose, "<f8"),
            "landmark_ids": wire.array(ekf.ids, "<i8"),
            "landmarks": wire.array(ekf.landmarks.reshape(n, 2), "<f8"),
            "covariance": wire.array(ekf.P.reshape(-1), "<f8"),
            "diagnostics": {FLAG: 1.0} if flag else {}})
        return self.lockstep.exchange(state, seq)

    def close(self) -> None:
        self.session.close()


def healths(router: int, robot: str, flag: bool) -> Iterator[dict[str, Any]]:
    """A monitor process for ``robot``; the third party's invariant EKF over a simulated
    run, a state after every input; the Health of each."""
    monitor = start("monitor", "--robot", robot, "--connect", endpoint(router),
                    ready="monitor ready")
    party = ThirdParty(router, robot)
    try:
        wire.wait_matched(party.session, wire.key(robot, "state"))
        ekf = DenseInvariantEkf(**SIGMA)
        yield party.publish(0, "init", ekf, flag)
        for seq, item in enumerate(simulate(seed=15), start=1):
            apply(ekf, item)
            yield party.publish(seq, "predict" if item.leaf == "odometry" else "update",
                                ekf, flag)
    finally:
        party.close()
        monitor.stop()


def test_the_monitor_holds_an_invariant_ekf_to_its_own_theorems(router: int) -> None:
    seen = list(healths(router, "inv-flagged", flag=True))
    broken = [(h["seq"], v["kind"], v.get("detail")) for h in seen
              for v in h.get("violations", []) if v["kind"] in THEOREMS]
    assert not broken, broken[:5]
    checked = sum("unobservable_growth" in h.get("statistics", {}) for h in seen)
    assert checked > 0.9 * len(seen), f"unobservable directions checked on {checked}"
    assert all(h.get("verdict", "ok") != "fault" for h in seen)


def test_without_the_flag_the_same_states_break_the_standard_theorem(router: int) -> None:
    seen = list(healths(router, "inv-unflagged", flag=False))
    growth = [h["seq"] for h in seen
              for v in h.get("violations", []) if v["kind"] in ("feature", "pair")]
    assert len(growth) > 5, growth
    assert np.any([h.get("verdict") == "fault" for h in seen])
