"""Finite but absurd, and malformed, inputs from a plain client (docs/protocol.md,
"Refusals"): each malformed input is refused and counted in ``dropped`` (``state?header``,
``slamlens status``), each absurd one refused by a plausibility gate and counted in the
state's ``diagnostics`` (``refused.<reason>``); the estimator keeps running, and its final
state is the dense oracle's over the ordinary inputs alone, to 1e-9.
"""

from __future__ import annotations

import math
import time
from typing import Any

import kit_wire as wire
import msgpack
import numpy as np
from kit_driver import Driver, check_final, estimator, stop_line
from kit_run import Input, simulate

ROBOT = "hostile"


def _odo(**change: Any) -> bytes:
    fields = {"robot": ROBOT, "stamp": 1.0, "dt": 0.1, "v": 0.2, "w": 0.1, **change}
    return wire.pack({k: v for k, v in fields.items() if v is not None})


def _obs(**change: Any) -> bytes:
    fields = {"robot": ROBOT, "stamp": 1.0, "ids": wire.array([1], "<i8"),
              "ranges": wire.array([1.0], "<f8"), "bearings": wire.array([0.1], "<f8"),
              **change}
    return wire.pack(fields)


def _raw(data: Any) -> bytes:
    return msgpack.packb(data, use_bin_type=True)


#: (leaf, payload): refused as malformed, each counted once in ``dropped``
MALFORMED: list[tuple[str, bytes]] = [
    ("odometry", b"\xc1\xff\x00 not msgpack"),
    ("observations", _raw([1, 2, 3])),
    ("odometry", _raw({"schema": 2, "robot": ROBOT, "stamp": 1.0, "dt": 0.1, "v": 0.0,
                       "w": 0.0})),
    ("odometry", _odo(v="fast")),
    ("odometry", _odo(dt=None)),
    ("odometry", _odo(stamp=True)),
    ("odometry", _odo(w=math.nan)),
    ("odometry", _odo(dt=-0.1)),
    ("odometry", _odo(input_seq=-2)),
    ("observations", _obs(ranges=wire.array([math.inf], "<f8"))),
    ("observations", _obs(ids={"dtype": "<i8", "shape": [-1], "data": b""})),
    ("observations", _obs(ranges={"dtype": "<f8", "shape": [3], "data": b"\x00" * 16})),
    ("observations", _obs(ranges={"dtype": ">f8", "shape": [1], "data": b"\x00" * 8})),
    ("observations", _obs(ranges=wire.array([1.0, 2.0], "<f8"))),
    ("observations", _obs(ids=wire.array([-5], "<i8"))),
    ("observations", _obs(ranges=wire.array([-1.0], "<f8"))),
    ("observations", _obs(ids=[[1, 2], [3]])),
    ("odometry", _odo(robot="intruder")),
]

#: (leaf, fields beyond robot and stamp, the reason it is refused for)
ABSURD: list[tuple[str, dict[str, Any], str]] = [
    ("odometry", {"dt": 1e6, "v": 0.0, "w": 0.0}, "dt"),
    ("odometry", {"dt": 0.1, "v": 1e6, "w": 0.0}, "speed"),
    ("odometry", {"dt": 0.1, "v": 0.0, "w": 1e4}, "turn_rate"),
    ("observations", {"ids": [3], "ranges": [1e9], "bearings": [0.0]}, "range"),
    ("observations", {"ids": np.arange(10 ** 6), "ranges": np.ones(10 ** 6),
                      "bearings": np.zeros(10 ** 6)}, "batch_size"),
]


def _absurd(leaf: str, fields: dict[str, Any], stamp: float) -> bytes:
    if leaf == "odometry":
        return wire.pack(wire.odometry(ROBOT, stamp, **fields))
    return wire.pack(wire.observations(ROBOT, stamp, **fields))


def _publish_interleaved(driver: Driver, inputs: list[Input]) -> None:
    """The ordinary inputs, with a bad one after every few of them (all before the last)."""
    bad = [(leaf, payload) for leaf, payload in MALFORMED]
    bad += [(leaf, _absurd(leaf, fields, 0.0)) for leaf, fields, _ in ABSURD]
    stamp_jump = ("odometry", wire.pack(wire.odometry(ROBOT, 1e9, 0.1, 0.0, 0.0)))
    bad.append(stamp_jump)
    every = (len(inputs) - 2) // len(bad)
    for n, item in enumerate(inputs):
        driver.publish(ROBOT, [item])
        if n % every == every - 1 and bad and n < len(inputs) - 2:
            leaf, payload = bad.pop(0)
            (driver.odometry if leaf == "odometry" else driver.observations).put(payload)
    assert not bad, "the run is too short for every bad input"


def _estimator_status(s: Any, robot: str) -> dict[str, Any] | None:
    """The estimator's ServiceStatus (docs/protocol.md, "The status protocol")."""
    for reply in s.get(f"{wire.PREFIX}/status/**", timeout=wire.GET_TIMEOUT_S):
        if reply.ok is None:
            continue
        status = wire.unpack(reply.ok.payload.to_bytes())
        if status.get("service") == "estimator" and status.get("robot") == robot:
            return dict(status)
    return None


def test_bad_inputs_are_refused_and_counted(router: int) -> None:
    inputs = simulate(seed=31)
    est = estimator(router, ROBOT)
    driver = Driver.open(router, ROBOT, kind="plain", timestamping=False)
    watch = wire.StateWatch(driver.session, ROBOT)
    try:
        _publish_interleaved(driver, inputs)
        final = inputs[-1].stamp
        watch.wait(lambda h: h.get("input_stamp") == final and h.get("step") == "update",
                   "the last input's state")
        head = wire.header(driver.session, ROBOT)
        assert head is not None and head["dropped"] == len(MALFORMED), head
        state = wire.state_of(wire.get_one(driver.session, wire.key(ROBOT, "state")) or b"")
        refused = {k: v for k, v in (state.get("diagnostics") or {}).items()
                   if k.startswith("refused.")}
        want = {f"refused.{reason}": 1.0 for _, _, reason in ABSURD}
        want["refused.stamp_jump"] = 1.0
        assert refused == want, f"diagnostics {state.get('diagnostics')}"
        deadline = time.monotonic() + wire.PATIENCE_S
        while True:  # the status is rebuilt once a second: ask until it says so
            status = _estimator_status(driver.session, ROBOT)
            if status is not None and status.get("dropped") == len(MALFORMED):
                break
            assert time.monotonic() < deadline, f"status {status}"
            time.sleep(0.2)
        missing = [n for n in ("duplicates", "late", "waited", "reordered")
                   if n not in status.get("counts", {})]
        assert not missing, f"slamlens status lacks the counts {missing}: {status}"
        check_final(watch, inputs, {"late": 0, "lost": 0, "dropped": len(MALFORMED)})
    finally:
        watch.close()
        driver.close()
        code = est.stop()
    said = stop_line(est, code)
    assert said["dropped"] == len(MALFORMED), said
