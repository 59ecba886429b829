"""What one Zenoh publication costs the publishing process, back to back and spaced out.

The MRCLAM target is CPU-bound on two cores: every state, Health and input is one
``put``. This measures the floor that sets, with the publisher as the services make it
(``Bus.publisher(key, cache=…)``: a ``zenoh.ext`` advanced publisher, congestion control
drop, heartbeats), a ``slamlens router`` process and a subscriber in a third process, all
on loopback:

* **back to back**: puts in a tight loop, as a flood of small messages (Zenoh batches them
  while its transmit queue is busy);
* **spaced**: one put every ``--gap-us`` µs of busy work (the estimator's ~300 µs per state
  at MRCLAM's map size), so each put finds the queue idle and goes out in a batch of its own.

For each: the caller's thread CPU inside ``put`` and the process CPU per put (the caller
plus Zenoh's own threads; the busy wait between puts subtracted), median of ``--repeats``.
The ratio spaced / back to back is the price of sending each message as soon as it is made.

Run: ``.venv/bin/python benchmarks/bench_put.py [--repeats 5] [--count 5000]``
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.services.harness.procs import spawn, stop  # noqa: E402

KEY = "bench/put"
_SUBSCRIBER = """
import os, sys
from slamlens.common.session import BusSettings, open_bus
bus = open_bus(BusSettings(connect=(sys.argv[1],)))
got = [0]
bus.session.declare_subscriber(sys.argv[2], lambda s: got.__setitem__(0, got[0] + 1))
print("ready", flush=True)
sys.stdin.readline()
print(got[0], flush=True)
os._exit(0)
"""


def _busy(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def measure(pub, payload: bytes, *, count: int, gap_s: float) -> tuple[float, float]:
    """(caller thread CPU µs per put, process CPU µs per put) for ``count`` puts."""
    in_put = 0.0
    busy = 0.0
    cpu0 = time.process_time()
    for _ in range(count):
        if gap_s:
            b0 = time.thread_time()
            _busy(gap_s)
            busy += time.thread_time() - b0
        t0 = time.thread_time()
        pub.put(payload)
        in_put += time.thread_time() - t0
    process = time.process_time() - cpu0 - busy
    return in_put / count * 1e6, process / count * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--count", type=int, default=5000)
    ap.add_argument("--gap-us", type=float, default=300.0)
    args = ap.parse_args()
    ep = free_tcp_endpoint()
    router = spawn("router", "--listen", ep)
    router.wait_for_line("router ready")
    sub = subprocess.Popen([sys.executable, "-c", _SUBSCRIBER, ep, KEY], cwd=REPO,
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    bus = open_bus(BusSettings(connect=(ep,)))
    try:
        assert sub.stdout is not None and sub.stdin is not None
        assert sub.stdout.readline().strip() == "ready"
        assert bus.wait_for_subscriber(KEY)
        pub = bus.publisher(KEY, cache=10_000)
        sent = 0
        print(f"{args.count} puts per run, median of {args.repeats} runs "
              f"(caller thread CPU in put / process CPU per put, µs)")
        for size in (600, 9_300):  # a Health / an MRCLAM-sized state (n = 15)
            payload = bytes(size)
            measure(pub, payload, count=500, gap_s=0.0)  # warm
            sent += 500
            rows = {}
            for name, gap in (("back to back", 0.0), ("spaced", args.gap_us * 1e-6)):
                runs = [measure(pub, payload, count=args.count, gap_s=gap)
                        for _ in range(args.repeats)]
                sent += args.count * args.repeats
                rows[name] = (statistics.median(r[0] for r in runs),
                              statistics.median(r[1] for r in runs))
                print(f"  {size:>6} B, {name:<12}: {rows[name][0]:6.1f} / {rows[name][1]:6.1f}")
            ratio = rows["spaced"][1] / rows["back to back"][1]
            print(f"  {size:>6} B, spaced / back to back (process CPU): {ratio:.2f}×")
        sub.stdin.write("\n")
        sub.stdin.flush()
        received = int(sub.stdout.readline())
        print(f"subscriber received {received} of {sent} (congestion control drop)")
    finally:
        bus.close()
        sub.kill()
        stop(router)


if __name__ == "__main__":
    main()
