"""A third-party robot driver and the estimator it feeds, as the conformance cases use
them: start ``slamlens estimator``, publish a simulated run on the two input keys in one of
the ways docs/protocol.md allows, wait for the last input's state, compare with the oracle.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import kit_wire as wire
import zenoh
from kit_ekf import assert_state_equals
from kit_procs import Proc, endpoint, start
from kit_run import Input, estimator_flags, oracle

#: the input counts every report carries (docs/protocol.md, "Counts")
INPUT_COUNTS = ("duplicates", "late", "lost", "waited", "reordered", "joined_late", "dropped")


def estimator(port: int, robot: str, *extra: str) -> Proc:
    """``slamlens estimator --robot ROBOT`` with the oracle's settings, once ready."""
    return start("estimator", "--robot", robot, "--connect", endpoint(port),
                 *estimator_flags(), *extra, ready="estimator ready")


@dataclass
class Driver:
    """One publishing session with its two input publishers."""

    session: zenoh.Session
    odometry: Any
    observations: Any

    @classmethod
    def open(cls, port: int, robot: str, *, kind: str, timestamping: bool) -> Driver:
        s = wire.session(port, timestamping=timestamping)
        make = wire.advanced if kind == "advanced" else wire.plain
        for leaf in ("odometry", "observations"):
            wire.wait_matched(s, wire.key(robot, leaf))
        return cls(s, make(s, wire.key(robot, "odometry")),
                   make(s, wire.key(robot, "observations")))

    def publish(self, robot: str, inputs: Iterable[Input], *, numbered_from: int | None = None,
                only: str | None = None) -> None:
        """Put ``inputs`` as fast as they go (``only``: one leaf of them), numbered from
        ``numbered_from`` (one counter over both keys) if given."""
        for n, item in enumerate(inputs):
            seq = None if numbered_from is None else numbered_from + n
            if only is not None and item.leaf != only:
                continue
            if item.leaf == "odometry":
                self.odometry.put(wire.pack(wire.odometry(robot, item.stamp,
                                                          input_seq=seq, **item.fields)))
            else:
                self.observations.put(wire.pack(wire.observations(robot, item.stamp,
                                                                  input_seq=seq,
                                                                  **item.fields)))

    def close(self) -> None:
        self.session.close()


def last_state(watch: wire.StateWatch, inputs: list[Input]) -> dict[str, Any]:
    """Wait for the state of the last input (its stamp, an update), then ``get`` the
    state: the estimator's final answer, decoded."""
    final = inputs[-1].stamp
    watch.wait(lambda h: h.get("input_stamp") == final and h.get("step") == "update",
               f"input_stamp {final} (the last input's)")
    payload = wire.get_one(watch.session, wire.key(watch.robot, "state"))
    assert payload is not None, "nobody answered a get on the state key"
    return wire.state_of(payload)


def check_final(watch: wire.StateWatch, inputs: list[Input],
                counts: dict[str, int]) -> dict[str, Any]:
    """The final state equals the oracle's; the header's counts are all there and those
    named in ``counts`` have those values. Returns the header."""
    state = last_state(watch, inputs)
    assert_state_equals(state, oracle(inputs))
    head = wire.header(watch.session, watch.robot)
    assert head is not None
    missing = [name for name in INPUT_COUNTS if name not in head]
    assert not missing, f"state?header lacks the counts {missing}: {head}"
    wrong = {name: head[name] for name, value in counts.items() if head[name] != value}
    assert not wrong, f"counts {wrong}, expected {counts} (header {head})"
    return head


def check_accounted(watch: wire.StateWatch, inputs: list[Input]) -> dict[str, Any]:
    """Every input applied or counted (docs/protocol.md, "Unnumbered inputs": one that
    Zenoh recovered after later ones were applied is counted ``late``; one missed for good
    ``lost``), nothing duplicated, dropped or refused. Returns the header."""
    n = len(inputs)
    head = watch.wait(lambda h: sum(int(h.get(k, 0)) for k in ("seq", "late", "lost")) >= n,
                      f"all {n} inputs applied or counted")
    accounted = {k: int(head.get(k, 0)) for k in ("seq", "late", "lost")}
    assert sum(accounted.values()) == n, f"{accounted} for {n} inputs (header {head})"
    wrong = {k: head.get(k) for k in ("duplicates", "dropped", "refused") if head.get(k)}
    assert not wrong, f"counts {wrong}, expected none (header {head})"
    return head


def stop_line(proc: Proc, code: int) -> dict[str, Any]:
    """Of an estimator stopped with SIGTERM: exit status 0 and the stop line ``estimator
    stopped: {JSON}``, which must carry the input counts (docs/protocol.md, "Counts");
    its JSON."""
    assert code == 0, f"the estimator exited {code}:\n{proc.tail()}"
    lines = [line for line in proc.out if line.startswith("estimator stopped: ")]
    assert lines, proc.tail()
    said = json.loads(lines[-1].split(": ", 1)[1])
    missing = [name for name in INPUT_COUNTS if name not in said]
    assert not missing, f"the stop line lacks the counts {missing}: {lines[-1]}"
    return dict(said)


def checkpoint_written(directory: Path) -> bool:
    return any(directory.glob("*.ckpt"))
