"""Serial robot link: the record format, a parser that survives garbage, a real pty port."""

from __future__ import annotations

import functools
import math
import os
import random
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.errors import SourceError
from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam.serial_link import (
    SerialLink,
    SerialParser,
    checksum,
    encode,
    encode_observations,
    encode_odometry,
)


def nmea(body: str) -> bytes:
    """A record built here independently: XOR of the body, as NMEA 0183 defines it."""
    value = functools.reduce(lambda a, b: a ^ b, body.encode(), 0)
    return f"${body}*{value:02X}\r\n".encode()


def random_message(rng: random.Random, stamp: float) -> Odometry | Observations:
    if rng.random() < 0.5:
        return Odometry(robot="r1", stamp=stamp, dt=rng.uniform(0, 0.2),
                        v=rng.uniform(-1, 1), w=rng.uniform(-2, 2))
    k = rng.randrange(0, 6)
    return Observations(robot="r1", stamp=stamp,
                        ids=[rng.choice([-1, rng.randrange(0, 1000)]) for _ in range(k)],
                        ranges=[rng.uniform(0, 10) for _ in range(k)],
                        bearings=[rng.uniform(-math.pi, math.pi) for _ in range(k)])


def test_checksum_is_the_nmea_xor() -> None:
    # a textbook NMEA sentence and its published checksum
    assert checksum(b"GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == "47"
    assert nmea("O,1.5,0.1,0.25,-0.125") == encode_odometry(
        Odometry(robot="x", stamp=1.5, dt=0.1, v=0.25, w=-0.125))


def test_records_parse_into_messages() -> None:
    parser = SerialParser("r1")
    out = parser.feed(nmea("O,10.25,0.01,0.3,-0.5") + nmea("Z,10.3,2,7,1.25,0.5,-1,2.5,-0.25")
                      + nmea("Z,10.4,0"))
    assert out == [
        Odometry(robot="r1", stamp=10.25, dt=0.01, v=0.3, w=-0.5),
        Observations(robot="r1", stamp=10.3, ids=[7, -1], ranges=[1.25, 2.5],
                     bearings=[0.5, -0.25]),
        Observations(robot="r1", stamp=10.4, ids=np.zeros(0, int), ranges=np.zeros(0),
                     bearings=np.zeros(0)),
    ]
    assert parser.stats.odometry == 1 and parser.stats.observations == 2
    assert parser.stats.dropped == 0


def test_encode_round_trips_exactly() -> None:
    rng = random.Random(1)
    messages = [random_message(rng, 100 + i * 0.1) for i in range(200)]
    parser = SerialParser("r1")
    assert parser.feed(b"".join(encode(m) for m in messages)) == messages
    batch = next(m for m in messages if isinstance(m, Observations) and m.ids.size)
    assert encode_observations(batch).startswith(f"$Z,{batch.stamp!r},{batch.ids.size},".encode())


def test_any_chunking_gives_the_same_messages() -> None:
    rng = random.Random(2)
    messages = [random_message(rng, float(i)) for i in range(50)]
    stream = b"".join(encode(m) for m in messages)
    parser = SerialParser("r1")
    out = []
    i = 0
    while i < len(stream):
        n = rng.randrange(1, 40)
        out += parser.feed(stream[i:i + n])
        i += n
    assert out == messages


@pytest.mark.parametrize(("line", "reason"), [
    (nmea("O,1,0.1,0.2")[:-2] + b"\n", "malformed"),  # 3 fields
    (nmea("O,1,0.1,x,0.3"), "malformed"),
    (nmea("O,1,0.1,nan,0.3"), "non_finite"),
    (nmea("O,1,0.1,inf,0.3"), "non_finite"),
    (nmea("O,1,-0.1,0.2,0.3"), "invalid"),
    (nmea("Z,1,2,3,1.0,0.1"), "bad_count"),
    (nmea("Z,1,-1"), "bad_count"),
    (nmea("Z,1,1,3,-1.0,0.1"), "invalid"),
    (nmea("Z,1,1,-2,1.0,0.1"), "invalid"),
    (nmea("Z,1,1,3.5,1.0,0.1"), "malformed"),
    (nmea("Q,1,2,3"), "unknown_type"),
    (b"$O,1,0.1,0.2,0.3*00\r\n", "bad_checksum"),
    (b"$O,1,0.1,0.2,0.3\r\n", "malformed"),
    (b"$O,1,0.1,0.2,0.3*ZZ\r\n", "malformed"),
    (nmea("O,1,0.1,0.2,0.3").replace(b"0.2", b"0\xe9")[:-5] + b"*"
     + checksum(b"O,1,0.1,0\xe9,0.3").encode() + b"\r\n", "malformed"),
])
def test_bad_records_are_dropped_and_counted(line: bytes, reason: str) -> None:
    parser = SerialParser("r1")
    good = nmea("O,2,0.1,0.2,0.3")
    out = parser.feed(good + line + good)
    assert len(out) == 2 and all(m.stamp == 2.0 for m in out)
    stats = parser.stats.as_dict()
    assert stats[reason] == 1
    assert parser.stats.dropped == 1


def test_lower_case_checksum_and_bare_newline_accepted() -> None:
    body = "O,3,0.1,0.2,0.25"
    line = f"${body}*{checksum(body.encode()).lower()}\n".encode()
    assert SerialParser("r1").feed(line)[0].stamp == 3.0


def test_overlong_lines_are_dropped_and_parsing_resumes() -> None:
    parser = SerialParser("r1", max_line_bytes=100)
    good = nmea("O,2,0.1,0.2,0.3")
    assert parser.feed(b"x" * 250) == []  # no newline at all: buffer must not grow forever
    assert len(parser._buffer) <= 100
    assert parser.feed(b"yy\n" + good) != []
    assert parser.feed(b"$" + b"1" * 150 + b"\n" + good)[0].stamp == 2.0
    assert parser.stats.overflow == 2


def test_random_garbage_between_and_inside_records() -> None:
    """Only the records left intact come out, in order; the parser never raises."""
    rng = random.Random(20240611)
    parser = SerialParser("r1")
    expected, stream = [], bytearray()
    for i in range(400):
        message = random_message(rng, float(i))
        record = bytearray(encode(message))
        if rng.random() < 0.2:  # corrupt one byte inside the record
            j = rng.randrange(1, len(record) - 2)
            record[j] = (record[j] + rng.randrange(1, 256)) % 256
        else:
            expected.append(message)
        stream += record
        if rng.random() < 0.3:  # garbage between records, ended by a newline or not
            stream += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 120)))
            if rng.random() < 0.5:
                stream += b"\n"
    out = []
    for i in range(0, len(stream), 64):
        out += parser.feed(bytes(stream[i:i + 64]))
    assert out == expected
    assert parser.stats.garbage_bytes > 0 and parser.stats.dropped > 0


# -- the link, on a real pseudo-terminal -------------------------------------------------

class Pty:
    """A pseudo-terminal whose slave is reachable through a stable symlink, like udev's."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        if link.is_symlink():
            link.unlink()
        link.symlink_to(os.ttyname(self.slave))

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def vanish(self) -> None:
        if self.master >= 0:
            os.close(self.master)
            os.close(self.slave)
            self.master = self.slave = -1  # never close a number the OS may reuse


def read_until(link: SerialLink, count: int, timeout_s: float = 5.0) -> list:
    out: list = []
    deadline = time.monotonic() + timeout_s
    while len(out) < count and time.monotonic() < deadline:
        out += link.read()
    return out


@pytest.fixture
def pty_port(tmp_path: Path) -> Iterator[Pty]:
    port = Pty(tmp_path / "ttyROBOT")
    yield port
    port.vanish()


def test_link_reads_records_and_garbage_through_a_pty(pty_port: Pty) -> None:
    rng = random.Random(5)
    messages = [random_message(rng, float(i)) for i in range(30)]
    with SerialLink(str(pty_port.link), robot="r1", read_timeout_s=0.05) as link:
        assert link.open() and link.connected
        for m in messages:
            pty_port.write(b"\x00\xff garbage" + encode(m))
        out = read_until(link, len(messages))
    assert out == messages
    assert link.stats["garbage_bytes"] == 30 * 10


def test_link_survives_a_vanished_port_and_reconnects(pty_port: Pty, tmp_path: Path) -> None:
    with SerialLink(str(pty_port.link), robot="r1", read_timeout_s=0.05,
                    backoff_initial_s=0.05, backoff_max_s=0.2) as link:
        assert link.open()
        pty_port.write(nmea("O,1,0.1,0.2,0.3") + b"$O,2,0.1")  # the second never ends
        assert [m.stamp for m in read_until(link, 1)] == [1.0]
        vanished = time.monotonic()
        pty_port.vanish()
        deadline = time.monotonic() + 3.0
        while link.connected and time.monotonic() < deadline:
            assert link.read() == []
        assert not link.connected
        assert link.stats["disconnects"] == 1 and link.stats["partial"] == 1
        # the device stays away for a while: reopen attempts fail quietly, with backoff:
        # 0.05, 0.1 and 0.2 s after the disconnect and each failure, so the third failure
        # comes ≥ 0.35 s after the port vanished, however slow the machine (not a busy loop)
        deadline = time.monotonic() + 10.0
        while link.stats["open_failures"] < 3 and time.monotonic() < deadline:
            assert link.read() == []
        assert link.stats["open_failures"] == 3
        assert time.monotonic() - vanished >= 0.35
        # it comes back under the same name
        again = Pty(pty_port.link)
        try:
            deadline = time.monotonic() + 3.0
            while not link.connected and time.monotonic() < deadline:
                assert link.read() == []
            # (pyserial flushes the input on open, so the robot talks once we are there)
            again.write(nmea("O,3,0.1,0.2,0.3"))
            out = read_until(link, 1)
            assert link.connected and [m.stamp for m in out] == [3.0]
            assert link.stats["opens"] == 2
        finally:
            again.vanish()


def test_loop_url_and_bad_urls() -> None:
    with SerialLink("loop://", robot="r1", read_timeout_s=0.05) as link:
        assert link.open()
        assert link.write(nmea("O,4,0.1,0.2,0.3"))
        assert [m.stamp for m in read_until(link, 1)] == [4.0]
    with pytest.raises(SourceError, match="nosuchscheme"):
        SerialLink("nosuchscheme://x").open()
    missing = SerialLink("/dev/does-not-exist-slamlens", read_timeout_s=0.01,
                         backoff_initial_s=0.01)
    assert missing.read() == [] and not missing.connected
    assert missing.stats["open_failures"] == 1
