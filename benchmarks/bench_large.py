"""The n = 1000 targets: the whole pipeline on the ``large`` world, on one host.

Real processes over Zenoh on loopback, as ``slamlens demo`` runs them: a router, the
estimator, the monitor, the synthetic overhead camera with registration at 30 fps, the viewer
with one view open (an MJPEG client), and ``slamlens sim --scenario large --rate 0`` (paced on
the estimator). Once the map holds every landmark (n = 1000), a window of ``--window`` s is
measured:

* **estimator**: states published per second (Δseq / Δt of the estimator's own
  ``state?header`` answer, polled at 5 Hz: the bench receives no 32 MB state itself), median
  of 1 s bins. Target ≥ 100 states/s.
* **viewer**: distinct states rendered per second (the ``X-State-Seq`` of the MJPEG parts),
  median of 1 s bins, with the camera at 30 fps; and its ``/api/status`` fps and
  render_ms_median. Target ≥ 10 states/s.
* **monitor**: states it checked per second (Health messages in the window, a mean: it
  checks in bursts), and whether it kept up: the ``sampled_out`` and ``behind`` statistics
  of its Health (docs/monitor.md, large maps).

Baselines measured in the same run: (a) the estimator and the simulator alone on the same
world (no monitor, camera or viewer): what the consumers cost it; (b) the same whole pipeline
on the ``paper`` world (n = 15): what n = 1000 costs. Ratios are printed against both.
CPU seconds per process over the window and the load average are printed too.

``--profile`` first profiles the estimator service in this process at n = 1000 (a real
Zenoh session, shared memory on): where a state's time goes (EKF update, materialising the
covariance, encoding, the shared-memory copy, the publish), and the publish path as it was
before the large-map work (msgpack.packb of a freshly materialised state) timed on the same states.
When the window opens the bench prints a line with the processes' ids, so a sampling
profiler can be attached for it (e.g. ``py-spy record -p PID -d 20``).
``--profile-viewer`` profiles the viewer's state → picture path in this process at
n = 1000 (:func:`profile_viewer`); ``--profile-only`` skips the pipeline runs.

Run: ``.venv/bin/python benchmarks/bench_large.py [--window 20] [--repeats 1] [--profile]
[--profile-viewer] [--profile-only] [--only large-alone,large-full,paper-full]
[--monitor-share S] [--sim-rate R]`` (about 5 min per repeat on the shared 2-core machine;
``--monitor-share 1`` is the baseline of the monitor's ``large_share`` rest, docs/monitor.md).

``--sim-rate 1`` drives the simulator at the robot's own rate (10 Hz odometry, a state per
predict and per update: ~20 states/s) instead of as fast as the estimator goes: the stress
run has the estimator take a whole core of the two, which a robot's estimator, on the robot,
does not take from the workstation. Building the large map then takes ~7 min of robot time.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path

import msgpack

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the services run (docs/monitor.md)

from _large_profiles import profile_estimator, profile_viewer  # noqa: E402

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.memory import keep_freed_memory  # noqa: E402
from slamlens.common.messages import Health  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.services.harness.procs import Service, spawn, stop  # noqa: E402

KEYS = Keys()
ROBOT = "robot1"
CAMERA = "overhead"
#: the synthetic overhead camera over each world: arena (map frame), height, marker size
CAMERAS = {
    "paper": ("-1,-1,2,2", "3", "0.2"),
    # the 41 m x 26 m arena from 30 m up; a 1 m marker is ~30 px in a 1280 px image
    "large": ("-1.5,-1.5,39.5,24.5", "30", "1.0"),
}
FULL_N = {"paper": 15, "large": 1000}


class Header(threading.Thread):
    """Polls the estimator's ``state?header`` (seq, n) at 5 Hz."""

    def __init__(self, bus) -> None:
        super().__init__(daemon=True)
        self.bus = bus
        self.samples: list[tuple[float, int, int]] = []  # (time, seq, n)
        self.stopped = threading.Event()

    def run(self) -> None:
        while not self.stopped.wait(0.2):
            for reply in self.bus.get(KEYS.state(ROBOT) + "?header", timeout=1.0):
                h = msgpack.unpackb(reply.payload)
                if "n" in h:
                    self.samples.append((time.monotonic(), int(h["seq"]), int(h["n"])))

    def latest_n(self) -> int:
        return self.samples[-1][2] if self.samples else 0


class HealthLog:
    """Every Health: (arrival, seq, sampled_out, behind)."""

    def __init__(self, bus) -> None:
        self.rows: list[tuple[float, int, float, float]] = []
        bus.subscribe(KEYS.health(ROBOT), self._on)

    def _on(self, _key: str, payload: bytes) -> None:
        h = Health.from_bytes(payload)
        self.rows.append((time.monotonic(), h.seq, float(h.statistics.get("sampled_out", 0)),
                          float(h.statistics.get("behind", 0))))


class Mjpeg(threading.Thread):
    """One open view: reads ``/stream.mjpg`` and keeps (arrival, X-State-Seq) per part."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(daemon=True)
        self.conn = http.client.HTTPConnection(host, port, timeout=30)
        self.parts: list[tuple[float, int | None]] = []
        self.stopped = threading.Event()
        self.error: str | None = None  #: why the stream ended before stop() (a dead reader)

    def run(self) -> None:
        self.conn.request("GET", "/stream.mjpg?client=bench")
        response = self.conn.getresponse()
        try:
            while not self.stopped.is_set():
                headers = {}
                line = response.readline()
                while line.strip() == b"":
                    line = response.readline()
                while (line := response.readline().strip()):
                    name, _, value = line.decode().partition(":")
                    headers[name.strip().lower()] = value.strip()
                response.read(int(headers["content-length"]))
                seq = headers.get("x-state-seq")
                self.parts.append((time.monotonic(), int(seq) if seq else None))
        except (OSError, ValueError, KeyError, AttributeError) as exc:
            if not self.stopped.is_set():  # not our own close: say so in the results
                self.error = f"{type(exc).__name__}: {exc}"[:200]

    def stop(self) -> None:
        self.stopped.set()
        self.conn.close()


def _status(host: str, port: int) -> dict:
    conn = http.client.HTTPConnection(host, port, timeout=10)
    conn.request("GET", "/api/status")
    data = json.loads(conn.getresponse().read())
    conn.close()
    return data


def _bins(events: list[tuple[float, float]], t0: float, t1: float) -> float:
    """Median over 1 s bins of the summed weights of ``events`` (time, weight)."""
    bins = max(1, int(t1 - t0))
    totals = [0.0] * bins
    for t, w in events:
        k = int(t - t0)
        if 0 <= k < bins:
            totals[k] += w
    return statistics.median(totals)


def _cpu(procs: dict[str, Service]) -> dict[str, float]:
    return {name: p.cpu_seconds() or 0.0 for name, p in procs.items()}


def _start(endpoint: str, world: str, full: bool,
           monitor_args: tuple[str, ...]) -> tuple[dict[str, Service], tuple[str, int] | None]:
    """The estimator and, for the whole pipeline, the monitor, the camera with its
    registration and the viewer, each ready; (the processes, the viewer's host and port)."""
    procs: dict[str, Service] = {}
    procs["estimator"] = spawn("estimator", "--robot", ROBOT, "--connect", endpoint, "-q")
    procs["estimator"].wait_for_line("estimator ready")
    if not full:
        return procs, None
    arena, height, marker = CAMERAS[world]
    procs["monitor"] = spawn("monitor", "--robot", ROBOT, "--connect", endpoint, "-q",
                             *monitor_args)
    procs["registration"] = spawn(
        "registration", "--camera", CAMERA, "--robot", ROBOT, "--source", "synthetic",
        "--fps", "30", f"--arena={arena}", "--camera-height", height,
        "--marker-size", marker, "--connect", endpoint, "-q")
    procs["viewer"] = spawn("viewer", "--robot", ROBOT, "--camera", CAMERA,
                            "--http", "127.0.0.1:0", "--connect", endpoint, "-q")
    procs["monitor"].wait_for_line("monitor ready")
    procs["registration"].wait_for_line("registration ready")
    url = procs["viewer"].wait_for_line("viewer ready").split()[-1]
    host, port = url.removeprefix("http://").split("/")[0].split(":")
    return procs, (host, int(port))


def _sim_args(endpoint: str, world: str, *, full: bool, seed: int,
              sim_rate: float) -> list[str]:
    args = ["sim", "--robot", ROBOT, "--scenario", world, "--rate", f"{sim_rate:g}",
            "--seed", str(seed), "--loops", "2" if world == "large" else "40",
            "--connect", endpoint, "-q", "--progress", "off"]
    return args + ["--hold", "3"] if full else args  # the camera registers the map first


def _wait_full(sim: Service, header: Header, world: str) -> None:
    """Until the estimator's map holds the world's every landmark."""
    while header.latest_n() < FULL_N[world]:
        if sim.poll() is not None:
            raise RuntimeError(f"the sim ended before n = {FULL_N[world]}: {sim.output()}")
        time.sleep(0.2)


def _full_figures(reader: Mjpeg, health: HealthLog, status_end: dict,
                  finals: dict[str, str], t0: float, t1: float) -> dict:
    """The viewer's, the camera's and the monitor's figures over the window [t0, t1]."""
    seen: set[int] = set()
    rendered = []
    for t, seq in reader.parts:
        if seq is not None and seq not in seen:
            seen.add(seq)
            rendered.append((t, 1.0))
    in_window = [r for r in health.rows if t0 <= r[0] <= t1]
    sampled = (in_window[-1][2] - in_window[0][2]) if len(in_window) > 1 else 0.0
    return {
        "viewer_states_s": _bins(rendered, t0, t1),
        "viewer_parts_s": _bins([(t, 1.0) for t, _ in reader.parts], t0, t1),
        "viewer_fps": status_end.get("fps"),
        "render_ms_median": status_end.get("render_ms_median"),
        "registered": bool(status_end.get("cameras")
                           and status_end["cameras"][0].get("registration")),
        "viewer_state_rate_hz": (status_end.get("state") or {}).get("rate_hz"),
        "camera_hz": (status_end.get("cameras") or [{}])[0].get("frame", {}).get("rate_hz"),
        # checks come in bursts (a run of states, then a jump to the newest): a mean
        "monitor_checked_s": len(in_window) / (t1 - t0),
        "monitor_sampled_out": sampled,
        "monitor_behind_max": max((r[3] for r in in_window), default=0.0),
        "monitor_sampled_total": health.rows[-1][2] if health.rows else 0.0,
        "mjpeg_error": reader.error,
        "mjpeg_parts_in_window": sum(1 for t, _ in reader.parts if t0 <= t <= t1),
        "detection": _detection(finals.get("registration", "")),
    }


def run(endpoint: str, world: str, *, full: bool, window_s: float, seed: int,
        monitor_args: tuple[str, ...] = (), sim_rate: float = 0.0) -> dict:
    """One pipeline on ``world``: measured for ``window_s`` once the map is complete."""
    procs: dict[str, Service] = {}
    bus = open_bus(BusSettings(connect=(endpoint,)))
    reader: Mjpeg | None = None
    header = Header(bus)
    try:
        procs, viewer_at = _start(endpoint, world, full, monitor_args)
        if viewer_at is not None:
            reader = Mjpeg(*viewer_at)
            reader.start()
        health = HealthLog(bus)
        header.start()
        t_start = time.monotonic()
        procs["sim"] = spawn(*_sim_args(endpoint, world, full=full, seed=seed,
                                        sim_rate=sim_rate))
        _wait_full(procs["sim"], header, world)
        t_full = time.monotonic()
        cpu0, load0 = _cpu(procs), os.getloadavg()[0]
        t0 = time.monotonic()
        pids = " ".join(f"{k}={p.pid}" for k, p in procs.items())
        print(f"  window open for {window_s:.0f} s ({world}, pids {pids})", flush=True)
        time.sleep(window_s)
        t1 = time.monotonic()
        cpu1, load1 = _cpu(procs), os.getloadavg()[0]
        status_end = _status(*viewer_at) if viewer_at else None
        if procs["sim"].poll() is not None:
            print(f"  (warning: the sim ended inside the window, {world})", flush=True)
    finally:
        header.stopped.set()
        if reader is not None:
            reader.stop()
        finals = {name: stop(procs[name])[0] for name in
                  ("sim", "viewer", "registration", "monitor", "estimator") if name in procs}
        bus.close()

    hs = [(t, seq) for t, seq, n in header.samples if t0 <= t <= t1]
    est_events = [(hs[i][0], float(hs[i][1] - hs[i - 1][1])) for i in range(1, len(hs))]
    out: dict = {
        "world": world, "full": full, "window_s": t1 - t0, "load": (load0 + load1) / 2,
        "sim_rate": sim_rate,
        "build_s": t_full - t_start,
        "estimator_states_s": _bins(est_events, t0, t1),
        "estimator_mean_states_s": (hs[-1][1] - hs[0][1]) / (hs[-1][0] - hs[0][0]),
        "cpu_s": {k: cpu1[k] - cpu0.get(k, 0.0) for k in cpu1},
    }
    if full:
        assert reader is not None and status_end is not None
        out.update(_full_figures(reader, health, status_end, finals, t0, t1))
    return out


def _detection(output: str) -> dict[str, int]:
    """How the registration detected its frames over the whole run (its final line):
    whole, in windows only, windows that lost a marker (docs/registration.md)."""
    for line in output.splitlines():
        if line.startswith("registration stopped: "):
            cameras = json.loads(line.removeprefix("registration stopped: "))["cameras"]
            counts = cameras.get(CAMERA, {})
            return {k: int(counts.get(k, 0)) for k in
                    ("frames", "detected_whole", "detected_in_windows", "window_fallbacks")}
    return {}


def _rate_note(r: dict) -> str:
    return f" (sim at {r['sim_rate']:g}x real time)" if r["sim_rate"] else ""


def _line(r: dict) -> str:
    text = (f"{r['world']:>5} {'pipeline' if r['full'] else 'alone   '} n={FULL_N[r['world']]}"
            f"{_rate_note(r)}: "
            f"estimator {r['estimator_states_s']:.0f} states/s (mean "
            f"{r['estimator_mean_states_s']:.0f})")
    if r["full"]:
        text += (f"; viewer renders {r['viewer_states_s']:.0f} states/s "
                 f"({r['viewer_parts_s']:.0f} frames/s, fps {r['viewer_fps']:.1f}, "
                 f"render {r['render_ms_median'] or 0:.1f} ms median, camera "
                 f"{r['camera_hz'] or 0:.0f} Hz, registered {r['registered']}); monitor "
                 f"checks {r['monitor_checked_s']:.1f} states/s, sampled_out "
                 f"{r['monitor_sampled_out']:.0f} in the window, behind ≤ "
                 f"{r['monitor_behind_max']:.0f}; MJPEG parts in the window "
                 f"{r['mjpeg_parts_in_window']}"
                 + (f", the stream ended: {r['mjpeg_error']}" if r["mjpeg_error"] else ""))
        if r["detection"]:
            d = r["detection"]
            text += (f"\n      registration over the run: {d['frames']} frames, detected "
                     f"{d['detected_whole']} whole, {d['detected_in_windows']} in windows, "
                     f"{d['window_fallbacks']} windows lost a marker")
    cpu = ", ".join(f"{k} {v:.1f}" for k, v in r["cpu_s"].items())
    return (text + f"\n      window {r['window_s']:.1f} s after {r['build_s']:.0f} s to build "
            f"the map, load {r['load']:.2f}; CPU s in the window: {cpu}")


RUNS = (("large-alone", "large", False), ("large-full", "large", True),
        ("paper-full", "paper", True))


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--window", type=float, default=20.0, help="seconds measured at full n")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--profile", action="store_true",
                        help="first profile the estimator service in-process at n = 1000")
    parser.add_argument("--profile-viewer", action="store_true",
                        help="first profile the viewer's state → picture path at n = 1000")
    parser.add_argument("--profile-only", action="store_true",
                        help="only the profiles, no pipeline runs")
    parser.add_argument("--monitor-share", type=float, default=None,
                        help="the monitor's --large-share (default: its own, 0.25; 1 = the "
                             "monitor never rests, the baseline for that rule)")
    parser.add_argument("--sim-rate", type=float, default=0.0,
                        help="the simulator's --rate (default 0: as fast as the estimator "
                             "goes, the stress run; 1: the robot's own rate, 20 states/s, "
                             "~7 min to build the large map)")
    parser.add_argument("--only", default="large-alone,large-full,paper-full",
                        help="the pipeline runs to make, comma-separated (default: all three)")
    return parser


def _runs(args: argparse.Namespace, wanted: set[str]) -> dict[str, list[dict]]:
    """Each wanted pipeline, ``--repeats`` times, over one router; each run's line printed."""
    router = spawn("router", "--listen", (endpoint := free_tcp_endpoint()), "-q")
    router.wait_for_line("router ready")
    results: dict[str, list[dict]] = {name: [] for name, _, _ in RUNS}
    share = () if args.monitor_share is None else ("--large-share", str(args.monitor_share))
    try:
        for k in range(args.repeats):
            for name, world, full in RUNS:
                if name in wanted:
                    r = run(endpoint, world, full=full, window_s=args.window, seed=k,
                            monitor_args=share, sim_rate=args.sim_rate)
                    results[name].append(r)
                    print(_line(r), flush=True)
    finally:
        stop(router)
    return results


def _report(results: dict[str, list[dict]], wanted: set[str], window: float) -> None:
    """Medians over the repeats; with all three runs, the ratios between them."""
    def med(name: str, key: str) -> float:
        return statistics.median(float(r[key] or 0.0) for r in results[name])

    if wanted != {name for name, _, _ in RUNS}:
        for name in sorted(wanted):  # a subset: each run's median, no ratios between them
            viewer = (f", viewer {med(name, 'viewer_states_s'):.0f} states/s"
                      if name.endswith("-full") else "")
            print(f"{name}: estimator {med(name, 'estimator_states_s'):.0f} states/s"
                  f"{viewer} (median of {len(results[name])})")
        return
    est, alone = med("large-full", "estimator_states_s"), med("large-alone",
                                                              "estimator_states_s")
    paper_est = med("paper-full", "estimator_states_s")
    view, paper_view = med("large-full", "viewer_states_s"), med("paper-full",
                                                                 "viewer_states_s")
    print(f"ESTIMATOR at n = 1000 in the pipeline: {est:.0f} states/s published (target ≥ 100)"
          f"; alone {alone:.0f} states/s (pipeline/alone {est / alone:.2f}×); paper pipeline "
          f"{paper_est:.0f} states/s (n=1000/n=15 {est / paper_est:.3f}×)")
    print(f"VIEWER at n = 1000, camera 30 fps: {view:.0f} states/s rendered (target ≥ 10), "
          f"render_ms_median {med('large-full', 'render_ms_median'):.1f} ms; paper "
          f"{paper_view:.0f} states/s (ratio {view / max(paper_view, 1e-9):.2f}×)")
    print(f"MONITOR at n = 1000: checks {med('large-full', 'monitor_checked_s'):.1f} states/s "
          f"of {est:.0f} published, sampled_out {med('large-full', 'monitor_sampled_out'):.0f} "
          f"in {window:.0f} s; paper: checks {med('paper-full', 'monitor_checked_s'):.0f} "
          f"of {paper_est:.0f}, sampled_out {med('paper-full', 'monitor_sampled_out'):.0f}")


def main() -> None:
    parser = _parser()
    args = parser.parse_args()
    wanted = set(args.only.split(","))
    unknown = wanted - {name for name, _, _ in RUNS}
    if unknown:
        parser.error(f"--only: unknown run(s) {', '.join(sorted(unknown))}")
    if args.profile or args.profile_viewer:
        keep_freed_memory()  # the in-process profiles allocate as the services do
    if args.profile:
        profile_estimator()
    if args.profile_viewer:
        profile_viewer()
    if not args.profile_only:
        _report(_runs(args, wanted), wanted, args.window)


if __name__ == "__main__":
    main()
