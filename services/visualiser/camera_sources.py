"""What the viewer's cameras' sources are doing, from their registration services' status.

A camera unplugged, or a stream that stalled, sends no more frames; its registration
service says why and when it tries again in its status (``slamlens status``,
docs/protocol.md "The status protocol": ``state`` "source lost 12 s ago: … ; retrying
(attempt 4, next in 2.0 s)"). :class:`SourceWatch` asks every registration service's
status every ``period_s`` on its own thread (``viewer-sources``; a query, so it works for
a viewer identity that may publish nothing) and keeps, per camera the viewer shows, the
trouble its service reports: the page shows it under the picture.
"""

from __future__ import annotations

import logging
import threading
import time

from slamlens.common.bus import Bus
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import ServiceStatus

log = logging.getLogger("slamlens.viewer")

TROUBLE = ("source lost", "source ended")  #: the states that are news for the page


class SourceWatch:
    """The newest source trouble of each of ``cameras`` (none: "")."""

    def __init__(self, bus: Bus, keys: Keys, cameras: tuple[str, ...], *,
                 period_s: float = 2.0) -> None:
        self.bus, self.keys = bus, keys
        self.cameras = cameras
        self.period_s = period_s
        self._lock = threading.Lock()
        self._notes: dict[str, str] = {}
        self.asked = 0  #: status queries made
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="viewer-sources", daemon=True)

    def start(self) -> None:
        if self.cameras:
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)

    def notes(self) -> dict[str, str]:
        with self._lock:
            return dict(self._notes)

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self._ask()
            except Exception as exc:  # the session closing under us at shutdown
                log.debug("asking the cameras' status failed: %s", exc)
            self._stop.wait(max(0.1, self.period_s - (time.monotonic() - t0)))

    def _ask(self) -> None:
        notes = {camera: "" for camera in self.cameras}
        for reply in self.bus.get(self.keys.any_status(), timeout=1.0):
            named = self.keys.status_of(reply.key)
            if named is None or named[1] != "registration":
                continue
            try:
                status = ServiceStatus.from_bytes(reply.payload)
            except MessageError as exc:
                log.debug("a registration service's status is malformed: %s", exc)
                continue
            served = set((status.camera or "").split(","))
            for camera in self.cameras:
                base = camera.rsplit("-", 1)[0]
                if (camera in served or base in served) and status.state.startswith(TROUBLE):
                    notes[camera] = f"camera {camera}: {status.state}"
        with self._lock:
            self._notes = notes
        self.asked += 1
