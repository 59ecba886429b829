"""A subscriber process for multi-host tests: ``python -m tests.bus_probe KEY_EXPR [flags]``.

It takes the common bus flags (``--connect``, ``--secure DIR --name NAME`` …), prints
``probe ready`` once subscribed, ``first KEY`` for the first sample of each key (so a test
reads a few lines, never a flood) and, at SIGTERM, ``probe done: {"KEY": count, …}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading

from common.cli import add_common_flags, bus_settings, run_cli, stop_event
from common.session import open_bus


def main() -> int:
    parser = argparse.ArgumentParser(prog="bus_probe")
    parser.add_argument("key")
    add_common_flags(parser, config=False)
    args = parser.parse_args()
    counts: dict[str, int] = {}
    lock = threading.Lock()

    def on_sample(key: str, payload: bytes) -> None:
        with lock:
            counts[key] = counts.get(key, 0) + 1
            first = counts[key] == 1
        if first:
            print(f"first {key}", flush=True)

    def run() -> int:
        stop = stop_event()
        bus = open_bus(bus_settings(args))
        try:
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
