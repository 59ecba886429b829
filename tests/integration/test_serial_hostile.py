"""``slamlens serial`` over a real pseudo-terminal against checksum-valid but absurd records:
an id beyond int64 ended the process with OverflowError, ``$O,1e308,…`` was
accepted. Every parsed field is range-checked; the service drops, counts and goes on."""

from __future__ import annotations

import os
import time
import tty
from pathlib import Path

from slamlens.common.keys import Keys
from slamlens.common.messages import Observations, Odometry
from slamlens.services.harness.procs import spawn, stop
from slamlens.services.slam.serial_link import checksum

KEYS = Keys()


def nmea(body: str) -> bytes:
    return f"${body}*{checksum(body.encode())}\r\n".encode()


def test_absurd_records_are_dropped_and_the_line_keeps_working(tmp_path: Path, router_endpoint,
                                                               make_client) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "ttyROBOT"
    link.symlink_to(os.ttyname(slave))
    client = make_client()
    odo = client.channel(KEYS.odometry("r5"), recover=True)
    obs = client.channel(KEYS.observations("r5"), recover=True)
    proc = spawn("serial", "--port", str(link), "--robot", "r5", "--connect",
                 router_endpoint)
    try:
        proc.wait_for_line("serial ready", timeout=60)
        hostile = [b"$Z,1.0,1,99999999999999999999,1.0,0.0*69\r\n",  # the record
                   nmea("O,1e308,0.1,0.2,0.3"), nmea("O,1.0,1e308,0.2,0.3"),
                   nmea("O,1.0,0.1,1e300,0.3"), nmea("O,1.0,0.1,0.2,-1e300"),
                   nmea("Z,1.0,1,3,1e300,0.1"), nmea("Z,1.0,1,3,1.0,1e300"),
                   nmea("Z,1e300,0"), nmea("Z,1.0,1,-99999999999999999999,1.0,0.0")]
        good_odo, good_obs = nmea("O,2.0,0.1,0.2,0.3"), nmea("Z,2.0,1,7,1.5,0.25")
        deadline = time.monotonic() + 30
        got_odo = got_obs = None
        while (got_odo is None or got_obs is None) and time.monotonic() < deadline:
            for line in hostile:
                os.write(master, line)
            os.write(master, good_odo + good_obs)
            got_odo = got_odo or odo.recv(timeout=0.5)
            got_obs = got_obs or obs.recv(timeout=0.5)
        assert got_odo is not None and got_obs is not None, "".join(proc.err[-20:])
        o = Odometry.from_bytes(got_odo.payload)
        z = Observations.from_bytes(got_obs.payload)
        assert (o.stamp, o.dt, o.v, o.w) == (2.0, 0.1, 0.2, 0.3)
        assert list(z.ids) == [7] and list(z.ranges) == [1.5]
        assert proc.poll() is None  # still running
    finally:
        out, err = stop(proc)
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, err
    assert "OverflowError" not in err and "Traceback" not in err
    final = next(line for line in out.splitlines() if line.startswith("serial stopped"))
    assert "'out_of_range': " in final and "'out_of_range': 0" not in final
    assert err.count("out_of_range") == 1  # logged once, the rest counted
