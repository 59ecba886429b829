"""A subscriber process for multi-host tests: ``python -m tests.bus_probe KEY_EXPR [flags]``.

It takes the common bus flags (``--connect``, ``--secure DIR --name NAME`` …), prints
``probe ready`` once subscribed, ``first KEY`` for the first sample of each key (so a test
reads a few lines, never a flood) and, at SIGTERM, ``probe done: {"KEY": count, …}``.

``--subscribers N`` declares N subscribers on the key (counts are summed); ``--stall S``
makes every callback sit for S seconds, on purpose: a client as bad as a paused debugger,
which the publishers must not wait for (docs/delivery.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading

from slamlens.common.cli import add_common_flags, bus_settings, run_cli, stop_event
from slamlens.common.session import open_bus


def main() -> int:
    parser = argparse.ArgumentParser(prog="bus_probe")
    parser.add_argument("key")
    parser.add_argument("--subscribers", type=int, default=1, help="subscribers on KEY")
    parser.add_argument("--stall", type=float, default=0.0,
                        help="seconds every callback blocks (a deliberately bad client)")
    add_common_flags(parser, config=False)
    args = parser.parse_args()
    stop = stop_event()
    counts: dict[str, int] = {}
    lock = threading.Lock()

    def on_sample(key: str, payload: bytes) -> None:
        with lock:
            counts[key] = counts.get(key, 0) + 1
            first = counts[key] == 1
        if first:
            print(f"first {key}", flush=True)
        if args.stall > 0:
            stop.wait(args.stall)  # blocks Zenoh's thread, as a bad client would

    def run() -> int:
        bus = open_bus(bus_settings(args))
        try:
            for _ in range(args.subscribers):
                bus.subscribe(args.key, on_sample)
            print("probe ready", flush=True)
            stop.wait()
        finally:
            bus.close()
        with lock:
            print(f"probe done: {json.dumps(counts, sort_keys=True)}", flush=True)
        return 0

    return run_cli(run)


if __name__ == "__main__":
    sys.exit(main())
