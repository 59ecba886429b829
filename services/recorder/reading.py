"""Reading a recording back: channels, time range and messages, with bad input handled (pure).

:class:`Recording` opens an MCAP file for ``slamlens play``:

* a file that does not exist, or is not MCAP (no magic), is one clear
  :class:`~slamlens.common.errors.SourceError`;
* a file without its summary (a recorder killed with SIGKILL, a copy cut short) is read
  sequentially up to its last complete record, with a warning; its end is then unknown;
* a channel whose message encoding is not ``msgpack`` is skipped (Foxglove channels are
  derived from the others and not played; anything else is counted ``unknown encoding``);
* a message that is not a msgpack map with ``"schema": 1`` is skipped and counted;
* a chunk whose CRC does not match, or compressed with an unknown codec, is a SourceError.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import msgpack
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message
from mcap.stream_reader import CRCValidationError, StreamReader

from slamlens.common.drops import DropCounter
from slamlens.common.errors import SourceError
from slamlens.services.recorder.layout import FOXGLOVE_PREFIX, MESSAGE_ENCODING, check_topic_key

log = logging.getLogger("slamlens.play")

MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class Played:
    """One recorded bus sample to publish again."""

    key: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes


def valid_payload(data: bytes) -> str:
    """'' if ``data`` is a slamlens message (a msgpack map with schema 1), else why not."""
    try:
        raw = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        return f"not msgpack ({type(exc).__name__})"
    if not isinstance(raw, dict):
        return f"a msgpack {type(raw).__name__}, not a map"
    if raw.get("schema") != 1:
        return f"schema {raw.get('schema')!r}, expected 1"
    return ""


class Recording:
    """An MCAP recording opened for playing (module docstring)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f"recording {self.path} does not exist")
        with self.path.open("rb") as f:
            head = f.read(len(MAGIC))
        if head != MAGIC:
            raise SourceError(f"{self.path} is not an MCAP file (it starts with {head[:8]!r}, "
                              f"not the MCAP magic)")
        self.bad = DropCounter(log)
        self.skipped_channels: dict[str, str] = {}  #: topic → why it is not played
        self.channels: dict[int, Channel] = {}
        self.message_count: int | None = None
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.truncated = False
        self._said_cut = False
        summary = None
        try:
            with self.path.open("rb") as f:
                summary = SeekingReader(f).get_summary()
        except (McapError, ValueError, OSError, EOFError, KeyError):
            summary = None
        if summary is None:
            self.truncated = True
            log.warning("%s has no summary (the recorder was killed, or the file is cut "
                        "short): reading it up to its last complete record; no seek index",
                        self.path)
            self._scan_head()
        else:
            self.channels = dict(summary.channels)
            if summary.statistics is not None:
                stats = summary.statistics
                self.message_count = stats.message_count
                if stats.message_count:
                    self.start_ns, self.end_ns = stats.message_start_time, stats.message_end_time
        for channel in self.channels.values():
            self._check_channel(channel)

    def _scan_head(self) -> None:
        """Channels and the first log time of a file without a summary (one pass)."""
        first: int | None = None
        last: int | None = None
        count = 0
        with self.path.open("rb") as f:
            for record in self._records(f):
                if isinstance(record, Channel):
                    self.channels[record.id] = record
                elif isinstance(record, Message):
                    count += 1
                    first = record.log_time if first is None else min(first, record.log_time)
                    last = record.log_time if last is None else max(last, record.log_time)
        self.start_ns, self.end_ns, self.message_count = first, last, count

    def _records(self, f: IO[bytes]) -> Iterator[object]:
        reader = StreamReader(f, validate_crcs=True)
        try:
            yield from reader.records
        except (EndOfFile, EOFError):
            return  # a truncated file ends mid-record: what came before is complete
        except Exception as exc:  # the cut chunk: short, so garbage, a bad CRC or codec
            if self.truncated:
                if not self._said_cut:
                    self._said_cut = True
                    log.warning("%s: read up to its last complete record (then %s: %s)",
                                self.path, type(exc).__name__, str(exc)[:120])
                return
            if isinstance(exc, CRCValidationError):
                raise SourceError(f"{self.path}: a chunk fails its CRC check ({exc})") from None
            raise SourceError(f"{self.path}: unreadable MCAP record "
                              f"({type(exc).__name__}: {str(exc)[:120]})") from None

    def _check_channel(self, channel: Channel) -> None:
        topic = channel.topic
        if topic.startswith(FOXGLOVE_PREFIX):
            self.skipped_channels[topic] = "Foxglove channel (derived, not played)"
        elif channel.message_encoding != MESSAGE_ENCODING:
            self.skipped_channels[topic] = f"unknown message encoding " \
                                           f"{channel.message_encoding!r}"
            log.warning("channel %r: unknown message encoding %r (expected %r): skipped",
                        topic, channel.message_encoding, MESSAGE_ENCODING)
        else:
            try:
                check_topic_key(topic)
            except SourceError as exc:
                self.skipped_channels[topic] = str(exc)
                log.warning("%s: skipped", exc)

    def playable_topics(self) -> list[str]:
        return sorted({c.topic for c in self.channels.values()
                       if c.topic not in self.skipped_channels})

    def messages(self, *, start_ns: int | None = None, end_ns: int | None = None,
                 topics: set[str] | None = None) -> Iterator[Played]:
        """The playable messages in log-time order from ``start_ns`` (inclusive) to
        ``end_ns`` (exclusive), only of ``topics`` if given; bad payloads counted."""
        wanted = set(self.playable_topics()) if topics is None else \
            topics & set(self.playable_topics())
        with self.path.open("rb") as f:
            if self.truncated:
                source = self._truncated_messages(f)
            else:
                source = self._indexed_messages(f, wanted, start_ns, end_ns)
            for channel, message in source:
                if channel.topic not in wanted:
                    continue
                t = message.log_time
                if (start_ns is not None and t < start_ns) or (end_ns is not None
                                                               and t >= end_ns):
                    continue
                why = valid_payload(message.data)
                if why:
                    self.bad.drop(f"message on {channel.topic}", why)
                    continue
                yield Played(channel.topic, t, message.publish_time, bytes(message.data))

    def _indexed_messages(self, f: IO[bytes], topics: set[str], start_ns: int | None,
                          end_ns: int | None) -> Iterator[tuple[Channel, Message]]:
        reader = SeekingReader(f, validate_crcs=True)
        try:
            for _schema, channel, message in reader.iter_messages(
                    topics=sorted(topics), start_time=start_ns, end_time=end_ns,
                    log_time_order=True):
                yield channel, message
        except CRCValidationError as exc:
            raise SourceError(f"{self.path}: a chunk fails its CRC check ({exc})") from None
        except (McapError, ValueError, EOFError) as exc:
            raise SourceError(f"{self.path}: unreadable ({type(exc).__name__}: {exc})") from None

    def _truncated_messages(self, f: IO[bytes]) -> Iterator[tuple[Channel, Message]]:
        for record in self._records(f):
            if isinstance(record, Channel):
                self.channels.setdefault(record.id, record)
            elif isinstance(record, Message):
                channel = self.channels.get(record.channel_id)
                if channel is None:
                    self.bad.drop("message", f"channel id {record.channel_id} never declared")
                    continue
                yield channel, record
