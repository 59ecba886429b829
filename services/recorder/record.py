"""``slamlens record``: what flows on the bus, into an MCAP file (docs/recording.md).

One recovering channel (a ``zenoh.ext`` advanced subscriber with recovery, docs/delivery.md) per
key expression, each read by its own thread; every sample is written at once, under one
lock, as a message of its key's MCAP channel (:mod:`.layout`): the payload byte for byte,
``log_time`` when the recorder took it, ``publish_time`` its Zenoh timestamp. Nothing is
dropped on purpose: a backlog grows in the channel's queue (bounded by memory, counted by the
bus), and what a publisher's cache could not give back is counted ``lost``. Beside them the
Foxglove channels (:mod:`.channels`). The open chunk is written out at least every
``flush_s``, so a recorder killed with SIGKILL leaves a file the MCAP readers read up to its
last complete chunk; SIGINT/SIGTERM write what is queued (up to 1 s of it, the bytes only:
the Foxglove channels get each key's newest), the summary and the footer, and print a final
line.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from slamlens.common.bus import Bus, Channel, Sample
from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError, MessageError
from slamlens.services.recorder.channels import FoxgloveMessage, FoxgloveTranslator
from slamlens.services.recorder.layout import (
    MESSAGE_ENCODING,
    METADATA_NAME,
    PROFILE,
    message_of_key,
    ntp64_to_ns,
    record_expressions,
)
from slamlens.services.recorder.settings import RecordSettings

log = logging.getLogger("slamlens.record")

DRAIN_S = 1.0  #: at a stop, how long the recorder keeps writing what is already queued


def _compression(name: str) -> CompressionType:
    if name == "zstd":
        try:
            import zstandard  # noqa: F401
        except ImportError:  # mcap declares it; a trimmed install may lack it
            log.warning("zstandard is not installed: chunks compressed with lz4 instead")
            return CompressionType.LZ4
        return CompressionType.ZSTD
    return CompressionType.LZ4 if name == "lz4" else CompressionType.NONE


class Recorder:
    """Records the bus into one MCAP file until stopped."""

    def __init__(self, bus: Bus, *, settings: RecordSettings, prefix: str) -> None:
        self.settings = settings
        self.prefix = prefix
        path = Path(settings.path)
        if path.exists() and not settings.overwrite:
            raise ConfigError(f"{path} exists (give --overwrite to replace it)")
        if not path.parent.is_dir():
            raise ConfigError(f"folder {path.parent} does not exist")
        self.path = path
        self._file = path.open("wb")
        self._writer = Writer(self._file, chunk_size=settings.chunk_kb * 1024,
                              compression=_compression(settings.compression),
                              enable_data_crcs=True)
        self._writer.start(profile=PROFILE, library="slamlens record")
        self.expressions = record_expressions(prefix, robots=settings.robot,
                                              cameras=settings.camera, keys=settings.keys)
        self._writer.add_metadata(METADATA_NAME, {
            "prefix": prefix, "keys": json.dumps(self.expressions),
            "started_ns": str(time.time_ns()), "message_encoding": MESSAGE_ENCODING})
        self._lock = threading.Lock()
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._schemas: dict[str, int] = {}
        self._last_time: dict[tuple[str, str], int] = {}
        self._last_log_ns = 0
        self._last_flush = time.monotonic()
        self.translator = (FoxgloveTranslator(settings.scene_settings(), prefix=prefix,
                                              scene_hz=settings.scene_hz)
                           if settings.foxglove else None)
        self.bad = DropCounter(log)
        self.messages = 0  #: bus samples written
        self.foxglove_messages = 0
        self.bytes = 0  #: payload bytes of the bus samples written
        self.duplicates = 0  #: samples seen twice (overlapping key expressions)
        self.per_key: dict[str, int] = {}
        self._subs: list[Channel] = [
            bus.channel(expr, recover=True, history_s=settings.history_s)
            for expr in self.expressions]
        self._closed = False
        self.unwritten = 0  #: samples still queued when the recorder was stopped
        #: per key, the newest sample written at the stop without its Foxglove translation
        self._undrawn: dict[str, tuple[bytes, int]] = {}

    # -- writing ----------------------------------------------------------------------
    def _channel_id(self, key: str) -> int:
        cid = self._channels.get(key)
        if cid is None:
            meta = {"slamlens.prefix": self.prefix}
            kind = message_of_key(key, self.prefix)
            if kind:
                meta["slamlens.message"] = kind
            cid = self._channels[key] = self._writer.register_channel(
                key, MESSAGE_ENCODING, 0, meta)
            self._sequence[cid] = 0
        return cid

    def _foxglove_channel(self, msg: FoxgloveMessage) -> int:
        cid = self._channels.get(msg.topic)
        if cid is None:
            sid = self._schemas.get(msg.schema.name)
            if sid is None:
                sid = self._schemas[msg.schema.name] = self._writer.register_schema(
                    msg.schema.name, msg.schema.encoding, msg.schema.data)
            cid = self._channels[msg.topic] = self._writer.register_channel(
                msg.topic, msg.message_encoding, sid, {"slamlens.derived": "foxglove"})
            self._sequence[cid] = 0
        return cid

    def _add(self, cid: int, data: bytes, log_ns: int, publish_ns: int) -> None:
        seq = self._sequence[cid] = self._sequence[cid] + 1
        self._writer.add_message(cid, log_time=log_ns, data=data, publish_time=publish_ns,
                                 sequence=seq & 0xFFFF_FFFF)

    def write(self, sample: Sample, *, derive: bool = True) -> None:
        """Write one sample (and the Foxglove messages it makes; with ``derive`` False only
        the sample, its key's newest kept for the Foxglove translation at the close)."""
        with self._lock:
            if self._closed:
                return
            if sample.source is not None and sample.time is not None:
                last = self._last_time.get((sample.key, sample.source))
                if last is not None and sample.time <= last:
                    self.duplicates += 1  # the same sample through two expressions
                    return
                self._last_time[(sample.key, sample.source)] = sample.time
            log_ns = max(time.time_ns(), self._last_log_ns)  # log times never go back
            self._last_log_ns = log_ns
            publish_ns = ntp64_to_ns(sample.time) if sample.time is not None else log_ns
            self._add(self._channel_id(sample.key), sample.payload, log_ns, publish_ns)
            self.messages += 1
            self.bytes += len(sample.payload)
            self.per_key[sample.key] = self.per_key.get(sample.key, 0) + 1
            if self.translator is not None and not derive:
                self._undrawn[sample.key] = (sample.payload, log_ns)
            elif self.translator is not None:
                self._undrawn.pop(sample.key, None)
                try:
                    derived = self.translator.feed(sample.key, sample.payload, log_ns)
                except MessageError as exc:
                    self.bad.drop(message_of_key(sample.key, self.prefix) or sample.key,
                                  f"{exc} (recorded as is, no Foxglove message)")
                    derived = []
                self._write_derived(derived)
            if time.monotonic() - self._last_flush >= self.settings.flush_s:
                self._flush_locked()

    def _write_derived(self, derived: list[FoxgloveMessage]) -> None:
        for msg in derived:
            self._add(self._foxglove_channel(msg), msg.data, msg.log_time_ns, msg.log_time_ns)
            self.foxglove_messages += 1

    def _flush_locked(self) -> None:
        self._writer.flush()  # the open chunk out, the file buffer to the OS
        self._last_flush = time.monotonic()

    def flush(self) -> None:
        with self._lock:
            if not self._closed:
                self._flush_locked()

    # -- running ----------------------------------------------------------------------
    def _pump(self, channel: Channel, stop: threading.Event) -> None:
        while not stop.is_set():
            sample = channel.recv(timeout=0.2)
            if sample is not None:
                self.write(sample)
        # what is queued already is still written, as recorded bytes only (cheap: a loaded
        # machine may leave the Foxglove translation far behind); each key's newest is
        # translated at the close, so the file's last scene is the last state's
        deadline = time.monotonic() + DRAIN_S
        while channel.backlog and time.monotonic() < deadline:
            sample = channel.recv(timeout=0.0)
            if sample is None:
                break
            self.write(sample, derive=False)

    @property
    def lost(self) -> int:
        return sum(ch.lost for ch in self._subs)

    @property
    def backlog(self) -> int:
        return sum(ch.backlog for ch in self._subs)

    def run(self, stop: threading.Event, *, ready: threading.Event | None = None) -> None:
        threads = [threading.Thread(target=self._pump, args=(ch, stop), daemon=True,
                                    name=f"record {expr}")
                   for ch, expr in zip(self._subs, self.expressions, strict=True)]
        for t in threads:
            t.start()
        if ready is not None:
            ready.set()
        progress = _Progress(self, enabled=self.settings.progress)
        try:
            while not stop.wait(0.25):
                if time.monotonic() - self._last_flush >= self.settings.flush_s:
                    self.flush()
                progress.update()
        finally:
            for t in threads:
                t.join(timeout=DRAIN_S + 0.5)
            progress.close()
            self.close()

    def close(self) -> None:
        self.unwritten = self.backlog
        if self.unwritten:
            log.warning("stopped with %d samples received and not written: the exit budget "
                        "(2 s) ran out before the recorder caught up", self.unwritten)
        with self._lock:
            if self._closed:
                return
            if self.translator is not None:
                for key, (payload, log_ns) in self._undrawn.items():
                    try:
                        self._write_derived(self.translator.feed(key, payload, log_ns))
                    except MessageError as exc:
                        self.bad.drop(message_of_key(key, self.prefix) or key,
                                      f"{exc} (recorded as is, no Foxglove message)")
                self._write_derived(self.translator.finish())
            self._closed = True
            self._writer.finish()
            self._file.close()
        for ch in self._subs:
            ch.close()

    def summary(self) -> dict[str, Any]:
        return {"file": str(self.path), "messages": self.messages,
                "foxglove_messages": self.foxglove_messages, "bytes": self.bytes,
                "file_bytes": self.path.stat().st_size if self.path.exists() else 0,
                "channels": len(self.per_key), "lost": self.lost,
                "duplicates": self.duplicates, "bad": self.bad.total,
                "unwritten": self.unwritten,
                "scenes": self.translator.scenes if self.translator else 0}


class _Progress:
    """What has been written so far: a tqdm line on a terminal, else a log line every 10 s."""

    def __init__(self, recorder: Recorder, *, enabled: bool) -> None:
        self.recorder = recorder
        self._bar: Any = None
        self._shown = 0
        self._said = time.monotonic()
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(desc=f"recording {recorder.path.name}", unit=" msg",
                             file=sys.stderr, dynamic_ncols=True)

    def update(self) -> None:
        r = self.recorder
        if self._bar is not None:
            self._bar.update(r.messages - self._shown)
            self._shown = r.messages
            self._bar.set_postfix_str(f"{r.bytes / 1e6:.1f} MB, {len(r.per_key)} keys, "
                                      f"lost {r.lost}, backlog {r.backlog}", refresh=False)
        elif time.monotonic() - self._said >= 10.0:
            self._said = time.monotonic()
            log.info("%d messages (%.1f MB) on %d keys written, %d Foxglove messages, "
                     "lost %d, backlog %d", r.messages, r.bytes / 1e6, len(r.per_key),
                     r.foxglove_messages, r.lost, r.backlog)

    def close(self) -> None:
        if self._bar is not None:
            self.update()
            self._bar.close()
