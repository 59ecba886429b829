"""The two ends of ``bench_slow_link.py``: ``publish KEY N SIZE --period S`` and ``collect KEY
N [--plain]``, each its own Zenoh session (``--connect``). Run by the benchmark, not by hand.

``publish`` declares a caching publisher (the one every slamlens producer with a cache
uses), waits for a subscriber (``publisher matched``) and for SIGUSR1, puts N payloads of
SIZE bytes S seconds apart (payload i starts with i as 8 bytes), printing each put's
monotonic time (``put I T``), then ``published N``, and keeps its cache until SIGTERM.
``collect`` subscribes through a recovering channel (a plain subscriber with ``--plain``),
prints ``collect ready``, ``all N`` once it holds every index, and at SIGTERM ``collect
done: {"got": …, "lost": …}``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slamlens.common.cli import add_common_flags, bus_settings, run_cli, stop_event  # noqa: E402
from slamlens.common.session import open_bus  # noqa: E402


def publish(args: argparse.Namespace) -> int:
    stop = stop_event()
    go = threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: go.set())
    bus = open_bus(bus_settings(args))
    try:
        pub = bus.publisher(args.key, cache=args.n + 1, cache_bytes=(args.n + 1) * args.size)
        while not bus.wait_for_subscriber(args.key, timeout=1.0):
            if stop.is_set():
                return 1
        print("publisher matched", flush=True)
        go.wait()
        for i in range(args.n):
            pub.put(i.to_bytes(8, "little") + bytes(args.size - 8))
            print(f"put {i} {time.monotonic():.6f}", flush=True)
            stop.wait(args.period)
        print(f"published {args.n}", flush=True)
        stop.wait()
    finally:
        bus.close()
    return 0


def collect(args: argparse.Namespace) -> int:
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    got: set[int] = set()
    try:
        ch = bus.channel(args.key, recover=not args.plain)
        print("collect ready", flush=True)
        while not stop.is_set():
            sample = ch.recv(timeout=0.2)
            if sample is None:
                continue
            got.add(int.from_bytes(sample.payload[:8], "little"))
            if len(got) == args.n:
                print(f"all {args.n}", flush=True)
        done = {"got": len(got), "lost": ch.lost}
    finally:
        bus.close()
    print(f"collect done: {json.dumps(done)}", flush=True)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(prog="_slow_link_probe")
    parser.add_argument("role", choices=("publish", "collect"))
    parser.add_argument("key")
    parser.add_argument("n", type=int)
    parser.add_argument("size", type=int, nargs="?", default=1024)
    parser.add_argument("--period", type=float, default=0.0, help="seconds between puts")
    parser.add_argument("--plain", action="store_true", help="a subscriber without recovery")
    add_common_flags(parser, config=False)
    args = parser.parse_args()
    return run_cli(lambda: (publish if args.role == "publish" else collect)(args))


if __name__ == "__main__":
    sys.exit(main())
