"""A real robot on a serial line: the wire protocol, its parser, and a reconnecting link.

Wire protocol (robot → host; full description in ``docs/drivers.md``): ASCII records, one
per line, NMEA style::

    $O,<stamp>,<dt>,<v>,<w>*HH                                   odometry
    $Z,<stamp>,<k>,<id1>,<range1>,<bearing1>,...,<idk>,<rangek>,<bearingk>*HH   observations

``$`` starts a record, ``*`` ends its body, ``HH`` is the XOR of every byte strictly between
``$`` and ``*`` as two hex digits, and the line ends with ``\\n`` (``\\r\\n`` accepted).
Numbers are decimal (SI units, radians; stamp and dt in seconds); ids are integers, −1 for
"unknown, associate it yourself". ``k = 0`` is an empty batch.

:class:`SerialParser` is pure: feed it bytes, get messages. Garbage, partial lines, bad
checksums, NaN, wrong counts, out-of-range values and unknown record types are dropped and
counted in ``parser.stats``; it never raises. :class:`SerialLink` wraps pyserial's
``serial_for_url`` (a device path, ``loop://``, ``socket://host:port``, …) and reopens the
port with exponential backoff (:class:`~slamlens.common.backoff.Backoff`) when it vanishes.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields

import numpy as np
import serial

from slamlens.common.backoff import Backoff
from slamlens.common.errors import MessageError, SlamlensError, SourceError
from slamlens.common.messages import Observations, Odometry

log = logging.getLogger("slamlens.serial")

Message = Odometry | Observations

MAX_LINE_BYTES = 4096  #: longer lines are dropped (≈ 130 observations per batch at most)

#: Every parsed field must lie in its range (inclusive), else the record is dropped
#: (``out_of_range``). These are representation bounds, far beyond any real robot: a value
#: outside is a corrupted line whose checksum happened to match, or a firmware bug. What is
#: plausible for the robot is the estimator's plausibility gates' business (finer, and
#: configurable: docs/estimator.md).
FIELD_RANGES: dict[str, tuple[float, float]] = {
    "stamp": (0.0, 1e11),  # s: robot clock, ≈ 3000 years
    "dt": (0.0, 1e5),  # s
    "v": (-1e3, 1e3),  # m/s
    "w": (-1e3, 1e3),  # rad/s
    "id": (-1, 2 ** 63 - 1),  # int64; −1 = unknown
    "range": (0.0, 1e6),  # m
    "bearing": (-1e3, 1e3),  # rad
}


def checksum(body: bytes) -> str:
    """XOR of ``body``'s bytes as two upper-case hex digits."""
    value = 0
    for byte in body:
        value ^= byte
    return f"{value:02X}"


def _record(body: str) -> bytes:
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + checksum(raw).encode("ascii") + b"\r\n"


def encode_odometry(message: Odometry) -> bytes:
    """The ``$O`` record of an odometry message (floats in shortest round-trip form)."""
    return _record(f"O,{message.stamp!r},{message.dt!r},{message.v!r},{message.w!r}")


def encode_observations(message: Observations) -> bytes:
    """The ``$Z`` record of an observation batch."""
    triples = "".join(f",{int(i)},{float(r)!r},{float(b)!r}" for i, r, b in
                      zip(message.ids, message.ranges, message.bearings, strict=True))
    return _record(f"Z,{message.stamp!r},{message.ids.shape[0]}{triples}")


def encode(message: Message) -> bytes:
    """The record of either message type (what a robot's firmware would send)."""
    if isinstance(message, Odometry):
        return encode_odometry(message)
    return encode_observations(message)


@dataclass
class SerialStats:
    """Counters of a parser: what was read, kept and dropped (and why)."""

    bytes: int = 0  #: bytes fed
    odometry: int = 0  #: odometry records accepted
    observations: int = 0  #: observation records accepted
    garbage_bytes: int = 0  #: bytes outside any record
    bad_checksum: int = 0  #: records whose checksum did not match
    malformed: int = 0  #: no ``*HH``, not ASCII, not numbers, wrong field count
    non_finite: int = 0  #: NaN or infinity in a field
    bad_count: int = 0  #: ``$Z`` whose k does not match its fields
    invalid: int = 0  #: negative dt or range, id below −1
    out_of_range: int = 0  #: a field outside FIELD_RANGES (an id beyond int64, 1e308 …)
    unknown_type: int = 0  #: record types other than O and Z
    overflow: int = 0  #: lines longer than the maximum, dropped
    partial: int = 0  #: unfinished lines thrown away by ``reset`` (reconnects)

    @property
    def dropped(self) -> int:
        """Records (or lines) rejected, whatever the reason."""
        return (self.bad_checksum + self.malformed + self.non_finite + self.bad_count
                + self.invalid + self.out_of_range + self.unknown_type + self.overflow
                + self.partial)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class _Reject(SlamlensError):
    """A line the parser drops: ``reason`` is the stats counter, the message the detail."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def _float(text: str, name: str = "") -> float:
    try:
        value = float(text)
    except ValueError:
        raise _Reject("malformed", f"not a number: {text[:20]!r}") from None
    if not math.isfinite(value):
        raise _Reject("non_finite", f"non-finite value {text!r}")
    if name:
        _check_range(name, value)
    return value


def _int(text: str, name: str = "") -> int:
    if len(text) > 24:  # int() of a huge digit string is slow and no field needs one
        raise _Reject("out_of_range" if text.lstrip("+-").isdigit() else "malformed",
                      f"integer of {len(text)} characters")
    try:
        value = int(text)
    except ValueError:
        raise _Reject("malformed", f"not an integer: {text[:20]!r}") from None
    if name:
        _check_range(name, value)
    return value


def _check_range(name: str, value: float) -> None:
    lo, hi = FIELD_RANGES[name]
    if not lo <= value <= hi:
        raise _Reject("out_of_range" if name != "id" or value > hi else "invalid",
                      f"{name} {value!r} outside [{lo:g}, {hi:g}]")


class SerialParser:
    """Bytes in, messages out; bad input is dropped and counted, never raised."""

    def __init__(self, robot: str, *, max_line_bytes: int = MAX_LINE_BYTES) -> None:
        self.robot = robot
        self.max_line_bytes = max_line_bytes
        self.stats = SerialStats()
        self._buffer = bytearray()
        self._warned: set[str] = set()

    def feed(self, data: bytes) -> list[Message]:
        """Parse ``data`` (any chunking); returns the complete, valid records in it."""
        self.stats.bytes += len(data)
        self._buffer += data
        out: list[Message] = []
        while True:
            end = self._buffer.find(b"\n")
            if end < 0:
                break
            line = bytes(self._buffer[:end])
            del self._buffer[:end + 1]
            if len(line) > self.max_line_bytes:
                self._drop("overflow", f"line of {len(line)} bytes")
                continue
            message = self._line(line.rstrip(b"\r"))
            if message is not None:
                out.append(message)
        if len(self._buffer) > self.max_line_bytes:
            # keep a record that may be starting; throw away the rest
            start = self._buffer.rfind(b"$")
            keep = start >= 0 and len(self._buffer) - start <= self.max_line_bytes
            self._drop("overflow", f"{len(self._buffer)} bytes without a newline")
            self._buffer = self._buffer[start:] if keep else bytearray()
        return out

    def reset(self) -> None:
        """Forget an unfinished line (the port was reopened: its end will never come)."""
        if self._buffer.strip():
            self.stats.partial += 1
        self._buffer.clear()

    # -- one line --------------------------------------------------------------------
    def _line(self, line: bytes) -> Message | None:
        if not line.strip():
            return None
        start = line.rfind(b"$")  # the last '$': garbage before a record is skipped
        if start < 0:
            self.stats.garbage_bytes += len(line)
            return None
        self.stats.garbage_bytes += start
        record = line[start + 1:]
        star = record.rfind(b"*")
        if star < 0 or len(record) - star - 1 != 2:
            self._drop("malformed", f"no *HH checksum in {record[:40]!r}")
            return None
        body, given = record[:star], record[star + 1:]
        try:
            given_value = int(given.decode("ascii"), 16)
        except (UnicodeDecodeError, ValueError):
            self._drop("malformed", f"checksum {given!r} is not hex")
            return None
        if f"{given_value:02X}" != checksum(body):
            self._drop("bad_checksum", f"{given!r} != {checksum(body)} for {body[:40]!r}")
            return None
        try:
            text = body.decode("ascii")
            return self._record(text.split(","))
        except UnicodeDecodeError:
            self._drop("malformed", "non-ASCII bytes")
        except _Reject as exc:
            self._drop(exc.reason, str(exc))
        except MessageError as exc:  # anything the message's own validation still refuses
            self._drop("invalid", str(exc))
        except (ValueError, OverflowError, TypeError) as exc:  # never raise (docs/drivers.md)
            self._drop("malformed", f"{type(exc).__name__}: {exc}")
        return None

    def _record(self, parts: list[str]) -> Message:
        kind = parts[0]
        if kind == "O":
            if len(parts) != 5:
                raise _Reject("malformed", f"$O has {len(parts) - 1} fields, expected 4")
            if _float(parts[2]) < 0:
                raise _Reject("invalid", f"negative dt {parts[2]}")
            stamp, dt, v, w = (_float(p, name) for p, name in
                               zip(parts[1:], ("stamp", "dt", "v", "w"), strict=True))
            self.stats.odometry += 1
            return Odometry(robot=self.robot, stamp=stamp, dt=dt, v=v, w=w)
        if kind == "Z":
            if len(parts) < 3:
                raise _Reject("malformed", "$Z without stamp and count")
            stamp, k = _float(parts[1], "stamp"), _int(parts[2])
            if k < 0 or len(parts) != 3 + 3 * k:
                raise _Reject("bad_count", f"k = {k} but {len(parts) - 3} fields follow")
            triples = parts[3:]
            id_list = [_int(p) for p in triples[0::3]]
            range_list = [_float(p) for p in triples[1::3]]
            if any(i < -1 for i in id_list) or any(r < 0 for r in range_list):
                raise _Reject("invalid", "id below −1 or negative range")
            for i in id_list:
                _check_range("id", i)
            for r in range_list:
                _check_range("range", r)
            ids = np.array(id_list, dtype=np.int64)
            ranges = np.array(range_list)
            bearings = np.array([_float(p, "bearing") for p in triples[2::3]])
            self.stats.observations += 1
            return Observations(robot=self.robot, stamp=stamp, ids=ids, ranges=ranges,
                                bearings=bearings)
        raise _Reject("unknown_type", f"record type {kind[:10]!r}")

    def _drop(self, reason: str, detail: str) -> None:
        setattr(self.stats, reason, getattr(self.stats, reason) + 1)
        if reason not in self._warned:  # one line per kind of fault; the rest are counted
            self._warned.add(reason)
            log.warning("serial %s: dropped a record (%s: %s); further ones are counted",
                        self.robot, reason, detail)
        else:
            log.debug("serial %s: dropped (%s: %s)", self.robot, reason, detail)


@dataclass
class LinkStats:
    """Counters of a link's connection."""

    opens: int = 0  #: successful opens (the first and every reconnect)
    open_failures: int = 0  #: attempts that failed
    disconnects: int = 0  #: times an open port failed and was closed


Opener = Callable[..., serial.SerialBase]


class SerialLink:
    """A robot on a serial port: reopens it with backoff when it vanishes.

    Call :meth:`read` in a loop (or iterate :meth:`messages`); it never raises for a missing
    or failing port, only for a URL pyserial cannot understand (:class:`SourceError`).
    """

    def __init__(self, port_url: str, *, baudrate: int = 115200, robot: str = "robot1",
                 read_timeout_s: float = 0.1, backoff_initial_s: float = 0.2,
                 backoff_max_s: float = 5.0, opener: Opener = serial.serial_for_url) -> None:
        self.port_url = port_url
        self.baudrate = baudrate
        self.read_timeout_s = read_timeout_s
        self.parser = SerialParser(robot)
        self.link_stats = LinkStats()
        self.backoff = Backoff(f"serial {port_url}", logger=log, initial_s=backoff_initial_s,
                               max_s=backoff_max_s)
        self._opener = opener
        self._port: serial.SerialBase | None = None

    @property
    def connected(self) -> bool:
        return self._port is not None

    @property
    def stats(self) -> dict[str, int]:
        """Parser and link counters in one flat mapping (for logs and health)."""
        link = {f.name: getattr(self.link_stats, f.name) for f in fields(self.link_stats)}
        return {**self.parser.stats.as_dict(), **link}

    def open(self) -> bool:
        """Try to open the port now (ignoring the backoff); True when it is open."""
        if self._port is not None:
            return True
        try:
            port = self._opener(self.port_url, baudrate=self.baudrate,
                                timeout=self.read_timeout_s)
        except ValueError as exc:  # pyserial's answer to a URL it cannot parse: not transient
            raise SourceError(f"serial port {self.port_url!r}: {exc}") from None
        except (serial.SerialException, OSError) as exc:
            self.link_stats.open_failures += 1
            self.backoff.failed(f"cannot open ({exc})")
            return False
        self._port = port
        self.backoff.succeeded()
        self.link_stats.opens += 1
        log.info("serial %s: open at %d baud", self.port_url, self.baudrate)
        return True

    def read(self) -> list[Message]:
        """Read what arrives within about ``read_timeout_s`` and parse it."""
        if self._port is None:
            wait = self.backoff.wait_s()
            if wait > 0:
                time.sleep(min(wait, self.read_timeout_s))  # don't spin while backing off
                return []
            if not self.open():
                return []
        assert self._port is not None
        try:
            data = self._port.read(1)  # blocks up to the timeout for the first byte
            if data:
                data += self._port.read(self._port.in_waiting)
        except (serial.SerialException, OSError) as exc:
            self._disconnect(exc)
            return []
        return self.parser.feed(data)

    def messages(self, stop: threading.Event) -> Iterator[Message]:
        """Every valid message until ``stop`` is set."""
        while not stop.is_set():
            yield from self.read()

    def write(self, data: bytes) -> bool:
        """Send bytes to the robot (for commands); False when the port is not open."""
        if self._port is None:
            return False
        try:
            self._port.write(data)
            return True
        except (serial.SerialException, OSError) as exc:
            self._disconnect(exc)
            return False

    def close(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            except (serial.SerialException, OSError):
                pass
            self._port = None

    def __enter__(self) -> SerialLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _disconnect(self, exc: BaseException) -> None:
        self.link_stats.disconnects += 1
        self.close()
        self.parser.reset()
        self.backoff.failed(exc)
