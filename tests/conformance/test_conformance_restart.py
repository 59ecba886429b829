"""Crash recovery (docs/protocol.md, "Crash recovery"): a third-party driver publishing
through a zenoh.ext advanced publisher (cache, sample-miss detection, heartbeat), numbered
and unnumbered; the estimator, started with ``--checkpoint DIR``, is killed with SIGKILL in
the middle of the run and started again with the same DIR. Inputs published while it was
down come from the publisher's cache; what the checkpoint covered is not applied again. The
final state must be that of an uninterrupted run: the dense oracle's over every input, to
1e-9, with the same epoch and seq numbering.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import kit_wire as wire
import pytest
from kit_driver import Driver, check_final, checkpoint_written, estimator, stop_line
from kit_run import simulate


def wait_for_checkpoint(directory: Path, watch: wire.StateWatch, seq: int) -> int:
    """Until the estimator applied at least ``seq`` inputs and its checkpoint file exists
    (both events; the loop only looks again). The epoch it is on."""
    head = watch.wait(lambda h: h.get("seq", 0) >= seq, f"seq ≥ {seq}")
    deadline = time.monotonic() + wire.PATIENCE_S
    while not checkpoint_written(directory):
        assert time.monotonic() < deadline, f"no checkpoint in {directory}"
        time.sleep(0.05)
    return int(head["epoch"])


@pytest.mark.parametrize("numbered", [True, False], ids=["numbered", "unnumbered"])
def test_sigkill_and_resume(router: int, tmp_path: Path, numbered: bool) -> None:
    robot = f"restart-{'n' if numbered else 'u'}"
    inputs = simulate(seed=21)
    # [0, a) before the first checkpoint, [a, b) after it, [b, c) while the estimator is
    # down (only the publisher's cache has them), [c, end) after the restart
    a, b, c = (int(len(inputs) * f) for f in (0.3, 0.5, 0.75))

    def publish(lo: int, hi: int) -> None:
        driver.publish(robot, inputs[lo:hi], numbered_from=lo + 1 if numbered else None)

    est = estimator(router, robot, "--checkpoint", str(tmp_path))
    driver = Driver.open(router, robot, kind="advanced", timestamping=True)
    watch = wire.StateWatch(driver.session, robot)
    try:
        publish(0, a)
        epoch = wait_for_checkpoint(tmp_path, watch, a // 2)
        publish(a, b)
        watch.wait(lambda h: h.get("seq", 0) >= b, f"seq ≥ {b}")
        est.stop(signal.SIGKILL)  # at once: the checkpoint may be behind what was applied
        publish(b, c)
        est = estimator(router, robot, "--checkpoint", str(tmp_path))
        for leaf in ("odometry", "observations"):
            wire.wait_matched(driver.session, wire.key(robot, leaf))
        publish(c, len(inputs))
        head = check_final(watch, inputs, {"late": 0, "lost": 0, "dropped": 0})
        assert head["epoch"] == epoch, "the resumed estimator started another map"
    finally:
        watch.close()
        driver.close()
        code = est.stop()
    stop_line(est, code)
