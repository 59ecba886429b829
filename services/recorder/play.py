"""``slamlens play``: a recording published back on the bus (docs/recording.md).

Every recorded key is published again on itself, the payload byte for byte, as the live
service published it (docs/delivery.md): inputs and states through advanced publishers with caches
(a consumer that needs everything recovers what it missed), camera frames best effort; the
newest ``state``, ``health`` and ``registration`` also answer a ``get``, so a viewer that
joins late shows the current picture at once. Timing is the recorded log times × ``rate``
(0: no timing; with ``--inputs-only`` paced on the estimator, :class:`slamlens.common.pacer.Pacer`).

``--inputs-only`` publishes only odometry and observations, renumbered from 1 with one
``input_seq`` counter over both keys per robot (as a driver does), for a fresh estimator.

Before it starts, the player looks for a live estimator of each robot it plays
(liveliness ``…/alive/estimator``): a full playback would mix its states with the
recording's, so it refuses unless ``--mix``; ``--inputs-only`` instead waits for one and
refuses one that has already applied inputs (not fresh) unless ``--mix``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import msgpack

from slamlens.common.bus import Bus, Publisher
from slamlens.common.errors import ConfigError, MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import peek_fields
from slamlens.common.pacer import Pacer
from slamlens.services.recorder.layout import message_of_key
from slamlens.services.recorder.reading import Played, Recording
from slamlens.services.recorder.settings import PlaySettings
from slamlens.services.recorder.timeline import PlayClock

log = logging.getLogger("slamlens.play")

INPUT_CACHE = 10_000  #: as a driver's (docs/delivery.md: at least 10 000 samples and 60 s)
STATE_CACHE = 10_000  #: as the estimator's
STATE_CACHE_BYTES = 256 << 20
INPUTS = ("Odometry", "Observations")
SERVED = ("SlamState", "Health", "Registration")


def _matches(expr: str, key: str) -> bool:
    import zenoh

    return bool(zenoh.KeyExpr(expr).intersects(zenoh.KeyExpr(key)))


class Player:
    """Plays one recording on a bus (module docstring); ``control`` commands are
    thread-safe (the control page calls them)."""

    def __init__(self, bus: Bus, *, settings: PlaySettings, keys: Keys,
                 recording: Recording | None = None) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = keys
        self.recording = recording if recording is not None else Recording(settings.path)
        topics = self.recording.playable_topics()
        if settings.robot:
            topics = [t for t in topics if keys.robot_of(t) in settings.robot]
        if settings.keys:
            topics = [t for t in topics if any(_matches(e, t) for e in settings.keys)]
        if settings.inputs_only:
            topics = [t for t in topics if message_of_key(t, keys.prefix) in INPUTS]
        if not topics:
            raise ConfigError(f"{settings.path}: nothing to play (recorded keys: "
                              f"{', '.join(self.recording.playable_topics()) or 'none'})")
        self.topics = topics
        self.robots = sorted({r for t in topics if (r := keys.robot_of(t)) is not None})
        start = self.recording.start_ns or 0
        self.origin_ns = start
        self.start_ns = start + int(settings.start_s * 1e9)
        self.end_ns = start + int(settings.end_s * 1e9) if settings.end_s else None
        self._pubs: dict[str, Publisher] = {}
        self._latest: dict[str, bytes] = {}
        self._input_seq: dict[str, int] = {}
        self._pacers: dict[str, Pacer] = {}
        self._lock = threading.Lock()
        self._changed = threading.Event()
        self.clock = PlayClock(rate=settings.rate, anchor_pos_ns=self.start_ns,
                               anchor_wall=time.monotonic(), paused=settings.paused)
        self._seek_to: int | None = None
        self.published = 0
        self.per_kind: dict[str, int] = {}
        self.loops = 0
        self.finished = False

    # -- before playing -----------------------------------------------------------------
    def check_estimators(self, stop: threading.Event) -> None:
        """Refuse (ConfigError) or warn about live estimators (module docstring)."""
        for robot in self.robots:
            key = self.keys.estimator_alive(robot)
            if self.settings.inputs_only:
                self._wait_for_estimator(robot, stop)
                replies = self.bus.get(self.keys.state(robot), timeout=2.0)
                seq = max((int(peek_fields(r.payload, ("seq",)).get("seq", 0) or 0)
                           for r in replies), default=0)
                if seq > 0:
                    text = (f"the estimator of robot {robot!r} has already applied {seq} "
                            f"inputs: it is not fresh, and the recording's inputs would be "
                            f"folded into its map")
                    if not self.settings.mix:
                        raise ConfigError(f"{text} (restart it, or give --mix)")
                    log.warning("%s (--mix: playing anyway)", text)
            elif self.bus.alive(key, timeout=1.0):
                text = (f"an estimator is live for robot {robot!r}: its states and the "
                        f"recording's would mix on {self.keys.state(robot)}")
                if not self.settings.mix:
                    raise ConfigError(f"{text} (stop it, give --inputs-only to feed it the "
                                      f"recorded inputs, or --mix to play anyway)")
                log.warning("%s (--mix: playing anyway)", text)

    def _wait_for_estimator(self, robot: str, stop: threading.Event) -> None:
        key = self.keys.estimator_alive(robot)
        deadline = time.monotonic() + self.settings.wait_timeout_s
        said = False
        while not stop.is_set():
            if self.bus.alive(key, timeout=1.0):
                left = max(0.1, deadline - time.monotonic())
                for k in (self.keys.odometry(robot), self.keys.observations(robot)):
                    self.bus.wait_for_subscriber(k, timeout=left)
                return
            if not said:
                log.info("waiting for an estimator on %s", key)
                said = True
            if time.monotonic() >= deadline:
                raise ConfigError(f"no estimator for robot {robot!r} appeared within "
                                  f"{self.settings.wait_timeout_s:g} s")
            stop.wait(0.1)

    # -- control (thread-safe) ------------------------------------------------------------
    def pause(self) -> None:
        with self._lock:
            self.clock.pause(time.monotonic())
        self._changed.set()

    def resume(self) -> None:
        with self._lock:
            self.clock.resume(time.monotonic())
        self._changed.set()

    def seek(self, seconds: float) -> None:
        """Go to ``seconds`` after the start of the recording."""
        target = self.origin_ns + int(max(0.0, seconds) * 1e9)
        with self._lock:
            self._seek_to = target
            self.clock.seek(target, time.monotonic())
        self._changed.set()

    def set_rate(self, rate: float) -> None:
        if not rate >= 0:
            raise ConfigError(f"rate {rate!r} must be ≥ 0")
        with self._lock:
            self.clock.set_rate(rate, time.monotonic())
        self._changed.set()

    def status(self) -> dict[str, Any]:
        with self._lock:
            pos = self.clock.position_ns(time.monotonic())
            rate, paused = self.clock.rate, self.clock.paused
        end = self.end_ns or self.recording.end_ns
        return {"file": str(self.recording.path), "position_s": (pos - self.origin_ns) / 1e9,
                "duration_s": None if end is None else (end - self.origin_ns) / 1e9,
                "rate": rate, "paused": paused, "published": self.published,
                "loops": self.loops, "finished": self.finished,
                "inputs_only": self.settings.inputs_only, "keys": self.topics}

    # -- publishing -----------------------------------------------------------------------
    def _publisher(self, key: str, kind: str) -> Publisher:
        pub = self._pubs.get(key)
        if pub is None:
            if kind in INPUTS:
                pub = self.bus.publisher(key, cache=INPUT_CACHE)
            elif kind == "SlamState":
                pub = self.bus.publisher(key, cache=STATE_CACHE, cache_bytes=STATE_CACHE_BYTES)
            elif kind == "Health":
                pub = self.bus.publisher(key, cache=STATE_CACHE)
            elif kind == "CameraFrame":
                pub = self.bus.publisher(key, latest_wins=True)
            else:
                pub = self.bus.publisher(key)
            if kind in SERVED:
                self.bus.serve_latest(key, self._provider(key))
            self._pubs[key] = pub
        return pub

    def _provider(self, key: str) -> Callable[[], bytes | None]:
        return lambda: self._latest.get(key)

    def _renumber(self, robot: str, data: bytes) -> tuple[bytes, float]:
        raw = msgpack.unpackb(data, raw=False, strict_map_key=False)
        seq = self._input_seq[robot] = self._input_seq.get(robot, 0) + 1
        raw["input_seq"] = seq
        stamp = raw.get("stamp")
        if not isinstance(stamp, (int, float)):
            raise MessageError("input", "stamp", "a number", repr(stamp))
        return msgpack.packb(raw, use_bin_type=True), float(stamp)

    def publish(self, msg: Played, stop: threading.Event) -> None:
        kind = message_of_key(msg.key, self.keys.prefix)
        data = msg.data
        if self.settings.inputs_only:
            robot = self.keys.robot_of(msg.key) or ""
            try:
                data, stamp = self._renumber(robot, data)
            except MessageError as exc:
                self.recording.bad.drop(kind, str(exc))
                return
            if self.settings.rate == 0 and self.clock.rate == 0:
                pacer = self._pacers.get(robot)
                if pacer is None:
                    pacer = self._pacers[robot] = Pacer(self.bus, keys=self.keys, robot=robot)
                pacer.before(stamp, stop)
        if kind in SERVED:
            self._latest[msg.key] = data
        self._publisher(msg.key, kind).put(data)
        self.published += 1
        self.per_kind[kind or msg.key] = self.per_kind.get(kind or msg.key, 0) + 1

    # -- the loop -------------------------------------------------------------------------
    def _wait_until_due(self, msg: Played, stop: threading.Event) -> bool:
        """Wait until ``msg`` is due (False: a control change or a stop came first)."""
        while not stop.is_set():
            with self._lock:
                if self._seek_to is not None:
                    return False
                paused = self.clock.paused
                due = self.clock.due(msg.log_time_ns)
            wait = 0.2 if paused else due - time.monotonic()
            if wait <= 0:
                return True
            self._changed.wait(min(wait, 0.2))
            self._changed.clear()
        return False

    def run(self, stop: threading.Event) -> float:
        """Play until the end (or forever with --loop) or ``stop``; wall seconds."""
        started = time.monotonic()
        position = self.start_ns
        wanted = set(self.topics)
        while not stop.is_set():
            with self._lock:
                self.clock.seek(position, time.monotonic())
                self._seek_to = None
            restarted = False
            for msg in self.recording.messages(start_ns=position, end_ns=self.end_ns,
                                               topics=wanted):
                if not self._wait_until_due(msg, stop):
                    if stop.is_set():
                        break
                    with self._lock:
                        position = self._seek_to if self._seek_to is not None else position
                    restarted = True
                    break
                self.publish(msg, stop)
                with self._lock:
                    self.clock.played(msg.log_time_ns)
            if stop.is_set():
                break
            if restarted:
                continue
            if not self.settings.loop:
                break
            self.loops += 1
            position = self.start_ns
        self.finished = not stop.is_set()
        return time.monotonic() - started

    def drain(self, stop: threading.Event, *, timeout_s: float = 10.0) -> bool:
        """--inputs-only at rate 0: wait until the estimators applied everything."""
        return all(p.drain(stop, timeout_s=timeout_s) for p in self._pacers.values())

    def summary(self) -> dict[str, Any]:
        return {"published": self.published, **self.per_kind, "loops": self.loops,
                "bad": self.recording.bad.total,
                "skipped_channels": len(self.recording.skipped_channels),
                "truncated": self.recording.truncated}

    def close(self) -> None:
        for pacer in self._pacers.values():
            pacer.close()
