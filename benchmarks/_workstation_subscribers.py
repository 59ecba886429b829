"""The workstation side of ``bench_delivery.py --only 2 --two-host``: one subscriber whose
callback sleeps 1 s per sample and ``--extra`` ordinary ones on a robot's state key, each its
own Zenoh session to ``--connect``. Prints ``subscribed`` once the subscribers are declared,
then, when stdin closes, one JSON line of how many samples each kind received, and exits.

Run by the benchmark (pinned to its own core), not by hand.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.session import BusSettings, open_bus  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--robot", required=True)
    ap.add_argument("--extra", type=int, default=10)
    ap.add_argument("--no-stalled", action="store_true")
    args = ap.parse_args()
    key = Keys().state(args.robot)
    done = threading.Event()  # once set, the stalled callback stops sleeping
    counts = {"stalled": 0, "ordinary": 0}
    lock = threading.Lock()

    def stalled(_k: str, _p: bytes) -> None:
        with lock:
            counts["stalled"] += 1
        if not done.is_set():
            time.sleep(1.0)

    def ordinary(_k: str, _p: bytes) -> None:
        with lock:
            counts["ordinary"] += 1

    buses = []
    if not args.no_stalled:
        buses.append(open_bus(BusSettings(connect=(args.connect,))))
        buses[-1].subscribe(key, stalled)
    for _ in range(args.extra):
        buses.append(open_bus(BusSettings(connect=(args.connect,))))
        buses[-1].subscribe(key, ordinary)
    print("subscribed", flush=True)
    sys.stdin.read()  # the benchmark closes it when the run is measured
    done.set()
    with lock:
        print(json.dumps(counts), flush=True)
    os._exit(0)  # do not drain the stalled subscriber's queue through its callback


if __name__ == "__main__":
    main()
