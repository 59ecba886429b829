"""What encoding and decoding a message costs, against msgpack alone on the same map.

For an Odometry, an Observations batch of 10, and SlamStates of n = 15 and n = 1000
landmarks: ``to_bytes`` and ``from_bytes`` (the fast decoding path, and the full validation
``decode_reference``), each the median of ``--repeats`` timings of a loop, beside
``msgpack.packb`` / ``msgpack.unpackb`` of the same wire map (the floor a codec cannot beat:
slamlens validates every field on top). Run it on two checkouts to compare them.

Then the n = 1000 state's ``wire_parts`` into Zenoh shared memory (``ShmPool.wrap``, a
large array part copied a megabyte at a time) against the same parts each turned into
``bytes`` whole first (the baseline, in the same run), three buffers kept alive as a
subscriber or a cache would.

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
    shm_ms, whole_ms = _shm(_state(1000), args.repeats)
    print(f"SlamState n=1000 into shared memory: {shm_ms:.1f} ms chunked, {whole_ms:.1f} ms "
          f"through whole bytes copies (ratio {shm_ms / whole_ms:.2f}; medians)")
    return 0


def _shm(state: SlamState, repeats: int, loops: int = 40) -> tuple[float, float]:
    """Median ms of ShmPool.wrap(wire_parts) and of the whole-bytes baseline, interleaved."""
    import zenoh
    from zenoh import shm

    from slamlens.common.zenoh_publishing import ShmPool

    parts = state.wire_parts()
    size = sum(len(p) for p in parts)
    pool = ShmPool()
    provider = shm.ShmProvider.default_backend(1 << 30)

    def whole() -> object:
        buf = provider.alloc(size, shm.GarbageCollect())
        offset = 0
        for part in parts:
            data = part if isinstance(part, (bytes, bytearray)) else bytes(part)
            buf[offset:offset + len(data)] = data
            offset += len(data)
        return zenoh.ZBytes(buf)

    runs: dict[str, list[float]] = {"chunked": [], "whole": []}
    for _ in range(repeats):
        for name, fn in (("chunked", lambda: pool.wrap(parts)), ("whole", whole)):
            kept: list[object] = []
            times = []
            for _ in range(loops):
                start = time.perf_counter()
                kept.append(fn())
                times.append(time.perf_counter() - start)
                del kept[:-3]
            runs[name].append(statistics.median(times[loops // 2:]) * 1e3)
    return statistics.median(runs["chunked"]), statistics.median(runs["whole"])


if __name__ == "__main__":
    sys.exit(main())
