"""End-to-end speed of the SLAM pipeline over real Zenoh on loopback (s).

1. Throughput: ``slamlens sim --rate 0`` and ``slamlens estimator`` as separate processes
   through a ``slamlens router`` process; this script subscribes to every state and times
   the paper scenario's default run from the first state to the last. Target: faster than
   100× real time with every state published and received.
2. Latency: an observation published by this script to the estimator process → the
   resulting state received back, at n = 15. Target: median under 2 ms. The baseline in
   the same run is a bare Zenoh round trip (put → echo process → back) with the same
   payload sizes, i.e. the transport's own floor.

Run: ``.venv/bin/python benchmarks/bench_pipeline.py [--repeats 3] [--samples 500]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import Observations, SlamState  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402

KEYS = Keys()


def _spawn(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "slamlens.services", *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_line(proc: subprocess.Popen, text: str) -> None:
    while True:
        line = proc.stdout.readline()
        if text in line:
            return
        if not line and proc.poll() is not None:
            raise RuntimeError(f"{proc.args} died: {proc.stderr.read()}")


def _stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()


def throughput(endpoint: str, seed: int) -> dict:
    est = _spawn("estimator", "--robot", "bench", "--connect", endpoint, "-q")
    _wait_line(est, "estimator ready")
    bus = open_bus(BusSettings(connect=(endpoint,)))
    arrivals: list[tuple[float, int, float]] = []
    lock = threading.Lock()

    def on_state(key: str, payload: bytes) -> None:
        s = SlamState.from_bytes(payload)
        with lock:
            arrivals.append((time.perf_counter(), s.seq, s.stamp))

    bus.subscribe(KEYS.state("bench"), on_state)
    time.sleep(0.3)
    sim = _spawn("sim", "--robot", "bench", "--rate", "0", "--seed", str(seed),
                 "--connect", endpoint, "-q")
    out, err = sim.communicate(timeout=600)
    if sim.returncode != 0:
        raise RuntimeError(err)
    counts = json.loads(out.split("sim done: ", 1)[1].split(" in ")[0])
    expected = counts["Odometry"] + counts["Observations"]
    deadline = time.monotonic() + 60
    while True:
        with lock:
            got = sum(1 for a in arrivals if a[1] > 0)
        if got >= expected or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    bus.close()
    _stop(est)
    states = [a for a in arrivals if a[1] > 0]
    wall = states[-1][0] - states[0][0]
    robot_time = states[-1][2] - states[0][2]
    return {"published": expected, "received": len(states), "wall_s": wall,
            "robot_s": robot_time, "speedup": robot_time / wall}


def latency(endpoint: str, samples: int) -> list[float]:
    est = _spawn("estimator", "--robot", "lat", "--connect", endpoint, "-q")
    _wait_line(est, "estimator ready")
    bus = open_bus(BusSettings(connect=(endpoint,)))
    got = threading.Event()
    last = {"t": 0.0, "seq": -1}

    def on_state(key: str, payload: bytes) -> None:
        last["t"] = time.perf_counter()
        last["seq"] = SlamState.from_bytes(payload).seq
        got.set()

    bus.subscribe(KEYS.state("lat"), on_state)
    # published as a driver does: an advanced publisher, inputs numbered (docs/delivery.md)
    pub = bus.publisher(KEYS.observations("lat"), cache=100)
    while not bus.wait_for_subscriber(KEYS.observations("lat"), timeout=5):
        pass
    ids = np.arange(15)
    angles = np.linspace(-1.4, 1.4, 15)
    first = Observations(robot="lat", stamp=0.0, ids=ids, ranges=np.full(15, 1.2),
                         bearings=angles, input_seq=1)
    got.clear()
    pub.put(first.to_bytes())
    got.wait(5)
    out = []
    rng = np.random.default_rng(0)
    for i in range(samples):
        k = int(rng.integers(15))
        msg = Observations(robot="lat", stamp=0.01 * (i + 1), ids=[k],
                           ranges=[1.2 + rng.normal(0, 0.05)],
                           bearings=[angles[k] + rng.normal(0, 0.02)],
                           input_seq=i + 2).to_bytes()
        got.clear()
        t0 = time.perf_counter()
        pub.put(msg)
        if not got.wait(5):
            raise RuntimeError("no state came back")
        out.append((last["t"] - t0) * 1e3)
        time.sleep(0.002)
    bus.close()
    _stop(est)
    return out


def transport_floor(endpoint: str, samples: int, size: int) -> list[float]:
    """Bare round trip through the router and an echo process (same payload size)."""
    code = (
        "import sys,time\n"
        "from slamlens.common.session import BusSettings, open_bus\n"
        f"b = open_bus(BusSettings(connect=({endpoint!r},)))\n"
        "p = b.publisher('bench/echo/out')\n"
        f"b.subscribe('bench/echo/in', lambda k, x: p.put(bytes({size})))\n"
        "print('echo ready', flush=True)\n"
        "time.sleep(3600)\n"
    )
    echo = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _wait_line(echo, "echo ready")
    bus = open_bus(BusSettings(connect=(endpoint,)))
    got = threading.Event()
    stamp = {"t": 0.0}

    def on(key: str, payload: bytes) -> None:
        stamp["t"] = time.perf_counter()
        got.set()

    bus.subscribe("bench/echo/out", on)
    pub = bus.publisher("bench/echo/in")
    time.sleep(0.3)
    out = []
    for _ in range(samples):
        got.clear()
        t0 = time.perf_counter()
        pub.put(b"x" * 120)
        got.wait(5)
        out.append((stamp["t"] - t0) * 1e3)
        time.sleep(0.002)
    bus.close()
    _stop(echo)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--samples", type=int, default=500)
    args = parser.parse_args()
    endpoint = free_tcp_endpoint()
    router = _spawn("router", "--listen", endpoint, "-q")
    _wait_line(router, "router ready")
    try:
        runs = [throughput(endpoint, seed) for seed in range(args.repeats)]
        for r in runs:
            print(f"throughput: {r['received']}/{r['published']} states received, "
                  f"{r['robot_s']:.1f} s of robot time in {r['wall_s']:.3f} s wall "
                  f"= {r['speedup']:.0f}× real time")
        speed = statistics.median(r["speedup"] for r in runs)
        print(f"THROUGHPUT median {speed:.0f}× real time (target > 100×), every state "
              f"received: {all(r['received'] == r['published'] for r in runs)}")
        lat = latency(endpoint, args.samples)
        size = len(SlamState(robot="lat", seq=1, stamp=0.0, step="update", pose=[0, 0, 0],
                             landmark_ids=np.arange(15), landmarks=np.zeros((15, 2)),
                             covariance=np.eye(33)).to_bytes())
        floor = transport_floor(endpoint, args.samples, size)
        lat_med, floor_med = statistics.median(lat), statistics.median(floor)
        print(f"LATENCY observation → state at n = 15: median {lat_med:.2f} ms, "
              f"p90 {np.percentile(lat, 90):.2f} ms (target median < 2 ms)")
        print(f"baseline bare Zenoh round trip ({size} B reply) median {floor_med:.2f} ms; "
              f"estimator adds {lat_med - floor_med:.2f} ms "
              f"(ratio {lat_med / floor_med:.2f}×)")
    finally:
        _stop(router)


if __name__ == "__main__":
    main()
