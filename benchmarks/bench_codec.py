"""What encoding and decoding a message costs, against msgpack alone on the same map.

For an Odometry, an Observations batch of 10, and SlamStates of n = 15 and n = 1000
landmarks: ``to_bytes`` and ``from_bytes`` (the fast decoding path, and the full validation
``decode_reference``), each the median of ``--repeats`` timings of a loop, beside
``msgpack.packb`` / ``msgpack.unpackb`` of the same wire map (the floor a codec cannot beat:
slamlens validates every field on top). Run it on two checkouts to compare them.

    python benchmarks/bench_codec.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.messages import Observations, Odometry, SlamState  # noqa: E402


def _state(n: int) -> SlamState:
    rng = np.random.default_rng(n)
    N = 3 + 2 * n
    A = rng.normal(size=(N, N)) / N
    return SlamState(robot="r1", seq=7, stamp=1.5, step="update", pose=rng.normal(size=3),
                     landmark_ids=np.arange(n), landmarks=rng.normal(size=(n, 2)),
                     covariance=A @ A.T + np.eye(N), observed_ids=[1], new_ids=[],
                     diagnostics={"gated": 0.0})


def _time(fn: Callable[[], object], loops: int, repeats: int) -> float:
    """Median µs per call over ``repeats`` loops of ``loops`` calls."""
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(loops):
            fn()
        runs.append((time.perf_counter() - start) / loops * 1e6)
    return statistics.median(runs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    cases = [
        ("Odometry", Odometry(robot="r1", stamp=1.0, dt=0.1, v=0.2, w=0.1, input_seq=5), 20000),
        ("Observations k=10", Observations(robot="r1", stamp=1.0, ids=np.arange(10),
                                           ranges=np.linspace(1, 2, 10),
                                           bearings=np.linspace(-1, 1, 10)), 10000),
        ("SlamState n=15", _state(15), 5000),
        ("SlamState n=1000", _state(1000), 20),
    ]
    print(f"{'message':20s} {'to_bytes':>10s} {'packb':>8s} {'ratio':>6s}  {'from_bytes':>10s} "
          f"{'full':>9s} {'unpackb':>8s} {'ratio':>6s}   (µs, medians)")
    for name, msg, loops in cases:
        payload = msg.to_bytes()
        wire = msg.to_dict()
        cls = type(msg)
        enc = _time(msg.to_bytes, loops, args.repeats)
        pack = _time(lambda w=wire: msgpack.packb(w, use_bin_type=True), loops, args.repeats)
        dec = _time(lambda c=cls, p=payload: c.from_bytes(p), loops, args.repeats)
        full = _time(lambda c=cls, p=payload: c.decode_reference(p), loops, args.repeats)
        unpack = _time(lambda p=payload: msgpack.unpackb(p, raw=False), loops, args.repeats)
        print(f"{name:20s} {enc:10.2f} {pack:8.2f} {enc / pack:6.2f}  {dec:10.2f} {full:9.2f} "
              f"{unpack:8.2f} {dec / unpack:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
