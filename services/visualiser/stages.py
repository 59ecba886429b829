"""The viewer's stages before rendering, each on its own thread, owned by the pipeline.

* ``viewer-decode`` takes each camera's newest frame from its raw slot and decodes it
  (:func:`~slamlens.services.visualiser.decoding.decode_frame`) into the store, no faster
  than the render cap;
* ``viewer-prepare`` takes each robot's newest state (copied out of Zenoh only now),
  decodes it and hands it to ``prepare`` (the pipeline computes the open views' scenes),
  then to ``viewer-layers``;
* ``viewer-layers`` hands it to ``finish`` (over a camera, the pipeline draws it onto its
  layers) while ``viewer-prepare`` takes the next, then leaves it for the render thread
  (:meth:`StateStages.take_prepared`).

At n = 1000 a state's decoding and scenes cost as much as drawing it: two stages, each a
state's half of the work, so on a machine with a core to spare a new state is ready every
max(stage) instead of every sum, while the render thread still puts the previous one's
layers over new camera frames. The next state is taken from Zenoh only once the hand-off
to ``viewer-layers`` is free, so it is the newest when its work begins (a finished state
never waits for another), and the states skipped meanwhile are never copied out.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

from slamlens.common.drops import DropCounter
from slamlens.common.latest import Latest
from slamlens.common.messages import SlamState
from slamlens.services.visualiser.decoding import decode_frame, decode_state
from slamlens.services.visualiser.inputs import LazyRaw, Prepared, RawSource, Wakeups
from slamlens.services.visualiser.store import InputStore

log = logging.getLogger("slamlens.viewer")

#: a state stage's work on one robot's decoded state
StateWork = Callable[[str, SlamState], None]


class StateStages:
    """The decode, prepare and layers threads between the raw slots of ``raw`` and the
    render thread (module docstring). ``prepare`` and ``finish`` are called on
    ``viewer-prepare`` and ``viewer-layers``; an exception there is logged and the state
    goes on (the render thread draws what was not prepared)."""

    def __init__(self, raw: RawSource, store: InputStore, wakeups: Wakeups, *, fps: float,
                 drops: DropCounter, max_frame_pixels: int, summary: bool = False,
                 prepare: StateWork | None = None, finish: StateWork | None = None) -> None:
        self._raw = raw
        self._store = store
        self._wakeups = wakeups
        self._fps = fps
        self._drops = drops
        self._max_frame_pixels = max_frame_pixels
        self._summary = summary  #: states are the robots' summaries (--source summary)
        self._prepare = prepare
        self._finish = finish
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        #: prepared states waiting for ``viewer-layers`` (one at most: the next state is
        #: taken from Zenoh only when it can go on, so it is the newest there is)
        self._handoff: queue.Queue[tuple[str, float, SlamState | None] | None] = \
            queue.Queue(maxsize=1)
        self._handed = threading.Event()  #: ``viewer-layers`` took a state from the handoff
        self._prepared: dict[str, Latest[Prepared]] = {}  #: by robot, for the render thread

    def start(self) -> None:
        loops = [("viewer-decode", self._decode_loop), ("viewer-prepare", self._prepare_loop)]
        if self._finish is not None:
            loops.append(("viewer-layers", self._finish_loop))
        for name, target in loops:
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        self._stop.set()
        self._wakeups.frame.set()
        self._wakeups.state.set()
        self._handed.set()
        try:  # wakes ``viewer-layers`` waiting for a state (a full handoff wakes it anyway)
            self._handoff.put_nowait(None)
        except queue.Full:
            pass
        for thread in self._threads:
            thread.join(timeout=5.0)

    def take_prepared(self, robot: str) -> Prepared | None:
        """The robot's newest state through both stages, once (None: nothing new)."""
        with self._lock:
            slot = self._prepared.get(robot)
        return None if slot is None else slot.take()

    def _slot(self, robot: str) -> Latest[Prepared]:
        with self._lock:
            slot = self._prepared.get(robot)
            if slot is None:
                slot = self._prepared[robot] = Latest(on_put=self._wakeups.input.set)
            return slot

    # -- states -------------------------------------------------------------------
    def _prepare_loop(self) -> None:
        """States: decoded here, newest first (latest wins), handed to ``prepare`` and
        then to ``viewer-layers`` (or, without ``finish``, to the render thread)."""
        wake = self._wakeups.state
        while not self._stop.is_set():
            while self._finish is not None and self._handoff.full() \
                    and not self._stop.is_set():
                self._handed.wait(0.5)
                self._handed.clear()
            wake.wait(0.5)
            wake.clear()
            for r in self._raw.robots():
                taken = r.state_slot.take()
                if taken is None:
                    continue
                try:
                    raw = taken.load() if isinstance(taken, LazyRaw) else taken
                except Exception as exc:  # e.g. the session closing under it
                    self._drops.drop("state", f"payload unreadable ({exc!r:.200})")
                    continue
                state = decode_state(raw, r.name, summary=self._summary, drops=self._drops)
                del raw  # the decoded state holds what it needs of the payload
                if state is not None and self._prepare is not None:
                    try:
                        self._prepare(r.name, state)
                    except Exception:  # preparing is an optimisation: the render draws
                        log.exception("preparing state seq %d failed", state.seq)
                if self._finish is None:
                    self._slot(r.name).put((taken.received, state))
                else:  # only this thread puts: after the wait above there is room
                    self._handoff.put((r.name, taken.received, state))

    def _finish_loop(self) -> None:
        """The second stage (``viewer-layers``): each prepared state to ``finish``, then
        to the render thread."""
        assert self._finish is not None
        while not self._stop.is_set():
            try:
                handed = self._handoff.get(timeout=0.5)
            except queue.Empty:
                continue
            if handed is None:  # stopping
                continue
            robot, received, state = handed
            self._handed.set()
            if state is not None:
                try:
                    self._finish(robot, state)
                except Exception:  # as in preparing: the render thread draws it itself
                    log.exception("finishing state seq %d failed", state.seq)
            self._slot(robot).put((received, state))

    # -- camera frames ------------------------------------------------------------
    def _decode_loop(self) -> None:
        # decode no faster than the render cap: a 60 Hz camera under a 30 fps cap would
        # otherwise spend half its decoding on frames nobody draws (latest wins meanwhile)
        min_interval = 0.9 / self._fps
        last = -float("inf")
        wake = self._wakeups.frame
        while not self._stop.is_set():
            wake.wait(0.5)
            wait = last + min_interval - time.monotonic()
            if wait > 0:
                self._stop.wait(wait)
            wake.clear()
            for cam in self._raw.cameras():
                raw = cam.frame_slot.take()
                if raw is None:
                    continue
                last = time.monotonic()
                source = f"frame {cam.name}"
                try:
                    decoded = decode_frame(cam.name, raw, drops=self._drops,
                                           max_frame_pixels=self._max_frame_pixels,
                                           registered=self._store.registrations(cam.name))
                except Exception as exc:  # a frame nobody foresaw: dropped, decoding goes on
                    self._drops.drop(source, f"undecodable ({exc!r:.200})")
                    continue
                if decoded is not None:
                    image, frame = decoded
                    self._store.put_frame(cam.name, image, frame, raw.received)
                    self._wakeups.input.set()
