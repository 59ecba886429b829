"""A remote viewer behind a 20 Mbit/s link: full state vs. the summary stream.

Two network namespaces (``services/harness/netns.py``: a robot and a workstation joined by a
veth pair)
with a token bucket on the link, both ways: ``tc qdisc … tbf rate 20mbit burst 32kbit
latency 400ms``. The robot runs its router (linked to the workstation's), a publisher of an
n = 1000 map state (3 + 2·1000 = 2003 rows: a 32 MB ``SlamState``; synthetic, three spatial
clusters, a PSD EKF-like covariance) at ``--rate`` states/s through the estimator's kind of
publisher (advanced, cache, congestion control drop), and ``slamlens summary``. Each state's
``stamp`` is the robot's wall clock at publication (the namespaces share the clock).

On the workstation, one phase after the other (the link carries one at a time):

(a) **full state**: a subscriber of ``robot/R/state`` that keeps the newest, as the
    viewer's intake does (the baseline): states/s received, and latency behind the robot
    (receipt − stamp);
(b) **summary**: a :class:`~slamlens.common.summary_pull.SummaryPuller` pulling the clustered
    min/mean/max summary (``what=clusters``, float32) — the viewer's ``--source summary``
    intake — decoding each answer: states/s and latency behind the robot;
(c) optional (``--viewer``): ``slamlens viewer --source summary`` itself, its state seq
    and age read from ``/api/status`` once a second.

Target: the clustered picture of an n = 1000 map at ≥ 2 states/s, ≤ 1 s behind.
Prints medians and the ratio summary/full. Needs root (namespaces, tc).

Run: ``.venv/bin/python benchmarks/bench_remote.py [--seconds 40] [--rate 20] [--viewer]``
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

ROBOT = "bench"
PORT = 7447


def synthetic_state(n: int, *, seed: int = 0):
    """n features in three clusters of an arena, EKF-like: P_mm = a common (robot-induced)
    part + a small anisotropic block per feature (PSD by construction)."""
    import numpy as np

    from slamlens.common.messages import SlamState

    rng = np.random.default_rng(seed)
    centres = np.array([[-0.8, 0.8], [0.9, 0.9], [0.1, -0.9]])
    xy = np.concatenate([c + rng.normal(0, 0.2, (n // 3 + 1, 2)) for c in centres])[:n]
    N = 3 + 2 * n
    P = np.zeros((N, N))
    P[:3, :3] = np.diag([0.01, 0.01, 0.003])
    P[3:, 3:] = np.kron(np.ones((n, n)), 0.03 ** 2 * np.eye(2))
    for i in range(n):
        a = rng.uniform(0.01, 0.04)
        b = rng.uniform(0.004, a)
        t = rng.uniform(0, np.pi)
        R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        P[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] += R @ np.diag([a * a, b * b]) @ R.T
    return SlamState(robot=ROBOT, seq=1, stamp=time.time(), step="update",
                     pose=[0.2, 0.1, 0.5], landmark_ids=np.arange(n), landmarks=xy,
                     covariance=P, epoch=1)


# ------------------------------------------------------------------------------ roles
def role_publish(args: argparse.Namespace) -> None:
    """Robot side: publish the state at ``--rate`` with a fresh seq and stamp each time."""
    import msgpack

    from slamlens.common.keys import Keys
    from slamlens.common.session import BusSettings, open_bus

    bus = open_bus(BusSettings(connect=(f"tcp/127.0.0.1:{args.port}",)))
    if args.no_shm:
        bus.shm.min_bytes = 1 << 62  # every payload as plain bytes
    pub = bus.publisher(Keys().state(ROBOT), cache=4, cache_bytes=256 << 20)
    latest: list[bytes] = []
    bus.serve_latest(Keys().state(ROBOT), lambda: latest[-1] if latest else None)
    raw = synthetic_state(args.n).to_dict()
    raw["epoch"] = time.time_ns()  # a new map per run, as the estimator's epoch
    print(json.dumps({"publisher": "ready", "bytes": len(msgpack.packb(raw))}), flush=True)
    seq, period, t_next = 0, 1.0 / args.rate, time.monotonic()
    end = time.monotonic() + args.seconds
    while time.monotonic() < end:
        seq += 1
        raw["seq"], raw["stamp"] = seq, time.time()
        payload = msgpack.packb(raw, use_bin_type=True)
        latest[:] = [payload]  # the estimator's `state` queryable: the latest state
        pub.put(payload)
        t_next += period
        time.sleep(max(0.0, t_next - time.monotonic()))
    print(json.dumps({"published": seq}), flush=True)
    bus.close()


def role_full(args: argparse.Namespace) -> None:
    """Workstation: the newest full state, as the viewer's intake keeps it."""
    from slamlens.common.keys import Keys
    from slamlens.common.latest import Latest
    from slamlens.common.messages import SlamState, peek_fields
    from slamlens.common.session import BusSettings, open_bus

    bus = open_bus(BusSettings(connect=(f"tcp/127.0.0.1:{args.port}",)))
    slot: Latest[tuple[bytes, float]] = Latest()
    bus.subscribe(Keys().state(ROBOT), lambda _k, p: slot.put((p, time.time())))
    print(json.dumps({"full": "ready"}), flush=True)
    end = time.monotonic() + args.seconds
    while time.monotonic() < end:
        item = slot.take(timeout=0.5)
        if item is None:
            continue
        payload, received = item
        head = peek_fields(payload, ("seq", "stamp"))
        SlamState.from_bytes(payload, check_symmetry=False)  # what a viewer must do
        print(json.dumps({"seq": head["seq"], "latency_s": received - head["stamp"],
                          "at": received, "bytes": len(payload)}), flush=True)
    bus.close()


def role_fullpull(args: argparse.Namespace) -> None:
    """Workstation: the full state by ``get`` on ``state`` (docs/protocol.md's queryable), one
    query in flight — the full-state counterpart of the summary pull."""
    from slamlens.common.keys import Keys
    from slamlens.common.messages import SlamState, peek_fields
    from slamlens.common.session import BusSettings, open_bus

    bus = open_bus(BusSettings(connect=(f"tcp/127.0.0.1:{args.port}",)))
    print(json.dumps({"fullpull": "ready"}), flush=True)
    end = time.monotonic() + args.seconds
    last = None
    while time.monotonic() < end:
        replies = bus.get(Keys().state(ROBOT), timeout=max(1.0, end - time.monotonic()))
        if not replies:
            time.sleep(0.2)
            continue
        payload, received = replies[-1].payload, time.time()
        head = peek_fields(payload, ("seq", "stamp"))
        if head["seq"] == last:
            continue
        last = head["seq"]
        SlamState.from_bytes(payload, check_symmetry=False)
        print(json.dumps({"seq": head["seq"], "latency_s": received - head["stamp"],
                          "at": received, "bytes": len(payload)}), flush=True)
    bus.close()


PROBE_MB = (0.5, 1.0, 2.0, 4.0, 8.0)  #: put sizes of the probe
PROBE_REPLY_MB = (8.0, 20.0)  #: reply sizes of the probe


def role_probe_put(args: argparse.Namespace) -> None:
    """Robot side of the probe: plain puts of growing size, congestion control drop or
    block, then queryables answering large replies."""
    import zenoh

    from slamlens.common.session import BusSettings, open_bus

    bus = open_bus(BusSettings(connect=(f"tcp/127.0.0.1:{args.port}",)))
    for size in PROBE_REPLY_MB:
        data = b"r" * int(size * 1e6)
        bus.session.declare_queryable(f"probe/reply/{size:g}",
                                      lambda q, d=data: (q.reply(q.key_expr, d), q.drop()))
    print(json.dumps({"probe": "ready"}), flush=True)
    time.sleep(2.0)
    for cc in ("DROP", "BLOCK"):
        pub = bus.session.declare_publisher(
            f"probe/put/{cc.lower()}", congestion_control=getattr(zenoh.CongestionControl, cc))
        for size in PROBE_MB:
            pub.put(b"p" * int(size * 1e6))
            time.sleep(size * 8e6 / _rate_bits(args.link) + 2.0)  # its link time, and 2 s
    time.sleep(60.0)  # serve the replies
    bus.close()


def role_probe_get(args: argparse.Namespace) -> None:
    """Workstation side of the probe: what arrives of the puts, then each reply."""
    from slamlens.common.session import BusSettings, open_bus

    bus = open_bus(BusSettings(connect=(f"tcp/127.0.0.1:{args.port}",)))
    bus.subscribe("probe/put/*", lambda k, p: print(json.dumps(
        {"put": k.rsplit("/", 1)[1], "mb": len(p) / 1e6}), flush=True))
    print(json.dumps({"probe": "ready"}), flush=True)
    total = sum(size * 8e6 / _rate_bits(args.link) + 2.0 for size in PROBE_MB) * 2 + 4
    time.sleep(total)
    for size in PROBE_REPLY_MB:
        t0 = time.monotonic()
        replies = bus.get(f"probe/reply/{size:g}", timeout=30.0)
        print(json.dumps({"reply_mb": size, "got": [len(r.payload) / 1e6 for r in replies],
                          "s": time.monotonic() - t0}), flush=True)
    bus.close()


def role_summary(args: argparse.Namespace) -> None:
    """Workstation: pull the clustered summary, one query in flight."""
    from slamlens.common.keys import Keys
    from slamlens.common.messages import StateSummary
    from slamlens.common.session import BusSettings, open_bus
    from slamlens.common.summary import SummaryQuery
    from slamlens.common.summary_pull import SummaryPuller

    bus = open_bus(BusSettings(connect=(f"tcp/127.0.0.1:{args.port}",)))

    def on_summary(payload: bytes, _received: float) -> None:
        now = time.time()
        s = StateSummary.from_bytes(payload)
        print(json.dumps({"seq": s.seq, "latency_s": now - s.stamp, "at": now,
                          "bytes": len(payload), "compute_s": s.compute_s,
                          "groups": 0 if s.group_pairs is None else len(s.group_pairs)}),
              flush=True)

    puller = SummaryPuller(bus, Keys().summary(ROBOT),
                           SummaryQuery(what="clusters", budget=args.budget), on_summary)
    print(json.dumps({"summary": "ready"}), flush=True)
    end = time.monotonic() + args.seconds
    while time.monotonic() < end:
        if puller.pull_once() is None:
            time.sleep(0.2)
    print(json.dumps({"errors": puller.errors, "silent": puller.silent}), flush=True)
    bus.close()


# ------------------------------------------------------------------------ orchestration
WORKSTATION_NS: set[str] = set()  #: namespaces given a private /dev/shm (see _in_ns)


def _in_ns(ns: str, argv: list[str]) -> list[str]:
    """``argv`` run in network namespace ``ns``; the workstation's processes also get an
    empty /dev/shm of their own (``harness.netns.own_shm``: otherwise Zenoh hands the robot's
    shared-memory buffers over by reference and 32 MB never cross the shaped link)."""
    from slamlens.services.harness.netns import own_shm

    return ["ip", "netns", "exec", ns, *(own_shm(argv) if ns in WORKSTATION_NS else argv)]


def _spawn(ns: str, *argv: str) -> subprocess.Popen[str]:
    return subprocess.Popen(_in_ns(ns, list(argv)), cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env={"PYTHONUNBUFFERED": "1", "PATH": "/usr/bin:/bin",
                                 "OPENBLAS_NUM_THREADS": "1"})


def _netns_python(ns: str, *argv: str) -> subprocess.Popen[str]:
    return _spawn(ns, sys.executable, *argv)


def _wait_line(proc: subprocess.Popen[str], text: str, timeout: float = 60.0) -> str:
    box: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if text in line:
                box.append(line)
                return

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout)
    if not box:
        proc.kill()
        raise RuntimeError(f"{proc.args} never printed {text!r}: "
                           f"{proc.stderr.read() if proc.stderr else ''}")
    return box[0]


def _records(proc: subprocess.Popen[str], timeout: float) -> list[dict]:
    out, err = proc.communicate(timeout=timeout)
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    if proc.returncode:
        raise RuntimeError(f"{proc.args} failed: {err[-2000:]}")
    for r in rows:
        if "errors" in r:  # the puller's own counts
            print(f"     (the puller: {r['errors']} error replies, {r['silent']} queries "
                  "unanswered within its timeout)")
    return [r for r in rows if "seq" in r]


def _stats(rows: list[dict], warmup_s: float) -> dict[str, float]:
    if not rows:
        return {"states": 0, "rate": 0.0, "latency_median_s": float("inf"),
                "latency_max_s": float("inf"), "bytes": 0}
    t0 = rows[0]["at"] + warmup_s
    kept = [r for r in rows if r["at"] >= t0] or rows[-1:]
    span = kept[-1]["at"] - kept[0]["at"]
    rate = (len(kept) - 1) / span if span > 0 else 0.0
    return {"states": len(kept), "rate": rate,
            "latency_median_s": statistics.median(r["latency_s"] for r in kept),
            "latency_max_s": max(r["latency_s"] for r in kept),
            "bytes": statistics.median(r["bytes"] for r in kept)}


def _phase(h, role: str, args: argparse.Namespace, rate: float) -> list[dict]:
    me = str(Path(__file__).resolve())
    common = ["--n", str(args.n), "--seconds", str(args.seconds), "--rate", str(rate),
              "--budget", str(args.budget), *(["--no-shm"] if args.no_shm else [])]
    consumer = _netns_python(h.workstation, me, "--role", role, *common)
    _wait_line(consumer, "ready")
    publisher = _netns_python(h.robot, me, "--role", "publish", *common)
    _wait_line(publisher, "ready", timeout=120.0)
    rows = _records(consumer, timeout=args.seconds + 120)
    publisher.communicate(timeout=args.seconds + 60)
    return rows


def _viewer_phase(h, args: argparse.Namespace) -> list[dict]:
    """(c): the viewer itself in summary mode, its state read from /api/status."""
    from slamlens.services.harness.netns import curl_json

    me = str(Path(__file__).resolve())
    viewer = _netns_python(h.workstation, "-m", "slamlens.services", "viewer", "--robot", ROBOT,
                           "--source", "summary", "--http", "127.0.0.1:8080", "--connect",
                           f"tcp/127.0.0.1:{PORT}")
    try:
        _wait_line(viewer, "viewer ready", timeout=120.0)
        publisher = _netns_python(h.robot, me, "--role", "publish", "--n", str(args.n),
                                  "--seconds", str(args.seconds), "--rate", str(args.rate))
        _wait_line(publisher, "ready", timeout=120.0)
        rows = []
        end = time.monotonic() + args.seconds - 2
        while time.monotonic() < end:
            status = curl_json(h.workstation, "http://127.0.0.1:8080/api/status", 2.0)
            now = time.time()
            state = (status or {}).get("state") or {}
            if state.get("seq") is not None:  # the robot's stamps are its wall clock
                rows.append({"seq": state["seq"], "behind_s": now - state["stamp"],
                             "rate": state.get("rate_hz"), "at": now})
            time.sleep(0.5)
        shot = subprocess.run(["ip", "netns", "exec", h.workstation, "curl", "-s", "-D", "-",
                               "-o", "/dev/null", "http://127.0.0.1:8080/snapshot.png"],
                              capture_output=True, text=True, timeout=30).stdout
        rows.append({"snapshot": [ln.strip() for ln in shot.splitlines()
                                  if ln.lower().startswith(("http/", "x-state-seq"))]})
        publisher.communicate(timeout=args.seconds + 60)
        return rows
    finally:
        viewer.terminate()
        viewer.communicate(timeout=10)


def _probe(h, args: argparse.Namespace, robot_router: subprocess.Popen[str]) -> None:
    """What of a large plain Zenoh message crosses the link: puts with congestion control
    drop and block, and replies (which Zenoh sends with block)."""
    me = str(Path(__file__).resolve())
    link = ["--link", args.link]
    far = _netns_python(h.workstation, me, "--role", "probe_get", *link)
    _wait_line(far, "ready")
    near = _netns_python(h.robot, me, "--role", "probe_put", *link)
    _wait_line(near, "ready")
    out, _ = far.communicate(timeout=600)
    near.kill()
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    for cc in ("drop", "block"):
        got = [r["mb"] for r in rows if r.get("put") == cc]
        print(f"put, congestion control {cc}: of {list(PROBE_MB)} MB, arrived {got}")
    for r in rows:
        if "reply_mb" in r:
            print(f"get of a {r['reply_mb']:g} MB reply: {r['got'] or 'nothing'} after "
                  f"{r['s']:.1f} s")
    robot_router.send_signal(signal.SIGINT)
    log, err = robot_router.communicate(timeout=10)
    closed = [ln for ln in (log + err).splitlines() if "Closing transport" in ln]
    print("robot router:", closed[0].strip() if closed else "no transport closed")


def _rate_bits(rate: str) -> float:
    """A tc rate ("20mbit", "5mbit", "800kbit") in bits per second."""
    units = {"kbit": 1e3, "mbit": 1e6, "gbit": 1e9}
    for unit, scale in units.items():
        if rate.endswith(unit):
            return float(rate[:-len(unit)]) * scale
    return float(rate)


def _phases(h, args: argparse.Namespace) -> None:
    """Phases (a1) full state subscribed, (a2) full state pulled, (b) the summary pulled,
    each printed, then the ratio, the target and the link's floor."""
    warm = min(5.0, args.seconds / 4)
    full_rate = args.full_rate or args.rate

    def line(label: str, r: dict[str, float], unit: float, unit_name: str) -> str:
        return (f"{label}: {r['states']} states, {r['rate']:.2f} states/s, latency "
                f"median {r['latency_median_s']:.2f} s (max {r['latency_max_s']:.2f} s), "
                f"{r['bytes'] / unit:.1f} {unit_name} each")

    sub = _stats(_phase(h, "full", args, full_rate), warm)
    print(line(f"(a1) full state, subscribed ({full_rate:g}/s published)", sub, 1e6,
               "MB"), flush=True)
    pull = _stats(_phase(h, "fullpull", args, full_rate), warm)
    print(line(f"(a2) full state, get on `state` ({full_rate:g}/s published)", pull,
               1e6, "MB"), flush=True)
    summ = _stats(_phase(h, "summary", args, args.rate), warm)
    print(line(f"(b)  summary pull, clusters ({args.rate:g}/s published)", summ, 1e3,
               "kB"), flush=True)
    base = max(sub, pull, key=lambda r: r["rate"])
    if base["rate"] > 0:
        print(f"ratio summary / best full-state path: {summ['rate'] / base['rate']:.1f}x "
              f"states/s, {base['latency_median_s'] / summ['latency_median_s']:.1f}x "
              "less behind")
    else:
        print("ratio summary / full state: no full state arrived in the phase")
    ok = summ["rate"] >= 2.0 and summ["latency_median_s"] <= 1.0
    print(f"target (>= 2 states/s, <= 1 s behind): {'met' if ok else 'NOT met'}")
    floor = full_bytes = 0.0
    if args.n:
        full_bytes = float(len(synthetic_state(args.n).to_bytes()))
        floor = full_bytes * 8 / _rate_bits(args.link)
        print(f"link floor for the full state: {full_bytes / 1e6:.1f} MB takes "
              f"{floor:.1f} s of a {args.link} link: at best {1 / floor:.3f} states/s, "
              f">= {floor:.1f} s behind; summary / floor: {summ['rate'] * floor:.0f}x "
              "states/s")


def _viewer_report(h, args: argparse.Namespace) -> None:
    """Phase (c): the viewer with --source summary on the workstation, printed."""
    rows = _viewer_phase(h, args)
    shot = rows.pop()["snapshot"] if rows and "snapshot" in rows[-1] else []
    seqs = sorted({r["seq"] for r in rows})
    behind = [r["behind_s"] for r in rows]
    rates = [r["rate"] for r in rows if r["rate"]]
    print(f"(c)  viewer --source summary: {len(seqs)} distinct states in "
          f"{len(rows)} polls of /api/status, its state rate median "
          f"{statistics.median(rates) if rates else 0:.2f}/s, picture behind the "
          f"robot median {statistics.median(behind) if behind else float('nan'):.2f} "
          f"s (max {max(behind) if behind else float('nan'):.2f} s); snapshot: "
          f"{' '.join(shot)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", default="main",
                        choices=("main", "publish", "full", "fullpull", "summary",
                                 "probe_put", "probe_get"))
    parser.add_argument("--n", type=int, default=1000, help="features in the map")
    parser.add_argument("--port", type=int, default=PORT, help="roles: the local router's port")
    parser.add_argument("--seconds", type=float, default=40.0, help="length of each phase")
    parser.add_argument("--rate", type=float, default=20.0, help="states/s published")
    parser.add_argument("--budget", type=int, default=2000, help="summary glyph budget")
    parser.add_argument("--link", default="20mbit", help="tbf rate of the link")
    parser.add_argument("--full-rate", type=float, default=0.0,
                        help="states/s published in phase (a) (0: --rate)")
    parser.add_argument("--no-shm", action="store_true",
                        help="the publisher puts plain bytes, never shared memory")
    parser.add_argument("--probe", action="store_true",
                        help="only probe the link: plain Zenoh puts (drop / block) and "
                             "replies of growing size")
    parser.add_argument("--viewer", action="store_true",
                        help="also run the viewer with --source summary (phase c)")
    args = parser.parse_args()
    if args.role != "main":
        {"publish": role_publish, "full": role_full, "fullpull": role_fullpull,
         "summary": role_summary, "probe_put": role_probe_put,
         "probe_get": role_probe_get}[args.role](args)
        return

    from slamlens.services.harness.netns import available, make_hosts

    why = available()
    if why is not None:
        sys.exit(f"bench_remote needs network namespaces: {why}")
    h = make_hosts()
    procs: list[subprocess.Popen[str]] = []
    try:
        h.shape(args.link, burst="32kbit", latency="400ms")
        WORKSTATION_NS.add(h.workstation)
        ws_router = _netns_python(h.workstation, "-m", "slamlens.services", "router", "--listen",
                                  f"tcp/{h.workstation_ip}:{PORT}", "--listen",
                                  f"tcp/127.0.0.1:{PORT}")
        procs.append(ws_router)
        _wait_line(ws_router, "router ready")
        robot_router = _netns_python(h.robot, "-m", "slamlens.services", "router", "--listen",
                                     f"tcp/127.0.0.1:{PORT}", "--connect",
                                     f"tcp/{h.workstation_ip}:{PORT}")
        procs.append(robot_router)
        _wait_line(robot_router, "router ready")
        if args.probe:
            _probe(h, args, robot_router)
            return
        summary = _netns_python(h.robot, "-m", "slamlens.services", "summary", "--robot", ROBOT,
                                "--connect", f"tcp/127.0.0.1:{PORT}")
        procs.append(summary)
        _wait_line(summary, "summary ready")
        print(f"n = {args.n} ({3 + 2 * args.n}² covariance), {args.rate:g} states/s "
              f"published, link {args.link} tbf both ways, {args.seconds:g} s per phase")
        _phases(h, args)
        if args.viewer:
            _viewer_report(h, args)
        summary.send_signal(signal.SIGINT)
        out, _ = summary.communicate(timeout=10)
        print("robot side:", *[ln for ln in out.splitlines() if "summary stopped" in ln])
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.communicate(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
        h.remove()


if __name__ == "__main__":
    main()
