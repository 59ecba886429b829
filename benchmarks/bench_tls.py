"""What mutual TLS and the router's access control cost (docs/security.md, ).

Two pipelines run side by side, each a real `slamlens router` process and a real
`slamlens estimator` process: one plain (tcp/), one secure (tls/, `--secure DIR --name …`,
the router enforcing the roles of DIR and reading Zenoh's access-control log). This script
publishes an observation batch (n = 15 map) as the robot and times the state coming back,
alternating between the two pipelines round by round so both see the same machine load.
A bare echo round trip through each router (same payload sizes, no estimator) is the
transport's own floor.

Target: TLS median ≤ 1.3× plain median, observation → state.

Run: ``.venv/bin/python benchmarks/bench_tls.py [--rounds 5] [--samples 200]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.certs import extend_authority  # noqa: E402
from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import Observations, SlamState  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.common.zenoh_bus import ZenohBus  # noqa: E402

KEYS = Keys()
ROBOT = "lat"
ECHO_IN, ECHO_OUT = "slamlens/robot/lat/echo/in", "slamlens/robot/lat/echo/out"


def _spawn(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "slamlens.services", *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_line(proc: subprocess.Popen, text: str) -> None:
    assert proc.stdout is not None
    while True:
        line = proc.stdout.readline()
        if text in line:
            return
        if not line and proc.poll() is not None:
            raise RuntimeError(f"{proc.args} died: {proc.stderr.read() if proc.stderr else ''}")


def _stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()


@dataclass
class Pipeline:
    """A router, an estimator and this script's client session (one of each kind)."""

    label: str
    flags: tuple[str, ...]  #: the bus flags every process of it takes
    procs: list[subprocess.Popen] = field(default_factory=list)
    bus: ZenohBus | None = None

    def start(self, endpoint: str, router_flags: tuple[str, ...]) -> None:
        router = _spawn("router", "--listen", endpoint, *router_flags, "-q")
        _wait_line(router, "router ready")
        est = _spawn("estimator", "--robot", ROBOT, "--connect", endpoint, *self.flags, "-q")
        _wait_line(est, "estimator ready")
        echo = subprocess.Popen(
            [sys.executable, "-c", _ECHO, endpoint, *self.flags], cwd=REPO,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _wait_line(echo, "echo ready")
        self.procs = [echo, est, router]
        secure = dict(zip(self.flags[::2], self.flags[1::2], strict=True))
        self.bus = open_bus(BusSettings(connect=(endpoint,), secure=secure.get("--secure"),
                                        name=secure.get("--name")))

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
        _stop(*self.procs)


# the echo answers as the robot would: its identity may publish under slamlens/robot/lat/**
_ECHO = """
import sys, time
from slamlens.common.session import BusSettings, open_bus
args = sys.argv[1:]
flags = dict(zip(args[1::2], args[2::2]))
b = open_bus(BusSettings(connect=(args[0],), secure=flags.get('--secure'),
                         name=flags.get('--name')))
def on(key, payload):
    p.put(bytes(int(payload)))
p = b.publisher('slamlens/robot/lat/echo/out')
b.subscribe('slamlens/robot/lat/echo/in', on)
print('echo ready', flush=True)
time.sleep(3600)
"""


class Timer:
    """Publish, then wait for the reply on another key; round-trip times in ms."""

    def __init__(self, bus: ZenohBus, out_key: str, in_key: str) -> None:
        self._got = threading.Event()
        self._t = 0.0
        bus.subscribe(in_key, self._on)
        self._pub = bus.publisher(out_key)

    def _on(self, key: str, payload: bytes) -> None:
        self._t = time.perf_counter()
        self._got.set()

    def round_trip(self, payload: bytes) -> float:
        self._got.clear()
        t0 = time.perf_counter()
        self._pub.put(payload)
        if not self._got.wait(5):
            raise RuntimeError("no reply came back")
        return (self._t - t0) * 1e3


def _observations(samples: int, offset: int) -> list[bytes]:
    rng = np.random.default_rng(offset)
    angles = np.linspace(-1.4, 1.4, 15)
    out = []
    for i in range(samples):
        k = int(rng.integers(15))
        out.append(Observations(robot=ROBOT, stamp=0.01 * (offset + i + 1), ids=[k],
                                ranges=[1.2 + rng.normal(0, 0.05)],
                                bearings=[angles[k] + rng.normal(0, 0.02)]).to_bytes())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--samples", type=int, default=200, help="per round and pipeline")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="slamlens-bench-tls-") as tmp:
        pki = str(Path(tmp) / "pki")
        extend_authority(pki, ["router-bench", f"robot-{ROBOT}"])
        plain = Pipeline("plain tcp", ())
        secure = Pipeline("mutual TLS + ACL", ("--secure", pki, "--name", f"robot-{ROBOT}"))
        try:
            plain.start(free_tcp_endpoint(), ())
            secure.start(free_tcp_endpoint().replace("tcp/", "tls/"),
                         ("--secure", pki, "--name", "router-bench"))
            timers = {}
            size = len(SlamState(robot=ROBOT, seq=1, stamp=0.0, step="update",
                                 pose=[0, 0, 0], landmark_ids=np.arange(15),
                                 landmarks=np.zeros((15, 2)), covariance=np.eye(33)).to_bytes())
            init = Observations(robot=ROBOT, stamp=0.0, ids=np.arange(15),
                                ranges=np.full(15, 1.2),
                                bearings=np.linspace(-1.4, 1.4, 15)).to_bytes()
            for p in (plain, secure):
                assert p.bus is not None
                timers[p.label] = (Timer(p.bus, KEYS.observations(ROBOT), KEYS.state(ROBOT)),
                                   Timer(p.bus, ECHO_IN, ECHO_OUT))
                _warm(timers[p.label][0], init)
                _warm(timers[p.label][1], str(size).encode())
            lat: dict[str, list[float]] = {p.label: [] for p in (plain, secure)}
            echo: dict[str, list[float]] = {p.label: [] for p in (plain, secure)}
            for r in range(args.rounds):
                batch = _observations(args.samples, offset=1 + r * args.samples)
                order = (plain, secure) if r % 2 == 0 else (secure, plain)
                for p in order:
                    pipeline, bare = timers[p.label]
                    for msg in batch:
                        lat[p.label].append(pipeline.round_trip(msg))
                        echo[p.label].append(bare.round_trip(str(size).encode()))
                        time.sleep(0.002)
                print(f"round {r + 1}: " + ", ".join(
                    f"{p.label} {statistics.median(lat[p.label][-args.samples:]):.2f} ms"
                    for p in (plain, secure)), flush=True)
            _report(lat, echo, plain.label, secure.label, size)
        finally:
            secure.close()
            plain.close()


def _warm(timer: Timer, payload: bytes) -> None:
    """The first message on a new route may be lost: retry until one comes back."""
    for _ in range(50):
        try:
            timer.round_trip(payload)
            return
        except RuntimeError:
            continue
    raise RuntimeError("the pipeline never answered")


def _report(lat: dict[str, list[float]], echo: dict[str, list[float]], plain: str,
            secure: str, size: int) -> None:
    for label in (plain, secure):
        print(f"{label}: observation → state median {statistics.median(lat[label]):.2f} ms "
              f"(p90 {np.percentile(lat[label], 90):.2f}), bare round trip ({size} B reply) "
              f"median {statistics.median(echo[label]):.2f} ms, {len(lat[label])} samples")
    ratio = statistics.median(lat[secure]) / statistics.median(lat[plain])
    bare = statistics.median(echo[secure]) / statistics.median(echo[plain])
    print(f"TLS RATIO observation → state: {ratio:.2f}× plain (target ≤ 1.3×); "
          f"bare round trip: {bare:.2f}×")


if __name__ == "__main__":
    main()
