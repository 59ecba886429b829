"""``slamlens rerun``: the live picture from the bus into Rerun (docs/rerun.md).

Inputs — the robot's ``state`` (or, ``--source summary``, its summary stream, pulled one
answer at a time as a remote viewer does), ``health``, ``truth`` and, per ``--camera``, the
camera's ``frame`` and ``registration`` — each land in a one-item slot, newest wins
(:class:`~slamlens.common.latest.Latest`): the Zenoh callbacks only keep a handle on the
newest sample (its payload is copied when the worker takes it), so they never wait, and a
sink (or a viewer behind it) that falls behind skips states instead of queueing them and
never slows the bus. One worker thread takes the newest of each input, turns it into Rerun
archetypes (:mod:`.translator`) and logs them to one ``RecordingStream`` whose sinks are an
``.rrd`` file, a viewer's gRPC endpoint and/or a gRPC server of its own. A message that
does not decode or convert is dropped and counted (one log line per kind, rate-limited).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rerun as rr

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError, MessageError, SlamlensError
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.summary import SummaryQuery
from slamlens.common.summary_pull import SummaryPuller
from slamlens.services.rerun.entities import blueprint
from slamlens.services.rerun.settings import RerunSettings
from slamlens.services.rerun.translator import Batch, RerunTranslator, log_batches

log = logging.getLogger("slamlens.rerun")

APPLICATION_ID = "slamlens"
FLUSH_S = 2.0  #: at the end, how long the sinks get to take what was logged

Fetch = Callable[[], bytes]


def _holding(payload: bytes) -> Fetch:
    """A fetch of a payload already in hand."""
    return lambda: payload


def _keeper(slot: Latest[Fetch]) -> Callable[[str, Fetch], None]:
    """The Zenoh callback of one input: keep the sample's handle in the slot, nothing else."""
    def keep(_key: str, fetch: Fetch) -> None:
        slot.put(fetch)
    return keep


def _summary_keeper(slot: Latest[Fetch]) -> Callable[[bytes, float], None]:
    def keep(payload: bytes, _received: float) -> None:
        slot.put(_holding(payload))
    return keep


class RerunSink:
    """The robot's inputs, newest wins, logged to Rerun by one worker (module docstring)."""

    def __init__(self, bus: Bus, *, settings: RerunSettings, keys: Keys) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = keys
        self.translator = RerunTranslator(settings)
        self.bad = DropCounter(log)
        self.logged = 0  #: log calls made
        self._wake = threading.Event()
        self._slots: dict[str, Latest[Fetch]] = {}
        self.rec = rr.RecordingStream(APPLICATION_ID)
        self.where = self._sinks()
        self._puller: SummaryPuller | None = None
        self._finished = False
        for kind, key in self.inputs():
            slot = self._slots[kind] = Latest(on_put=self._wake.set)
            if kind == "summary":
                self._puller = SummaryPuller(
                    bus, key, SummaryQuery(what="clusters",
                                           threshold_m=settings.cluster_threshold_m,
                                           count=settings.cluster_count,
                                           budget=settings.summary_budget),
                    _summary_keeper(slot), name="rerun-summary")
            else:
                bus.subscribe_lazy(key, _keeper(slot))

    def inputs(self) -> list[tuple[str, str]]:
        """(kind, key) of every input, in the order the worker takes them: the camera and
        the health before the state, so a state is drawn with the newest of them."""
        s, k = self.settings, self.keys
        out = [(f"registration {c}", k.registration(c, s.robot)) for c in s.camera]
        out += [("health", k.health(s.robot))]
        if s.truth:
            out.append(("truth", k.truth(s.robot)))
        out += [(f"frame {c}", k.frame(c)) for c in s.camera]
        out.append(("summary", k.summary(s.robot)) if s.source == "summary"
                   else ("state", k.state(s.robot)))
        return out

    def _sinks(self) -> str:
        """Attach the outputs the settings ask for; what they are, in words."""
        s = self.settings
        sinks: list[Any] = []
        where = []
        if s.save:
            path = Path(s.save)
            if path.exists() and not s.overwrite:
                raise ConfigError(f"{path} exists (give --overwrite to replace it)")
            if not path.parent.is_dir():
                raise ConfigError(f"folder {path.parent} does not exist")
            sinks.append(rr.FileSink(str(path)))
            where.append(f"saving {path}")
        if s.serve:
            try:
                server = rr.GrpcServerSink(bind_ip=s.host, port=s.port,
                                           server_memory_limit=s.serve_memory)
            except Exception as exc:  # the SDK raises its own error types
                raise ConfigError(f"cannot serve Rerun on {s.host}:{s.port}: {exc}") from None
            sinks.append(server)
            where.append(f"serving {server.uri}")
        if s.viewer_url:
            sinks.append(rr.GrpcSink(s.viewer_url))
            where.append(f"streaming to {s.viewer_url}")
        self.rec.set_sinks(*sinks, default_blueprint=blueprint(s.robot, s.camera))
        return ", ".join(where)

    # -- the worker ---------------------------------------------------------------------
    def late_join(self) -> None:
        """The newest state (or summary), health and registrations, by ``get`` (a sink
        started after the run still shows where it is)."""
        timeout = self.settings.late_join_timeout_s
        if timeout <= 0:
            return
        for kind, key in self.inputs():
            if kind.startswith(("frame", "truth", "summary")):
                continue
            for reply in self.bus.get(key, timeout=timeout)[-1:]:
                self._slots[kind].put(_holding(reply.payload))

    def _log(self, batches: list[Batch]) -> None:
        self.logged += log_batches(self.rec, batches)

    def handle(self, kind: str, fetch: Fetch) -> None:
        """One input: translated and logged, or dropped and counted."""
        name = kind.split()[0]
        try:
            self._log(self.translator.feed(name, fetch()))
        except MessageError as exc:
            self.bad.drop(name, str(exc))
        except (SlamlensError, ValueError, TypeError) as exc:  # Rerun refused what we made
            self.bad.drop(name, f"not converted to Rerun: {exc}")

    def step(self) -> int:
        """Take the newest of each input once; how many there were."""
        taken = 0
        for kind, slot in self._slots.items():
            fetch = slot.take()
            if fetch is not None:
                taken += 1
                self.handle(kind, fetch)
        return taken

    def run(self, stop: threading.Event) -> None:
        """Log the newest of each input as it comes, until ``stop``."""
        self._log(self.translator.start())
        if self._puller is not None:
            self._puller.start()
        while not stop.is_set():
            self._wake.wait(0.2)
            self._wake.clear()
            self.step()

    @property
    def superseded(self) -> int:
        """Inputs replaced by a newer one before the worker took them."""
        return sum(slot.dropped for slot in self._slots.values())

    def summary(self) -> dict[str, Any]:
        t = self.translator
        return {"where": self.where, "drawn": t.drawn, "glyphs": t.glyphs,
                "maps": t.maps, "logged": self.logged, "bad": self.bad.total,
                "bad_by_kind": dict(self.bad.counts),
                "rate_skipped": t.skipped, "early_frames": t.early,
                "received": {k: s.count for k, s in self._slots.items()},
                "superseded": {k: s.dropped for k, s in self._slots.items()}}

    def finish(self) -> None:
        """Stop taking input and log the final paths (idempotent)."""
        if self._finished:
            return
        self._finished = True
        if self._puller is not None:
            self._puller.stop()
        for slot in self._slots.values():
            slot.close()
        self._log(self.translator.finish())

    def close(self) -> None:
        """:meth:`finish`, then let the sinks take what was logged (the file gets its
        footer; a viewer that never answered is given up after Rerun's own wait)."""
        try:
            self.finish()
            self.rec.flush(timeout_sec=FLUSH_S)
        finally:
            self.rec.disconnect()
