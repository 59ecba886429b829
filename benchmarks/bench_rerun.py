"""Rerun sink targets, real processes over Zenoh on loopback (docs/rerun.md).

1. **n = 50, all pairs, 20 states/s.** The benchmark publishes states of a 50-feature map
   (1225 pairs) at 20 per second of wall time on the robot's state key; ``slamlens rerun
   --save`` draws them. Measured over a window: states drawn per second, states superseded
   (taken over by a newer one before the sink got to them: 0 when it keeps up), the sink's
   CPU (cores), and how long after the last state it shows it. Baseline in the same run:
   ``slamlens foxglove`` (the live Foxglove server, the other 3D exporter: a scene per
   state) on the same stream. Target: every state drawn.
2. **The `large` world at n = 1000.** States of the `large` world's 1000 landmarks (a
   30.6 MiB covariance each) at 20 per second, ``slamlens summary`` beside them (as on the
   robot), ``slamlens rerun --source summary --save`` pulling the summary stream. Measured:
   summaries drawn per second against the summaries the robot made per second (the
   baseline: what there was to draw), superseded, the sink's CPU. Target: ≤ 0.5 core,
   every summary drawn.

3. **In process, what one item costs the sink**: the CPU time of the translator and the
   Rerun log calls (into an ``.rrd`` file) per state at n = 50 (all pairs) and per summary
   of the `large` world at n = 1000 (clusters, budget 2000, made by ``Summariser`` as the
   robot makes them), median of ``--repeats`` batches of 200 — what 20 per second would
   cost a sink given the CPU, whatever the machine's load.

Each run takes ``--window`` seconds after a ``--warmup``; medians over ``--repeats``.

Run: ``.venv/bin/python benchmarks/bench_rerun.py [--window 30] [--repeats 3] [--only 1,2,3]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import ServiceStatus, SlamState, StateSummary  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.services.harness.procs import Service, spawn, stop  # noqa: E402
from slamlens.services.slam.world import load_world  # noqa: E402

KEYS = Keys()
ROBOT = "robot1"
RATE_HZ = 20.0


def _states(xy: np.ndarray, seed: int = 0) -> dict:
    """The fixed parts of the published states: landmarks and an SPD covariance."""
    n = len(xy)
    rng = np.random.default_rng(seed)
    A = rng.normal(0, 0.03, (3 + 2 * n, 3 + 2 * n))
    P = A @ A.T / (3 + 2 * n) + 1e-3 * np.eye(3 + 2 * n)
    return dict(robot=ROBOT, step="update", landmark_ids=np.arange(n), landmarks=xy,
                covariance=P, epoch=11)


class Publisher(threading.Thread):
    """Publishes a state every 1/RATE_HZ s of wall time (seq from 0, robot time 0.05 s
    apart) until stopped; the pose walks a circle."""

    def __init__(self, bus, base: dict) -> None:
        super().__init__(daemon=True)
        self.pub = bus.publisher(KEYS.state(ROBOT))
        self.base = base
        self.seq = -1
        self.late = 0  #: publications more than one period late (the bench fell behind)
        self.stopped = threading.Event()

    def run(self) -> None:
        start = time.monotonic()
        k = 0
        while not self.stopped.is_set():
            due = start + k / RATE_HZ
            wait = due - time.monotonic()
            if wait > 0:
                self.stopped.wait(wait)
            elif wait < -1 / RATE_HZ:
                self.late += 1
            angle = 0.05 * k
            state = SlamState(seq=k, stamp=k / RATE_HZ, pose=np.array(
                [np.cos(angle), np.sin(angle), angle + 1.57]), **self.base)
            self.pub.put(state.wire_parts())
            self.seq = k
            k += 1


def _status(bus, service: str) -> ServiceStatus | None:
    for reply in bus.get(f"{KEYS.prefix}/status/*/{service}/*", timeout=2.0):
        return ServiceStatus.from_bytes(reply.payload)
    return None


def _wait_status(bus, service: str, predicate, timeout: float = 120.0) -> ServiceStatus:
    deadline = time.monotonic() + timeout
    while True:
        status = _status(bus, service)
        if status is not None and predicate(status):
            return status
        if time.monotonic() > deadline:
            raise SystemExit(f"{service}: status never satisfied: "
                             f"{status.counts if status else None}")
        time.sleep(0.2)


def _run(name: str, base: dict, sink_args: list[str], *, extra: list[list[str]],
         window: float, warmup: float, baseline: list[str] | None) -> dict:
    """One run: router, the extra services, the sink (and the baseline consumer), the
    publisher; the window's figures."""
    ep = free_tcp_endpoint()
    procs: dict[str, Service] = {}
    out: dict = {"run": name}
    with tempfile.TemporaryDirectory() as tmp:
        try:
            procs["router"] = spawn("router", "--listen", ep)
            procs["router"].wait_for_line("router ready")
            for args in extra:
                procs[args[0]] = spawn(*args, "--connect", ep)
                procs[args[0]].wait_for_line(f"{args[0]} ready")
            procs["rerun"] = spawn("rerun", "--robot", ROBOT, "--save", f"{tmp}/b.rrd",
                                   "--late-join-timeout-s", "0", *sink_args, "--connect", ep)
            procs["rerun"].wait_for_line("rerun ready")
            if baseline is not None:
                procs[baseline[0]] = spawn(*baseline, "--connect", ep)
                procs[baseline[0]].wait_for_line(f"{baseline[0]} ready")
            bus = open_bus(BusSettings(connect=(ep,)))
            publisher = Publisher(bus, base)
            publisher.start()
            time.sleep(warmup)  # a benchmark's window, not a test's synchronisation
            s0 = _status(bus, "rerun")
            summary0 = _status(bus, "summary")
            cpu0 = {k: p.cpu_seconds() or 0.0 for k, p in procs.items()}
            t0 = time.monotonic()
            time.sleep(window)
            s1 = _status(bus, "rerun")
            summary1 = _status(bus, "summary")
            cpu1 = {k: p.cpu_seconds() or 0.0 for k, p in procs.items()}
            t1 = time.monotonic()
            publisher.stopped.set()
            publisher.join()
            last = publisher.seq
            caught = time.monotonic()
            _wait_status(bus, "rerun", lambda s: s.counts.get("seq") == last)
            out["catch_up_s"] = time.monotonic() - caught  # status: ≤ 1 s resolution
            bus.close()
        finally:
            finals = {k: stop(p)[0] for k, p in reversed(list(procs.items()))}
    assert s0 is not None and s1 is not None
    dt = t1 - t0
    out["published_per_s"] = RATE_HZ
    out["publisher_late"] = publisher.late
    out["drawn_per_s"] = (s1.counts["states"] - s0.counts["states"]) / dt
    out["superseded_in_window"] = s1.counts["superseded"] - s0.counts["superseded"]
    out["cpu_cores"] = {k: (cpu1[k] - cpu0[k]) / dt for k in cpu1}
    if summary0 is not None and summary1 is not None:
        made = "made" if "made" in summary1.counts else next(iter(summary1.counts))
        out["summaries_made_per_s"] = (summary1.counts[made] - summary0.counts[made]) / dt
        out["summaries_answered_per_s"] = (summary1.counts["answered"]
                                           - summary0.counts["answered"]) / dt
    line = next(ln for ln in finals["rerun"].splitlines() if ln.startswith("rerun stopped"))
    out["sink_final"] = json.loads(line.split(": ", 1)[1])
    out["load_1min"] = os.getloadavg()[0]
    return out


def _per_item_cpu_ms(kind: str, payloads: list[bytes], repeats: int) -> list[float]:
    """CPU ms per item of the translator + logging into an .rrd, per batch of payloads."""
    import rerun as rr

    from slamlens.services.rerun.settings import RerunSettings
    from slamlens.services.rerun.translator import RerunTranslator, log_batches

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(repeats):
            translator = RerunTranslator(RerunSettings(robot=ROBOT, source="summary"
                                                       if kind == "summary" else "state"))
            rec = rr.RecordingStream("bench")
            rec.set_sinks(rr.FileSink(f"{tmp}/{r}.rrd"))
            log_batches(rec, translator.start())
            t = time.process_time()
            for payload in payloads:
                log_batches(rec, translator.feed(kind, payload))
            out.append((time.process_time() - t) / len(payloads) * 1e3)
            rec.flush()
            rec.disconnect()
    return out


def in_process(repeats: int) -> dict:
    from slamlens.common.summary import Summariser, SummaryQuery

    rng = np.random.default_rng(5)
    base = _states(rng.uniform(0.0, 6.0, (50, 2)))
    states = [SlamState(seq=k, stamp=k / RATE_HZ, pose=np.array([0.01 * k, 0.0, 0.0]),
                        **base).to_bytes() for k in range(200)]
    n50 = _per_item_cpu_ms("state", states, repeats)
    world = load_world("large")
    large = _states(np.asarray(world.landmarks_xy, dtype=float))
    summariser = Summariser()
    query = SummaryQuery(what="clusters", budget=2000)
    summaries = []
    for k in range(200):
        state = SlamState(seq=k, stamp=k / RATE_HZ, pose=np.array([0.01 * k, 0.0, 0.0]),
                          **large)
        summaries.append(summariser.summary(state, query))
    glyphs = StateSummary.from_bytes(summaries[-1]).group_pairs
    return {"n50_state_ms": n50, "large_summary_ms": _per_item_cpu_ms("summary", summaries,
                                                                      repeats),
            "large_group_pairs": 0 if glyphs is None else len(glyphs),
            "large_summary_bytes": len(summaries[-1])}


def _median(runs: list[dict], key: str, sub: str | None = None) -> float:
    values = [r[key][sub] if sub else r[key] for r in runs]
    return statistics.median(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--window", type=float, default=30.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--only", default="1,2,3")
    args = parser.parse_args()
    only = set(args.only.split(","))
    results: dict[str, list[dict]] = {}
    if "1" in only:
        rng = np.random.default_rng(5)
        base = _states(rng.uniform(0.0, 6.0, (50, 2)))
        results["n50"] = [_run("n50", base, ["--mode", "all"], extra=[], window=args.window,
                               warmup=args.warmup,
                               baseline=["foxglove", "--robot", ROBOT, "--port", "0",
                                         "--late-join-timeout-s", "0"])
                          for _ in range(args.repeats)]
    if "2" in only:
        world = load_world("large")
        base = _states(np.asarray(world.landmarks_xy, dtype=float))
        results["large"] = [_run("large", base, ["--source", "summary"],
                                 extra=[["summary", "--robot", ROBOT]], window=args.window,
                                 warmup=args.warmup, baseline=None)
                            for _ in range(args.repeats)]
    if "3" in only:
        cost = in_process(args.repeats)
        print(f"\n== in process: {json.dumps(cost)}")
        print(f"median CPU per item: n = 50 state {statistics.median(cost['n50_state_ms']):.2f}"
              f" ms, large-world summary {statistics.median(cost['large_summary_ms']):.2f} ms "
              f"({cost['large_group_pairs']} group pairs, {cost['large_summary_bytes']} B); "
              f"× 20/s = {0.02 * statistics.median(cost['n50_state_ms']):.3f} and "
              f"{0.02 * statistics.median(cost['large_summary_ms']):.3f} cores")
    for name, runs in results.items():
        print(f"\n== {name}: {len(runs)} run(s) of {args.window:g} s")
        for r in runs:
            print(json.dumps({k: v for k, v in r.items() if k != "sink_final"}))
        print(f"median drawn/s {_median(runs, 'drawn_per_s'):.2f} (published {RATE_HZ:g}/s), "
              f"superseded in window {_median(runs, 'superseded_in_window'):g}, "
              f"sink CPU {_median(runs, 'cpu_cores', 'rerun'):.3f} cores, "
              f"catch-up {_median(runs, 'catch_up_s'):.2f} s")
        if name == "n50":
            print(f"baseline foxglove CPU {_median(runs, 'cpu_cores', 'foxglove'):.3f} cores")
        else:
            print(f"summaries made/s {_median(runs, 'summaries_made_per_s'):.2f}, answered/s "
                  f"{_median(runs, 'summaries_answered_per_s'):.2f}, summary service CPU "
                  f"{_median(runs, 'cpu_cores', 'summary'):.3f} cores")


if __name__ == "__main__":
    main()
