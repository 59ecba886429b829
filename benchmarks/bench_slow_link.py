"""A caching publisher behind a slow link while a subscriber recovers (docs/delivery.md,
"What a lab can expect").

Two network namespaces (``harness.netns``: made by the benchmark, root only) joined by a
veth pair shaped to ``--rate`` both ways (``tc … tbf``). The workstation runs a router
and a subscriber; the robot a publisher that caches everything it puts
(``Bus.publisher(cache=…)``, as the estimator, the drivers and the monitor do) and puts
``--n`` payloads of ``--size`` bytes ``--period`` s apart — by default eight times what
the link carries, so that samples are dropped on the way and the subscriber asks the
publisher's cache for them. Three ways:

1. ``direct, recovering`` — the publisher's session connects straight to the
   workstation's router, across the link; the subscriber recovers (advanced subscriber);
2. ``direct, plain`` — the same, the subscriber without recovery (nothing asks the cache);
3. ``robot router, recovering`` — the publisher connects to a router of the robot's own,
   on loopback, which is linked to the workstation's (as ``deploy/`` runs it).

Per run: how long the puts took against the plan (``--n`` × ``--period``), the longest
time between two consecutive puts, and how many samples the subscriber held and had
counted lost ``--window`` s after the last put (or when it had them all). Medians over
``--repeats`` runs of each.

Run: ``.venv/bin/python benchmarks/bench_slow_link.py [--repeats 3] [--rate 2mbit]``
(about 1.5 min a run).
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.services.harness.netns import Hosts, available, make_hosts, own_shm  # noqa: E402
from slamlens.services.harness.procs import (  # noqa: E402
    Service,
    Started,
    slamlens_cmd,
    stop,
)

WAYS = ("direct, recovering", "direct, plain", "robot router, recovering")
KEY = "bench/slow_link"
PROBE = [sys.executable, str(REPO / "benchmarks" / "_slow_link_probe.py")]


def _in(ns: str, argv: list[str], *, isolated: bool = False) -> Service:
    """``argv`` in namespace ``ns`` (with a /dev/shm of its own if ``isolated``)."""
    return Service(["ip", "netns", "exec", ns, *(own_shm(argv) if isolated else argv)],
                   cwd=REPO)


def _start(h: Hosts, way: str, args: argparse.Namespace,
           started: Started) -> tuple[Service, Service]:
    """The routers, the subscriber and the publisher of one run; returns (publisher,
    subscriber), the publisher matched."""
    started.add(_in(h.workstation, slamlens_cmd(
        "router", "--listen", f"tcp/{h.workstation_ip}:7447", "--listen",
        "tcp/127.0.0.1:7447"), isolated=True), ready="router ready")
    publisher_endpoint = f"tcp/{h.workstation_ip}:7447"
    if way.startswith("robot router"):
        started.start("router", "--listen", "tcp/127.0.0.1:7448", "--connect",
                      f"tcp/{h.workstation_ip}:7447", ready="router ready", netns=h.robot)
        publisher_endpoint = "tcp/127.0.0.1:7448"
    sub = started.add(_in(h.workstation, [
        *PROBE, "collect", KEY, str(args.n), "--connect", "tcp/127.0.0.1:7447",
        *(["--plain"] if "plain" in way else [])], isolated=True), ready="collect ready")
    pub = started.add(_in(h.robot, [
        *PROBE, "publish", KEY, str(args.n), str(args.size), "--period", str(args.period),
        "--connect", publisher_endpoint]), ready="publisher matched")
    return pub, sub


def one_run(way: str, args: argparse.Namespace) -> dict:
    h = make_hosts()
    started = Started()
    try:
        h.shape(args.rate, burst="16kb", latency="100ms")
        pub, sub = _start(h, way, args, started)
        pub.send_signal(signal.SIGUSR1)
        pub.wait_for_line(f"published {args.n}", timeout=args.n * args.period + 600)
        try:
            sub.wait_for_line(f"all {args.n}", timeout=args.window)
        except AssertionError:
            pass  # what it holds after the window is the figure
        sub_out, _ = stop(sub)
        pub_out, _ = stop(pub)
    finally:
        started.stop_all()
        h.remove()
    times = [float(line.split()[2]) for line in pub_out.splitlines()
             if line.startswith("put ")]
    done = json.loads(next(line for line in sub_out.splitlines()
                           if line.startswith("collect done: ")).split(": ", 1)[1])
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    return {"puts_s": times[-1] - times[0], "longest_s": max(gaps), **done}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rate", default="2mbit", help="the link, both ways (tc tbf rate)")
    ap.add_argument("--n", type=int, default=400, help="payloads put")
    ap.add_argument("--size", type=int, default=40_000, help="bytes each")
    ap.add_argument("--period", type=float, default=0.02, help="seconds between puts")
    ap.add_argument("--window", type=float, default=60.0,
                    help="seconds after the last put the subscriber is given")
    args = ap.parse_args()
    why = available()
    if why is not None:
        print(f"needs network namespaces: {why}")
        return 2
    plan = (args.n - 1) * args.period
    print(f"{args.n} × {args.size} B every {args.period} s over {args.rate}: puts planned "
          f"{plan:.1f} s")
    runs: dict[str, list[dict]] = {w: [] for w in WAYS}
    for r in range(args.repeats):
        for way in WAYS:  # alternated, so that a slow spell of the machine hits all three
            res = one_run(way, args)
            runs[way].append(res)
            print(f"run {r + 1} {way:<26} puts {res['puts_s']:6.1f} s, longest gap "
                  f"{res['longest_s']:5.2f} s; subscriber got {res['got']}, lost "
                  f"{res['lost']}", flush=True)
    print(f"\n{'way':<26} {'puts s':>7} {'longest s':>10} {'got':>5} {'lost':>5}   (medians)")
    for way, rs in runs.items():
        med = {k: statistics.median(x[k] for x in rs) for k in rs[0]}
        print(f"{way:<26} {med['puts_s']:7.1f} {med['longest_s']:10.2f} {med['got']:5.0f} "
              f"{med['lost']:5.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
