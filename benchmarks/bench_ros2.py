"""What the ROS 2 bridge costs: export CPU per state at n = 50, import rate at n = 1000.

A real router process and a real ``slamlens ros2`` process for each part.

(a) **Export**, target ≤ 5 ms of the bridge's CPU per state: states of an n = 50 map (all
    pairs: 1225 ellipsoids) are put on the robot's state key at 20 per second; a plain
    Zenoh subscriber on ``/slamlens/R/markers`` counts the MarkerArrays. The bridge's CPU
    (``/proc``, user + system) over each window of 20 states, per state exported; the
    baseline in the same run is the same process idle for as long (its CPU per second ×
    the window). Beside it, in this process, the median CPU of writing one state's
    messages (markers, pose, path of 2000 poses, tf) against the Foxglove scene of the
    same state (``services/recorder/scene.py``, the other 3D exporter).
(b) **Import**, target ≥ 20 states per second, each equal to the ROS message to the last
    bit: ``slamlens_msgs/msg/SlamEstimate`` of an n = 1000 map (32 MB; CDR from rosbags,
    key and attachment as rmw_zenoh writes them), numbered and built before anything is
    timed — put as bytes over TCP, and from shared memory as an rmw_zenoh publisher with
    shared memory on puts them (``--put``). 10 untimed ones first; once the last of them
    came out (the bridge's pool made, pages first touched) 50 at ``--rate`` (25/s). The
    rate: distinct SlamStates out of the bridge from the first timed put to the last
    arrival; the bridge's CPU per estimate (``/proc``) over the same time; the states
    compared with the messages after the run. The baseline in the same run: the same
    payloads relayed through the same router by a bare subscriber that republishes them
    (the transport's own rate).

Run: ``.venv/bin/python benchmarks/bench_ros2.py [--windows 10] [--estimates 50]
[--only export|import] [--put bytes|shm|both] [--rate 25]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import SlamState  # noqa: E402
from slamlens.common.scene3d import SceneSettings  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.common.zenoh_publishing import ShmPool  # noqa: E402
from slamlens.services.recorder.scene import scene_update  # noqa: E402
from slamlens.services.ros2.markers import MarkerExport  # noqa: E402
from slamlens.services.ros2.outputs import PathTrack, pose_with_covariance, transform  # noqa: E402
from slamlens.services.ros2.rostypes import ros_type, typestore  # noqa: E402

KEYS = Keys()
ROBOT = "bench"
ESTIMATE = "slamlens_msgs/msg/SlamEstimate"


def _spawn(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "slamlens.services", *args], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True)


def _wait_line(proc: subprocess.Popen, text: str) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        if text in line:
            return
    raise RuntimeError(f"{proc.args} ended before {text!r}")


def _cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _state(n: int, seq: int, rng: np.random.Generator) -> SlamState:
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    P = A @ A.T * 1e-4 + np.eye(3 + 2 * n) * 1e-3
    return SlamState(robot=ROBOT, seq=seq, stamp=100.0 + 0.05 * seq, step="update",
                     pose=np.array([0.01 * seq, 0.0, 0.1]),
                     landmark_ids=np.arange(6, 6 + n), landmarks=rng.uniform(-3, 3, (n, 2)),
                     covariance=P, epoch=1)


def in_process(samples: int = 30) -> tuple[float, float]:
    """Median CPU (ms) of one state's ROS 2 messages, and of its Foxglove scene."""
    rng = np.random.default_rng(0)
    state = _state(50, 1, rng)
    export, track = MarkerExport(SceneSettings()), PathTrack(2000)
    for k in range(2000):
        track.add(_state(0, k, rng))
    ros, fox = [], []
    for _ in range(samples):
        t = time.process_time()
        export.update(state, path_xy=track.xy())
        pose_with_covariance(state)
        track.path(state.stamp)
        transform(state)
        ros.append(time.process_time() - t)
        t = time.process_time()
        scene_update(state, SceneSettings(), log_time_ns=0, path_xy=track.xy())
        fox.append(time.process_time() - t)
    return 1e3 * statistics.median(ros), 1e3 * statistics.median(fox)


def export(windows: int, per_window: int = 20, rate: float = 20.0) -> dict[str, float]:
    endpoint = free_tcp_endpoint()
    router = _spawn("router", "--listen", endpoint)
    _wait_line(router, "router ready")
    bridge = _spawn("ros2", "--robot", ROBOT, "--connect", endpoint)
    _wait_line(bridge, "ros2 ready")
    bus = open_bus(BusSettings(connect=(endpoint,)))
    stamps: list[int] = []  #: header stamps (ns) of the MarkerArrays received
    cond = threading.Condition()

    def on_markers(sample) -> None:  # noqa: ANN001
        sec, nsec = np.frombuffer(sample.payload.to_bytes()[8:16], "<i4").tolist()
        with cond:
            stamps.append(sec * 10 ** 9 + nsec)
            cond.notify_all()

    bus.session.declare_subscriber(f"0/slamlens/{ROBOT}/markers/**", on_markers)
    pub = bus.publisher(KEYS.state(ROBOT), cache=100)
    assert bus.wait_for_subscriber(KEYS.state(ROBOT), timeout=30)
    rng = np.random.default_rng(1)
    payloads = [_state(50, k, rng).to_bytes() for k in range(1, windows * per_window + 1)]
    try:
        c0, t0 = _cpu(bridge.pid), time.monotonic()
        time.sleep(per_window / rate)
        idle = (_cpu(bridge.pid) - c0) / (time.monotonic() - t0)  # CPU s per s, idle
        per_state: list[float] = []
        seq, exported = 0, 0
        for _ in range(windows):
            c0, t0 = _cpu(bridge.pid), time.monotonic()
            for k in range(per_window):
                seq += 1
                time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
                pub.put(payloads[seq - 1])
            last = int(round((100.0 + 0.05 * seq) * 1e9))
            with cond:  # the window's last state drawn: the window is complete
                if not cond.wait_for(lambda last=last: last in stamps, timeout=30):
                    raise RuntimeError("the bridge stopped exporting")
                drawn, exported = len(stamps) - exported, len(stamps)
            spent = _cpu(bridge.pid) - c0
            per_state.append(1e3 * (spent - idle * (time.monotonic() - t0)) / drawn)
        return {"ms_per_state": statistics.median(per_state), "min": min(per_state),
                "max": max(per_state), "idle_ms_per_s": 1e3 * idle,
                "exported": exported, "put": seq}
    finally:
        bus.close()
        for proc in (bridge, router):
            proc.terminate()
            proc.wait(10)


def _estimate_payload(n: int) -> tuple[bytes, int]:
    """A SlamEstimate of n landmarks as rosbags writes it, and where its seq is."""
    store = typestore("jazzy")
    T = store.types
    rng = np.random.default_rng(2)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    msg = T[ESTIMATE](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
        sec=1_700_000_000, nanosec=0), frame_id="map"), seq=np.uint64(0),
        pose=T["geometry_msgs/msg/Pose2D"](x=0.5, y=0.25, theta=0.1),
        landmark_ids=np.arange(6, 6 + n, dtype=np.int64), landmarks=rng.normal(size=2 * n),
        covariance=(A + A.T).reshape(-1))
    payload = bytes(store.serialize_cdr(msg, ESTIMATE))
    return payload, 4 + 16  # header: stamp 8, "map" 8; seq is the next 8-aligned uint64


WARMUP = 10  #: estimates put before the timed ones


def _numbered(payload: bytes, seq_at: int, count: int) -> list[bytes]:
    """``count`` copies of ``payload`` with seq 0, 1, … (made before anything is timed)."""
    out = []
    for k in range(count):
        data = bytearray(payload)
        data[seq_at:seq_at + 8] = np.uint64(k).tobytes()
        out.append(bytes(data))
    return out


def import_rate(count: int, n: int = 1000, rate: float = 25.0, *, shm: bool = False
                ) -> dict[str, float]:
    """Bridge and bare relay, ``count`` estimates each put at ``rate``; with ``shm`` they
    are put from shared memory (as an rmw_zenoh publisher with shared memory on)."""
    payload, seq_at = _estimate_payload(n)
    size = 3 + 2 * n
    cov = payload[len(payload) - 8 * size * size:]  # the last field: the covariance
    end = len(payload) - 8 * size * size - 8  # before it: a count and 4 bytes of padding
    lms = payload[end - 16 * n:end]
    payloads = _numbered(payload, seq_at, count)
    pool = ShmPool(pool_bytes=(count + 4) * len(payload)) if shm else None
    endpoint = free_tcp_endpoint()
    router = _spawn("router", "--listen", endpoint)
    _wait_line(router, "router ready")
    bridge = _spawn("ros2", "--robot", ROBOT, "--connect", endpoint, "--from-ros", "estimate",
                    "--no-export")
    _wait_line(bridge, "ros2 ready")
    bus = open_bus(BusSettings(connect=(endpoint,)))
    key = (f"0/{ROBOT}/slam/estimate/slamlens_msgs::msg::dds_::SlamEstimate_/"
           f"{ros_type(ESTIMATE, 'jazzy').hash}")

    def state_seq(data: bytes) -> tuple[int, object]:
        state = SlamState.from_bytes(data, check_symmetry=False)
        return state.seq, state

    def same_state(state: SlamState) -> bool:  # afterwards, not while timing
        return (state.covariance.tobytes() == cov and state.landmarks.tobytes() == lms
                and state.landmark_ids.tolist() == list(range(6, 6 + n)))

    def relay_seq(data: bytes) -> tuple[int, object]:
        return int(np.frombuffer(data, np.uint64, 1, seq_at)[0]), data

    try:
        assert bus.wait_for_subscriber(key, timeout=30)
        cpu0: list[float] = []
        bridged = _timed(bus, key, KEYS.state(ROBOT), payloads, rate, state_seq, pool,
                         on_timed=lambda: cpu0.append(_cpu(bridge.pid)))
        cpu_s = _cpu(bridge.pid) - cpu0[0]
        timed = [v for k, v in bridged["kept"].items() if k >= WARMUP]
        bridge_equal, distinct = sum(same_state(x) for x in timed), len(timed)
        del timed
        bridged["kept"].clear()  # 32 MB each: not held through the relay's run
        relay = _Relay(bus, f"0/{ROBOT}/relay/in", f"0/{ROBOT}/relay/out")
        relayed = _timed(bus, f"0/{ROBOT}/relay/in", f"0/{ROBOT}/relay/out", payloads, rate,
                         relay_seq, pool)
        relay.close()
        relay_equal = sum(data == payloads[k] for k, data in relayed["kept"].items()
                          if k >= WARMUP)
        imported = bridged["received"]  # the timed ones the bridge took (not skipped)
        return {"bridge_per_s": bridged["per_s"], "received": bridged["received"],
                "cpu_ms": 1e3 * cpu_s / max(1, imported),
                "bit_equal": bridge_equal, "distinct": distinct,
                "relay_per_s": relayed["per_s"], "relay_received": relayed["received"],
                "relay_equal": relay_equal}
    finally:
        bus.close()
        for proc in (bridge, router):
            proc.terminate()
            out, _ = proc.communicate(timeout=10)
            for line in out.splitlines():
                if "stopped:" in line:
                    print(line[:400])


class _Relay:
    """Republishes every payload of ``src`` on ``dst`` (from a worker, not the callback)."""

    def __init__(self, bus, src: str, dst: str) -> None:  # noqa: ANN001
        self.ch = bus.channel(src)
        self.pub = bus.session.declare_publisher(dst)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.is_set():
            sample = self.ch.recv(timeout=0.2)
            if sample is not None:
                self.pub.put(sample.payload)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)


def _timed(bus, key: str, out_key: str, payloads: list[bytes], rate: float,  # noqa: ANN001
           seq_of, pool: ShmPool | None = None, warmup: int = WARMUP,  # noqa: ANN001
           on_timed=lambda: None) -> dict:  # noqa: ANN001
    """Put ``payloads`` (seq 0, 1, …) on ``key`` (from shared memory with ``pool``, wrapped
    before timing): the first ``warmup`` at ``rate``, then — once the last of them came out
    on ``out_key`` and was taken (pools made, pages first touched) — ``on_timed()`` and the
    others at ``rate``: the rate those came out, arrival times taken in the callback. A
    worker copies each payload out of Zenoh's buffer at once and reads its seq; it ends when
    the last one put has come (the bridge may skip older ones for it, never the newest)."""
    attachment = np.int64(1).tobytes() + np.int64(time.time_ns()).tobytes() + bytes([16]) \
        + bytes(16)
    outs = payloads if pool is None else [pool.wrap(p) for p in payloads]
    arrivals: list[float] = []
    waiting: list = []
    kept: dict[int, object] = {}
    cond = threading.Condition()
    last = len(payloads) - 1

    def on_sample(_key: str, fetch) -> None:  # noqa: ANN001
        with cond:
            waiting.append((time.monotonic(), fetch))
            cond.notify_all()

    def worker() -> None:
        while last not in kept:
            with cond:
                if not cond.wait_for(lambda: waiting, timeout=120):
                    return
                arrived, fetch = waiting.pop(0)
            seq, value = seq_of(fetch())
            with cond:
                kept[seq] = value
                if seq >= warmup:
                    arrivals.append(arrived)
                cond.notify_all()

    def put_at_rate(batch: list) -> float:
        t0 = time.monotonic()
        for k, out in enumerate(batch):
            time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
            bus.session.put(key, out, attachment=attachment)
        return t0

    sub = bus.subscribe_lazy(out_key, on_sample)
    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    put_at_rate(outs[:warmup])
    with cond:  # the newest warm-up one out and taken: nothing of the warm-up in flight
        cond.wait_for(lambda: warmup - 1 in kept and not waiting, timeout=120)
    on_timed()
    timed_from = put_at_rate(outs[warmup:])
    thread.join(300)  # ends on the last payload's arrival (or 120 s without any)
    sub.undeclare()
    # distinct payloads out per second, from the first timed put to the last arrival
    per_s = len(arrivals) / (max(arrivals) - timed_from) if arrivals else 0.0
    return {"per_s": per_s, "received": len(arrivals), "kept": kept}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--windows", type=int, default=10)
    parser.add_argument("--estimates", type=int, default=50,
                        help=f"estimates timed (after {WARMUP} untimed)")
    parser.add_argument("--only", choices=("export", "import"), help="one part only")
    parser.add_argument("--rate", type=float, default=25.0,
                        help="estimates put a second (import)")
    parser.add_argument("--put", choices=("bytes", "shm", "both"), default="both",
                        help="how the estimates are put: as bytes over TCP, from shared "
                             "memory, or both in turn")
    args = parser.parse_args()
    if args.only != "import":
        ros_ms, fox_ms = in_process()
        print(f"in process, one state (n = 50, all pairs, 2000-pose path): ROS 2 messages "
              f"{ros_ms:.2f} ms CPU, Foxglove scene {fox_ms:.2f} ms CPU (medians)")
        e = export(args.windows)
        print(f"(a) export at 20 states/s, n = 50 all pairs: bridge {e['ms_per_state']:.2f} ms "
              f"CPU per state (median of {args.windows} windows of 20; "
              f"{e['min']:.2f}–{e['max']:.2f}), idle baseline {e['idle_ms_per_s']:.2f} ms/s "
              f"subtracted; {e['exported']} of {e['put']} states drawn (the rest skipped for "
              "newer ones); target ≤ 5 ms")
    if args.only != "export":
        for shm, how in ((False, "as bytes (TCP)"), (True, "in shared memory")):
            if args.put != "both" and shm != (args.put == "shm"):
                continue
            r = import_rate(args.estimates + WARMUP, rate=args.rate, shm=shm)
            print(f"(b) import n = 1000 SlamEstimate put at {args.rate:g}/s {how}: "
                  f"{r['bridge_per_s']:.1f} states/s out of the bridge, {r['received']} of "
                  f"{args.estimates} put, bridge CPU {r['cpu_ms']:.1f} ms per estimate, "
                  f"{r['bit_equal']} bit-equal to the message "
                  f"({r['distinct']} distinct seqs); the same payloads relayed bare through "
                  f"the router: {r['relay_per_s']:.1f}/s ({r['relay_received']} received, "
                  f"{r['relay_equal']} equal); target ≥ 20/s", flush=True)
    print(f"load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
