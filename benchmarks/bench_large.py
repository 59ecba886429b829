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


def run(endpoint: str, world: str, *, full: bool, window_s: float, seed: int,
        monitor_args: tuple[str, ...] = (), sim_rate: float = 0.0) -> dict:
    """One pipeline on ``world``: measured for ``window_s`` once the map is complete."""
    procs: dict[str, Service] = {}
    bus = open_bus(BusSettings(connect=(endpoint,)))
    reader: Mjpeg | None = None
    header = Header(bus)
    try:
        procs["estimator"] = spawn("estimator", "--robot", ROBOT, "--connect", endpoint, "-q")
        procs["estimator"].wait_for_line("estimator ready")
        viewer_at = None
        if full:
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
            viewer_at = (host, int(port))
            reader = Mjpeg(*viewer_at)
            reader.start()
        health = HealthLog(bus)
        header.start()
        sim_args = ["sim", "--robot", ROBOT, "--scenario", world, "--rate", f"{sim_rate:g}",
                    "--seed", str(seed), "--loops", "2" if world == "large" else "40",
                    "--connect", endpoint, "-q", "--progress", "off"]
        if full:
            sim_args += ["--hold", "3"]  # the camera registers the map frame first
        t_start = time.monotonic()
        procs["sim"] = spawn(*sim_args)
        while header.latest_n() < FULL_N[world]:
            if procs["sim"].poll() is not None:
                raise RuntimeError(f"the sim ended before n = {FULL_N[world]}: "
                                   f"{procs['sim'].output()}")
            time.sleep(0.2)
        t_full = time.monotonic()
        status_start = _status(*viewer_at) if viewer_at else None
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
        finals: dict[str, str] = {}
        for name in ("sim", "viewer", "registration", "monitor", "estimator"):
            if name in procs:
                finals[name] = stop(procs[name])[0]
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
        seen: set[int] = set()
        rendered = []
        for t, seq in reader.parts:
            if seq is not None and seq not in seen:
                seen.add(seq)
                rendered.append((t, 1.0))
        in_window = [r for r in health.rows if t0 <= r[0] <= t1]
        sampled = (in_window[-1][2] - in_window[0][2]) if len(in_window) > 1 else 0.0
        out.update({
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
            "status_start": status_start is not None,
            "mjpeg_error": reader.error,
            "mjpeg_parts_in_window": sum(1 for t, _ in reader.parts if t0 <= t <= t1),
            "detection": _detection(finals.get("registration", "")),
        })
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


def _fill_to_1000(est, events) -> None:
    """Feed ``events`` (an iterator: what is left goes on from there) straight into the
    filter ``est`` until its map has 1000 landmarks."""
    from slamlens.common.messages import Observations, Odometry

    for m in events:
        if isinstance(m, (Odometry, Observations)):
            est.apply(m)
        if est.n >= 1000:
            break


def profile_estimator(events: int = 300) -> None:
    """cProfile of ``EstimatorService.apply`` at n = 1000, grouped by what the time is."""
    import cProfile
    import pstats

    from slamlens.common.messages import Observations, Odometry, SlamState
    from slamlens.services.slam import ekf
    from slamlens.services.slam.estimator_service import EstimatorService
    from slamlens.services.slam.input_order import Input
    from slamlens.services.slam.settings import EstimatorSettings
    from slamlens.services.slam.sim import Simulator
    from slamlens.services.slam.world import load_world

    endpoint = free_tcp_endpoint()
    router = open_bus(BusSettings(listen=(endpoint,), mode="router"))
    bus, sub = (open_bus(BusSettings(connect=(endpoint,))) for _ in range(2))
    received = [0]
    sub.session.declare_subscriber(  # a same-host consumer: the payload stays in shm
        KEYS.state(ROBOT), lambda _s: received.__setitem__(0, received[0] + 1))
    service = EstimatorService(bus, keys=KEYS, settings=EstimatorSettings(robot=ROBOT))
    stream = Simulator(load_world("large"), loops=2, seed=0).events()
    est = service.estimator
    _fill_to_1000(est, stream)  # the first loop straight into the filter: the map, unpublished
    items = [Input("odometry" if isinstance(m, Odometry) else "observations", m)
             for m in stream if isinstance(m, (Odometry, Observations))][:events + 20]
    for item in items[:20]:  # warm: the shared-memory pool is made on first use
        service.apply(item)
    reused_before = est.published.buffers.reused
    profiler = cProfile.Profile()
    t0 = time.perf_counter()
    profiler.enable()
    for item in items[20:]:
        service.apply(item)
    profiler.disable()
    wall = time.perf_counter() - t0
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    groups = {
        "EKF update (downdate, gains)": ("downdate_lower", "robot_columns", "_check_update",
                                         "mahalanobis", "initialise"),
        "EKF predict": ("predict",),
        "materialise P after an update (symmetric)": ("symmetric",),
        "materialise P after a predict (copy + robot rows)": ("symmetric_after_predict",),
        "patch P in place after a predict (robot rows)": ("robot_rows_into",),
        "finite checks on construction (sums)": ("reduce",),
        "shared-memory copy (ShmPool.wrap)": ("wrap",),
        "encode (wire_parts, msgpack of the small fields)": ("wire_parts", "_wire_dict",
                                                            "encode_array", "pack"),
        "Zenoh put": ("put",),
    }
    spent = {name: 0.0 for name in groups}
    for (_file, _line, func), (_cc, _nc, tottime, _ct, _callers) in stats.items():
        for name, funcs in groups.items():
            if func in funcs or any(func.startswith(f"<method '{f}'") for f in funcs):
                spent[name] += tottime
    n = len(items) - 20
    print(f"PROFILE estimator service at n = {est.n}: {n} events in {wall:.2f} s = "
          f"{n / wall:.0f} states/s (under cProfile), load {os.getloadavg()[0]:.2f}; "
          f"{received[0]} received by a same-host subscriber, shm {bus.shm.shared} / plain "
          f"{bus.shm.plain}; predict states patched in place {est.predicts_in_place}, "
          f"covariance buffers reused {est.published.buffers.reused - reused_before} of {n}")
    for name, t in sorted(spent.items(), key=lambda kv: -kv[1]):
        print(f"  {name:52s} {t / n * 1e3:6.2f} ms per state ({t / wall:5.1%})")
    # the same states through the old publish path (before the large-map work), unprofiled
    state = est.to_state(seq=1, stamp=0.0, step="update")
    old, new = [], []
    for _ in range(7):
        t = time.perf_counter()
        cov = ekf.symmetric(est.store.L, 3 + 2 * est.n)
        cov.flags.writeable = False
        old_state = SlamState(robot=ROBOT, seq=1, stamp=0.0, step="update", pose=est.pose,
                              landmark_ids=est.landmark_ids, landmarks=est.landmarks,
                              covariance=cov)
        d = old_state.to_dict()
        d["covariance"] = {"dtype": "<f8", "shape": [cov.size], "data": cov.tobytes()}
        bus.shm.wrap(msgpack.packb(d, use_bin_type=True))
        old.append(time.perf_counter() - t)
        est.published.dirty = True  # as after an update: the whole matrix, no predict shortcut
        t = time.perf_counter()
        state = est.to_state(seq=1, stamp=0.0, step="update")
        bus.shm.wrap(state.wire_parts())
        new.append(time.perf_counter() - t)
        del state
    alone = []
    N = 3 + 2 * est.n
    out = est.published.buffers.array((N, N), "<f8")
    for _ in range(7):
        t = time.perf_counter()
        ekf.symmetric(est.store.L, N, out=out)
        alone.append(time.perf_counter() - t)
    print(f"  ekf.symmetric alone at N = {N}, into one buffer: "
          f"{statistics.median(alone) * 1e3:.1f} ms (median of 7)")
    o, w = statistics.median(old) * 1e3, statistics.median(new) * 1e3
    print(f"  publish path of an update state (materialise + encode + shm): before {o:.1f} ms, "
          f"now {w:.1f} ms (ratio {o / w:.1f}×; median of 7)")
    for b in (bus, sub, router):
        b.close()


def profile_viewer(repeats: int = 9) -> None:
    """The viewer's state → picture path in this process at n = 1000 (a real state of the
    ``large`` world): thread CPU ms per picture of a new state and per camera frame of the
    same state, the plot sample, decoding; baselines in the same run: the scene computed
    for every picture (a fresh ``Renderer`` each time, as before the viewer work)
    and the plot sample as before (every pair's P_d gathered, then its size)."""
    import cProfile
    import dataclasses
    import pstats

    import cv2
    import numpy as np

    from slamlens.common.geometry import all_relative_covariances, pd_size_m
    from slamlens.common.messages import SlamState
    from slamlens.services.slam.estimator import Estimator
    from slamlens.services.slam.settings import EstimatorSettings
    from slamlens.services.slam.sim import Simulator
    from slamlens.services.slam.world import load_world
    from slamlens.services.visualiser.camera_model import CameraModel
    from slamlens.services.visualiser.legend import draw_legend, rejected_legend
    from slamlens.services.visualiser.render import Renderer
    from slamlens.services.visualiser.series import SeriesStore
    from slamlens.services.visualiser.settings import ViewSettings

    est = Estimator(EstimatorSettings(robot=ROBOT))
    _fill_to_1000(est, Simulator(load_world("large"), loops=2, seed=0).events())
    payload = est.to_state(seq=1, stamp=0.0, step="update").to_bytes()
    state0 = SlamState.from_bytes(payload, check_symmetry=False)
    states = [dataclasses.replace(state0, seq=2 + k) for k in range(repeats + 1)]
    camera = CameraModel.top_down(bounds_xy=(-1.5, -1.5, 39.5, 24.5), width=1280, height=720)
    frames = [np.full((720, 1280, 3), 60 + k, np.uint8) for k in range(repeats + 1)]

    def cpu_ms(f, k_from: int = 1) -> float:
        spent = []
        for k in range(repeats + 1):
            t = time.thread_time()
            f(k)
            spent.append((time.thread_time() - t) * 1e3)
        return statistics.median(spent[k_from:])

    def picture(renderer: Renderer, state: SlamState, k: int, settings: ViewSettings) -> None:
        cv2.imencode(".jpg", renderer.render(frames[k], state=state, camera=camera,
                                             settings=settings))

    print(f"PROFILE viewer at n = {state0.n} (thread CPU ms, median of {repeats}), load "
          f"{os.getloadavg()[0]:.2f}:")
    in_place = cpu_ms(lambda k: SlamState.from_bytes(payload, check_symmetry=False))
    # baseline in the same run: msgpack's own decode (it copies the covariance), as before
    copied = cpu_ms(lambda k: SlamState.from_dict(msgpack.unpackb(
        payload, raw=False, strict_map_key=False), check_symmetry=False))
    print(f"  decode a state (SlamState.from_bytes, {len(payload) / 2 ** 20:.1f} MiB): "
          f"{in_place:.1f} ms, its arrays in place; msgpack.unpackb + from_dict {copied:.1f} "
          f"ms (ratio {in_place / copied:.2f})")
    for mode in ("all", "minmeanmax"):
        settings = ViewSettings(mode=mode)
        r = Renderer()
        new = cpu_ms(lambda k, r=r, s=settings: picture(r, states[k], k, s))
        same = cpu_ms(lambda k, r=r, s=settings: picture(r, states[-1], k, s))
        fresh = cpu_ms(lambda k, s=settings: picture(Renderer(), states[-1], k, s))
        print(f"  mode {mode:10s}: new state {new:5.1f} ms; camera frame, same state "
              f"{same:5.1f} ms (scene reused) vs {fresh:5.1f} ms recomputed "
              f"(ratio {fresh / same:.1f}×)")
    # a state drawn onto layers once, put over every camera frame; baseline in the same
    # run: every step drawn straight onto each frame (as before the layers)
    settings = ViewSettings()
    r = Renderer()
    r.scene(states[-1], settings)
    layers = cpu_ms(lambda k: (r.layer_cache.clear(), r.layers(states[-1], camera, settings)))
    over = cpu_ms(lambda k: r.render(frames[k], state=states[-1], camera=camera,
                                     settings=settings))

    def straight(k: int) -> None:
        img = frames[k].copy()
        drawn = r.draw(img, state=states[-1], camera=camera, settings=settings)
        draw_legend(drawn.canvas, health=None, glyphs_shown=drawn.glyphs_shown,
                     notes=rejected_legend(states[-1], settings))

    direct = cpu_ms(straight)
    copy = cpu_ms(lambda k: bytearray(payload))
    print(f"  a state onto its layers (once per state, viewer-layers) {layers:5.1f} ms; a "
          f"camera frame: layers put over it {over:5.2f} ms vs drawn straight {direct:5.1f} "
          f"ms (ratio {direct / over:.0f}×)")
    print(f"  a {len(payload) / 2 ** 20:.1f} MiB payload copied (each state the viewer "
          f"skipped, before subscribe_lazy): {copy:.1f} ms")
    store = SeriesStore(min_interval_s=0.0)
    sample = cpu_ms(lambda k: SeriesStore(min_interval_s=0.0).add_state(states[k], now=0.0))
    old = cpu_ms(lambda k: pd_size_m(all_relative_covariances(states[k].covariance,
                                                              states[k].n)[2]))
    store.add_state(states[0], now=0.0)
    print(f"  plot sample: {sample:.1f} ms (every pair's size, {store.interval_s:.2f} s "
          f"apart at most: ≤ 1/20 of the time) vs before {old:.1f} ms every 0.2 s "
          f"(ratio {old / sample:.1f}×)")
    settings = ViewSettings()
    r = Renderer()
    profiler = cProfile.Profile(time.thread_time)
    profiler.enable()
    for k in range(repeats):
        picture(r, states[k], k, settings)
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    groups = {
        "overview kernel (group_min_mean_max)": "group_min_mean_max",
        "clusters (cluster_labels + tracker)": "cluster_ids",
        "glyphs and cones (_draw_objects)": "_draw_objects",
        "floor layer (outlines, lines, path)": "_draw_floor_layer",
        "legend": "draw_legend",
        "layers put over the frame (Overlay.put_over)": "put_over",
        "JPEG (imencode)": "imencode",
    }
    for name, func in groups.items():
        total = sum(v[3] for (_f, _l, fn), v in stats.items()
                    if fn == func or (fn.startswith("<") and func in fn))
        print(f"  {name:40s} {total / repeats * 1e3:6.1f} ms per new state")


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


def main() -> None:
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
    args = parser.parse_args()
    wanted = set(args.only.split(","))
    unknown = wanted - {"large-alone", "large-full", "paper-full"}
    if unknown:
        parser.error(f"--only: unknown run(s) {', '.join(sorted(unknown))}")
    if args.profile or args.profile_viewer:
        keep_freed_memory()  # the in-process profiles allocate as the services do
    if args.profile:
        profile_estimator()
    if args.profile_viewer:
        profile_viewer()
    if args.profile_only:
        return
    router = spawn("router", "--listen", (endpoint := free_tcp_endpoint()), "-q")
    router.wait_for_line("router ready")
    results: dict[str, list[dict]] = {"large-full": [], "large-alone": [], "paper-full": []}
    try:
        for k in range(args.repeats):
            for name, world, full in (("large-alone", "large", False),
                                      ("large-full", "large", True),
                                      ("paper-full", "paper", True)):
                if name not in wanted:
                    continue
                share = () if args.monitor_share is None else ("--large-share",
                                                               str(args.monitor_share))
                r = run(endpoint, world, full=full, window_s=args.window, seed=k,
                        monitor_args=share, sim_rate=args.sim_rate)
                results[name].append(r)
                print(_line(r), flush=True)
    finally:
        stop(router)

    def med(name: str, key: str) -> float:
        return statistics.median(float(r[key] or 0.0) for r in results[name])

    if wanted != {"large-alone", "large-full", "paper-full"}:
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
          f"in {args.window:.0f} s; paper: checks {med('paper-full', 'monitor_checked_s'):.0f} "
          f"of {paper_est:.0f}, sampled_out {med('paper-full', 'monitor_sampled_out'):.0f}")


if __name__ == "__main__":
    main()
