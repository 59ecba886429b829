"""Delivery targets (docs/delivery.md), real processes over Zenoh on loopback.

1. **MRCLAM at full speed.** ``slamlens replay ../shared/data/mrclam6 --rate 0`` (robot 1)
   through a router into an estimator, with a monitor and a recording subscriber (a
   recovering channel, as ``slamlens record`` will use) attached. Timed from the replay's
   start until the monitor has checked the last state and the recorder holds every state.
   Target: every input applied, every state recorded and checked, wall ≥ 30× real time.
   The baseline in the same run: the estimator and the replay alone (no monitor, no
   recorder), i.e. what the two consumers cost.
2. **A stalled consumer costs nothing.** The paper run at ``--rate 0`` (paced on the
   estimator) with and without a subscriber whose callback sleeps 1 s per sample plus 10
   extra ordinary subscribers. Target: throughput with them ≥ 0.95× without (median of
   ``--repeats`` alternating runs). With ``--two-host``, as it is deployed: the robot (its
   router, the estimator, the simulator) on one core and the workstation (its own router,
   the subscribers) on the other, the routers linked; the baseline there keeps one
   ordinary subscriber on the workstation, the lab's viewer (see
   :func:`stalled_two_host`).
3. **Crash recovery.** An estimator with ``--checkpoint`` is SIGKILLed in the middle of a
   run and started again: seconds from the new process's start to its first new state
   (seq beyond the checkpoint). Target ≤ 3 s.

Run: ``.venv/bin/python benchmarks/bench_delivery.py [--repeats 3] [--only 1,2,3] [--two-host]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import peek_fields  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.services.harness.collect import StateCollector  # noqa: E402
from slamlens.services.harness.procs import Service, slamlens_cmd, spawn, stop  # noqa: E402

KEYS = Keys()
ROBOT = "robot1"
MRCLAM = REPO.parent / "shared" / "data" / "mrclam6"


def _router() -> tuple[Service, str]:
    ep = free_tcp_endpoint()
    proc = spawn("router", "--listen", ep)
    proc.wait_for_line("router ready")
    return proc, ep


class Recorder(StateCollector):
    """Every state through a recovering channel (what a recorder does), on a thread."""

    def __init__(self, ep: str) -> None:
        self.seqs: set[int] = set()
        self.last = -1
        super().__init__(ep, KEYS.state(ROBOT), history_s=30.0)

    def take(self, payload: bytes) -> None:
        seq = int(peek_fields(payload, ("seq",))["seq"])
        self.seqs.add(seq)
        self.last = max(self.last, seq)


def _health_seq(bus) -> int:
    replies = bus.get(KEYS.health(ROBOT), timeout=2.0)
    return int(peek_fields(replies[0].payload, ("seq",))["seq"]) if replies else -1


def _final_json(out: str, prefix: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith(prefix)][-1]
    return json.loads(line.split(": ", 1)[1].split(" in ")[0])


def mrclam(*, with_consumers: bool) -> dict:
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    mon = rec = None
    if with_consumers:
        mon = spawn("monitor", "--robot", ROBOT, "--connect", ep)
        mon.wait_for_line("monitor ready")
        rec = Recorder(ep)
    probe = open_bus(BusSettings(connect=(ep,)))
    try:
        t0 = time.monotonic()
        replay = spawn("replay", str(MRCLAM), "--format", "mrclam", "--robot-index", "1",
                       "--rate", "0", "--connect", ep)
        replay_cpu = 0.0
        while replay.poll() is None:  # its CPU, read while it still runs
            replay_cpu = replay.cpu_seconds() or replay_cpu
            time.sleep(0.2)
        out, err = replay.communicate(timeout=1800)
        counts = _final_json(out, "replay done: ")
        total = counts["Odometry"] + counts["Observations"]
        replay_s = time.monotonic() - t0
        if with_consumers:
            assert rec is not None
            while (rec.last < total or _health_seq(probe) < total) and \
                    time.monotonic() - t0 < 1800:
                time.sleep(0.05)
        wall = time.monotonic() - t0
        first_stamp, last_stamp = _dataset_span()
        result = {"inputs": total, "replay_s": replay_s, "wall_s": wall,
                  "realtime_x": (last_stamp - first_stamp) / wall,
                  "all_applied": "all applied" in out,
                  "cpu_s": {"replay": replay_cpu, "estimator": est.cpu_seconds(),
                            "router": router.cpu_seconds(),
                            "monitor": mon.cpu_seconds() if mon else None}}
        if with_consumers:
            assert rec is not None
            result["recorded"] = len(rec.seqs)
            result["checked_up_to"] = _health_seq(probe)
    finally:
        probe.close()
        if rec is not None:
            rec.close()
        est_out, _ = stop(est)
        if mon is not None:
            mon_out, _ = stop(mon)
            result["monitor"] = _final_json(mon_out, "monitor stopped: ")
        result["estimator"] = _final_json(est_out, "estimator stopped: ")
        stop(router)
    return result


def _cpu(result: dict) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in result["cpu_s"].items() if v is not None)


_SPAN: tuple[float, float] | None = None


def _dataset_span() -> tuple[float, float]:
    global _SPAN
    if _SPAN is None:
        from slamlens.services.slam.mrclam import load_mrclam

        run = load_mrclam(str(MRCLAM), robot=1, robot_name=ROBOT)
        stamps = [float(m.stamp) for m in run.events(truth=False)]
        _SPAN = (stamps[0], stamps[-1])
    return _SPAN


def _sim_done(sim: Service) -> tuple[int, float]:
    """The inputs a simulator at ``--rate 0`` published and its wall seconds, from its
    final line, once it has ended."""
    out, _ = sim.communicate(timeout=600)
    counts = _final_json(out, "sim done: ")
    wall = float(out.split(" in ", 1)[1].split(" s")[0].rsplit(" ", 1)[-1])
    return counts["Odometry"] + counts["Observations"], wall


def stalled(*, with_load: bool, loops: int, stalled: bool = True, extra_subs: int = 10
            ) -> float:
    """States per second of a paced full-speed paper run (with the load: a subscriber
    whose callback sleeps 1 s per sample if ``stalled``, and ``extra_subs`` ordinary ones,
    each its own session in this process)."""
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    extra = []
    # zenoh-python drains a closed subscriber's queue through its callback before the
    # process may exit: once measured, the stalled client stops sleeping (else the
    # benchmark hung for an hour after printing, one second per state queued)
    measured = threading.Event()
    if with_load:
        if stalled:
            slow = open_bus(BusSettings(connect=(ep,)))
            slow.subscribe(KEYS.state(ROBOT),
                           lambda k, p: None if measured.is_set() else time.sleep(1.0))
            extra.append(slow)
        for _ in range(extra_subs):
            b = open_bus(BusSettings(connect=(ep,)))
            b.subscribe(KEYS.state(ROBOT), lambda k, p: None)
            extra.append(b)
        probe = open_bus(BusSettings(connect=(ep,)))
        while not probe.wait_for_subscriber(KEYS.state(ROBOT), timeout=5):
            pass
        probe.close()
    try:
        sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", str(loops), "--seed",
                    "1", "--connect", ep)
        states, wall = _sim_done(sim)
        return states / wall
    finally:
        measured.set()
        for b in extra:
            b.close()
        stop(est)
        stop(router)


ROBOT_CPU, WORKSTATION_CPU = "0", "1"


def _pinned(cpu: str, *args: str) -> Service:
    """A slamlens service started on one CPU (``taskset`` execs it: same pid, every thread
    it will ever make inherits the mask)."""
    return Service(["taskset", "-c", cpu, *slamlens_cmd(*args)])


def stalled_two_host(*, with_load: bool, loops: int, viewers: int = 1) -> dict:
    """Target 2 as it is deployed (deploy/README.md): the robot's router, estimator and
    simulator on one core, the workstation's router and its subscribers (their own
    process) on the other, the two routers linked over loopback. The workstation always
    has one ordinary subscriber (the viewer a lab runs); with the load a 1 s/sample one
    and ten more ordinary ones join it. ``viewers=0`` leaves the workstation without any
    subscriber (then the estimator's puts never leave its session). Returns the
    estimator's states/s and its CPU ms per state over the simulator's run."""
    ep_r = free_tcp_endpoint()
    robot_router = _pinned(ROBOT_CPU, "router", "--listen", ep_r)
    robot_router.wait_for_line("router ready")
    ep_w = free_tcp_endpoint()
    ws_router = _pinned(WORKSTATION_CPU, "router", "--listen", ep_w, "--connect", ep_r)
    ws_router.wait_for_line("router ready")
    est = _pinned(ROBOT_CPU, "estimator", "--robot", ROBOT, "--connect", ep_r)
    est.wait_for_line("estimator ready")
    subs = None
    try:
        if with_load or viewers:
            extra = viewers + 10 if with_load else viewers
            subs = subprocess.Popen(
                ["taskset", "-c", WORKSTATION_CPU, sys.executable,
                 str(REPO / "benchmarks" / "_workstation_subscribers.py"), "--connect", ep_w,
                 "--robot", ROBOT, "--extra", str(extra),
                 *(() if with_load else ("--no-stalled",))],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert subs.stdout is not None and subs.stdout.readline().strip() == "subscribed"
            probe = open_bus(BusSettings(connect=(ep_r,)))  # they reached the robot's router
            while not probe.wait_for_subscriber(KEYS.state(ROBOT), timeout=5):
                pass
            probe.close()
        cpu0 = est.cpu_seconds() or 0.0
        sim = _pinned(ROBOT_CPU, "sim", "--robot", ROBOT, "--rate", "0", "--loops",
                      str(loops), "--seed", "1", "--connect", ep_r)
        states, wall = _sim_done(sim)
        cpu = (est.cpu_seconds() or 0.0) - cpu0
        result = {"states_per_s": states / wall, "est_cpu_ms_per_state": 1e3 * cpu / states}
        if subs is not None:
            out_subs, _ = subs.communicate("", timeout=30)  # stdin closed: counts, exit
            result["received"] = json.loads(out_subs.strip().splitlines()[-1])
            result["states"] = states
        return result
    finally:
        if subs is not None and subs.poll() is None:
            subs.kill()
        stop(est)
        stop(ws_router)
        stop(robot_router)


def recovery() -> float:
    """Seconds from a restarted estimator's start to its first new state."""
    router, ep = _router()
    with tempfile.TemporaryDirectory() as tmp:
        est = spawn("estimator", "--robot", ROBOT, "--connect", ep, "--checkpoint", tmp)
        est.wait_for_line("estimator ready")
        rec = Recorder(ep)
        sim = spawn("sim", "--robot", ROBOT, "--rate", "4", "--loops", "6", "--seed", "1",
                    "--connect", ep)
        try:
            while rec.last < 200 or not any(Path(tmp).iterdir()):
                time.sleep(0.05)
            time.sleep(1.1)  # a checkpoint a second: let one be written at seq ≥ 200
            est.kill()
            est.wait(10)
            at = rec.last
            started = time.monotonic()
            est = spawn("estimator", "--robot", ROBOT, "--connect", ep, "--checkpoint", tmp)
            while rec.last <= at and time.monotonic() - started < 60:
                time.sleep(0.01)
            took = time.monotonic() - started
        finally:
            stop(sim)
            rec.close()
            stop(est)
            stop(router)
    return took


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", default="1,2,3")
    ap.add_argument("--loops", type=int, default=20, help="paper loops for target 2")
    ap.add_argument("--two-host", action="store_true",
                    help="target 2 as deployed: robot and workstation on a core each")
    args = ap.parse_args()
    parts = {int(p) for p in args.only.split(",")}
    if 1 in parts:
        base = mrclam(with_consumers=False)
        print(f"MRCLAM robot 1, replay + estimator alone: {base['inputs']} inputs in "
              f"{base['wall_s']:.1f} s = {base['realtime_x']:.1f}x real time; CPU s "
              f"{_cpu(base)}")
        runs = [mrclam(with_consumers=True) for _ in range(args.repeats)]
        for r in runs:
            print(f"  with monitor + recorder: {r['wall_s']:.1f} s = {r['realtime_x']:.1f}x "
                  f"real time; replay done after {r['replay_s']:.1f} s; all applied "
                  f"{r['all_applied']}; recorded {r['recorded']}/{r['inputs'] + 1}; checked up "
                  f"to seq {r['checked_up_to']}; monitor lost {r['monitor']['lost']}; CPU s "
                  f"{_cpu(r)} (monitor's checking thread "
                  f"{r['monitor'].get('worker_cpu_s', float('nan')):.1f})")
        med = statistics.median(r["realtime_x"] for r in runs)
        print(f"target 1: median {med:.1f}x real time (target >= 30x); "
              f"ratio to the estimator alone {med / base['realtime_x']:.2f}")
    if 2 in parts and args.two_host:
        runs_a, runs_b, runs_0 = [], [], []
        for _ in range(args.repeats):  # alternating
            runs_a.append(stalled_two_host(with_load=False, loops=args.loops))
            runs_b.append(stalled_two_host(with_load=True, loops=args.loops))
            runs_0.append(stalled_two_host(with_load=False, loops=args.loops, viewers=0))
        a = statistics.median(r["states_per_s"] for r in runs_a)
        b = statistics.median(r["states_per_s"] for r in runs_b)
        ca = statistics.median(r["est_cpu_ms_per_state"] for r in runs_a)
        cb = statistics.median(r["est_cpu_ms_per_state"] for r in runs_b)
        z = statistics.median(r["states_per_s"] for r in runs_0)
        print(f"target 2, two hosts (robot on CPU {ROBOT_CPU}, workstation on CPU "
              f"{WORKSTATION_CPU}): {a:.0f} states/s with one viewer on the workstation, "
              f"{b:.0f} with a 1 s/sample subscriber and 10 more beside it: ratio {b / a:.3f} "
              f"(target >= 0.95); with no subscriber at all {z:.0f} (the estimator's puts "
              f"never leave its session; ratio of the loaded run to it {b / z:.3f});"
              f" estimator CPU {ca:.3f} -> {cb:.3f} ms per state (ratio {cb / ca:.3f}); "
              f"runs {[round(r['states_per_s']) for r in runs_a]} / "
              f"{[round(r['states_per_s']) for r in runs_b]}; received by the subscribers "
              f"(of the states) {[(r['received'], r['states']) for r in runs_b]}")
    elif 2 in parts:
        without, with_ = [], []
        for _ in range(args.repeats):
            without.append(stalled(with_load=False, loops=args.loops))
            with_.append(stalled(with_load=True, loops=args.loops))
        a, b = statistics.median(without), statistics.median(with_)
        print(f"target 2: {a:.0f} states/s alone, {b:.0f} with a 1 s/sample subscriber and "
              f"10 more: ratio {b / a:.3f} (target >= 0.95); runs {without} / {with_}")
        # which of the two costs what: the stalled one alone, the ten ordinary ones alone
        alone, only_stalled, only_ten = [], [], []
        for _ in range(args.repeats):
            alone.append(stalled(with_load=False, loops=args.loops))
            only_stalled.append(stalled(with_load=True, loops=args.loops, extra_subs=0))
            only_ten.append(stalled(with_load=True, loops=args.loops, stalled=False))
        a = statistics.median(alone)
        print(f"  the stalled subscriber alone: ratio "
              f"{statistics.median(only_stalled) / a:.3f}; the ten ordinary ones alone: "
              f"{statistics.median(only_ten) / a:.3f} (runs {alone} / {only_stalled} / "
              f"{only_ten})")
    if 3 in parts:
        times = [recovery() for _ in range(args.repeats)]
        print(f"target 3: first new state {statistics.median(times):.2f} s after the restart "
              f"(median of {times}; target <= 3 s)")


if __name__ == "__main__":
    main()
