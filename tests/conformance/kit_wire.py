"""The wire of docs/protocol.md, written from the document: messages as msgpack maps,
arrays as ``{dtype, shape, data}``, Zenoh sessions, the publisher variants, and waiting
for the estimator's state by what it says (seq, input_stamp), never by time.

Only zenoh, msgpack, numpy and the standard library: no project code.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import msgpack
import numpy as np
import zenoh
import zenoh.ext as zext

PREFIX = "slamlens"
SCHEMA = 1
#: how long a failing wait may take before the test says so (a bound, never a pacing)
PATIENCE_S = 90.0
#: how long a ``get`` may wait for its answers: a bound only (a get with no queryable to ask
#: ends at once; one whose queryable answers ends when it did), so generous: a loaded
#: machine may take seconds to schedule the answering thread
GET_TIMEOUT_S = 30.0


# -- messages --------------------------------------------------------------------------
def array(values: Any, dtype: str) -> dict[str, Any]:
    """An array field: little-endian dtype, shape, C-order bytes."""
    a = np.ascontiguousarray(values, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def unarray(raw: Any) -> np.ndarray:
    """An array field back (the map form; a plain list is accepted too)."""
    if isinstance(raw, dict):
        return np.frombuffer(raw["data"], dtype=np.dtype(raw["dtype"])).reshape(raw["shape"])
    return np.asarray(raw)


def pack(message: dict[str, Any]) -> bytes:
    return msgpack.packb({"schema": SCHEMA, **message}, use_bin_type=True)


def unpack(payload: bytes) -> Any:
    return msgpack.unpackb(payload, raw=False, strict_map_key=False)


def odometry(robot: str, stamp: float, dt: float, v: float, w: float,
             input_seq: int | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"robot": robot, "stamp": stamp, "dt": dt, "v": v, "w": w}
    if input_seq is not None:
        out["input_seq"] = input_seq
    return out


def observations(robot: str, stamp: float, ids: Iterable[int], ranges: Iterable[float],
                 bearings: Iterable[float], input_seq: int | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"robot": robot, "stamp": stamp,
                           "ids": array(list(ids), "<i8"), "ranges": array(list(ranges), "<f8"),
                           "bearings": array(list(bearings), "<f8")}
    if input_seq is not None:
        out["input_seq"] = input_seq
    return out


def state_of(payload: bytes) -> dict[str, Any]:
    """A SlamState's fields, its arrays as numpy (the covariance square, N × N)."""
    raw = unpack(payload)
    out = dict(raw)
    for name in ("pose", "landmark_ids", "landmarks", "covariance", "observed_ids", "new_ids"):
        if name in raw:
            out[name] = unarray(raw[name])
    n = len(out["landmark_ids"])
    out["covariance"] = out["covariance"].reshape(3 + 2 * n, 3 + 2 * n)
    out["landmarks"] = out["landmarks"].reshape(n, 2)
    return out


def key(robot: str, leaf: str) -> str:
    return f"{PREFIX}/robot/{robot}/{leaf}"


# -- sessions and publishers -------------------------------------------------------------
def session(port: int, *, timestamping: bool = True) -> zenoh.Session:
    """A client session of the router on 127.0.0.1:``port``, multicast scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true" if timestamping else "false")
    return zenoh.open(conf)


def wait_matched(s: zenoh.Session, key_expr: str, timeout: float = PATIENCE_S) -> None:
    """Until a subscriber matches ``key_expr`` (Zenoh's matching status: an event)."""
    probe = s.declare_publisher(key_expr)
    try:
        done = threading.Event()
        listener = probe.declare_matching_listener(
            lambda status: done.set() if status.matching else None)
        if not probe.matching_status.matching and not done.wait(timeout):
            raise AssertionError(f"no subscriber of {key_expr} appeared")
        listener.undeclare()
    finally:
        probe.undeclare()


def plain(s: zenoh.Session, key_expr: str) -> Any:
    """A plain reliable publisher with congestion control BLOCK."""
    return s.declare_publisher(key_expr, congestion_control=zenoh.CongestionControl.BLOCK,
                               reliability=zenoh.Reliability.RELIABLE)


def advanced(s: zenoh.Session, key_expr: str, cache: int = 10_000) -> Any:
    """A zenoh.ext advanced publisher: cache, sample-miss detection with heartbeat,
    publisher detection (the session must have timestamping on)."""
    return zext.declare_advanced_publisher(
        s, key_expr, cache=zext.CacheConfig(cache),
        sample_miss_detection=zext.MissDetectionConfig(heartbeat=0.5),
        publisher_detection=True)


def header(s: zenoh.Session, robot: str, timeout: float = GET_TIMEOUT_S) -> dict[str, Any] | None:
    """The answer to ``get …/state?header`` (None if nobody answered)."""
    for reply in s.get(f"{key(robot, 'state')}?header", timeout=timeout):
        if reply.ok is not None:
            return dict(unpack(reply.ok.payload.to_bytes()))
    return None


def get_one(s: zenoh.Session, key_expr: str, timeout: float = GET_TIMEOUT_S) -> bytes | None:
    """The payload of the first good reply to a ``get`` (None if nobody answered)."""
    for reply in s.get(key_expr, timeout=timeout):
        if reply.ok is not None:
            return bytes(reply.ok.payload.to_bytes())
    return None


class StateWatch:
    """What the estimator of one robot published last: a subscriber on its state key that
    keeps the header fields of every state, and a waiter on a condition of them."""

    FIELDS = ("seq", "stamp", "step", "epoch", "input_stamp")

    def __init__(self, s: zenoh.Session, robot: str) -> None:
        self.session = s
        self.robot = robot
        self.seen: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        self._sub = s.declare_subscriber(key(robot, "state"), self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        raw = unpack(sample.payload.to_bytes())
        with self._cond:
            self.seen.append({k: raw.get(k) for k in self.FIELDS})
            self._cond.notify_all()

    def wait(self, done: Callable[[dict[str, Any]], bool], what: str,
             timeout: float = PATIENCE_S) -> dict[str, Any]:
        """The first state header (received, or answered to ``state?header``) for which
        ``done`` holds. Every state received wakes it; when none came for a second the
        header is asked, in case the subscriber missed the state (a plain subscriber may)."""
        deadline = time.monotonic() + timeout
        checked = 0
        quiet = False
        asked: dict[str, Any] | None = None
        while True:
            with self._cond:
                fresh = self.seen[checked:]
                checked = len(self.seen)
            for h in fresh:
                if done(h):
                    return h
            if quiet:  # nothing received for a while: ask
                asked = header(self.session, self.robot)
                if asked is not None and done(asked):
                    return asked
            left = deadline - time.monotonic()
            if left <= 0:
                last = self.seen[-1] if self.seen else None
                raise AssertionError(f"no state of {self.robot} with {what}; last received "
                                     f"{last}, last header {asked}")
            with self._cond:
                quiet = len(self.seen) == checked and not self._cond.wait(min(left, 1.0))

    def close(self) -> None:
        self._sub.undeclare()


class LockStep:
    """A third party's states of one robot, in lock step with the monitor: every Health of
    the robot heard, by seq; :meth:`exchange` puts a state and returns the monitor's Health
    of it (docs/protocol.md: the monitor answers each state it checks with a Health)."""

    def __init__(self, s: zenoh.Session, robot: str) -> None:
        self.states = plain(s, key(robot, "state"))
        self.healths: dict[int, dict[str, Any]] = {}
        self._heard = threading.Condition()
        self._sub = s.declare_subscriber(key(robot, "health"), self._on_health)

    def _on_health(self, sample: Any) -> None:
        health = unpack(sample.payload.to_bytes())
        with self._heard:
            self.healths[int(health["seq"])] = health
            self._heard.notify_all()

    def exchange(self, state: bytes, seq: int) -> dict[str, Any]:
        """Put ``state`` (of ``seq``) until its Health is heard — again if unheard: a late
        subscriber, a lost sample — and return that Health."""
        with self._heard:
            for _ in range(int(PATIENCE_S / 5)):
                self.states.put(state)
                if self._heard.wait_for(lambda: seq in self.healths, 5.0):
                    return self.healths[seq]
        raise AssertionError(f"no Health for seq {seq}")
