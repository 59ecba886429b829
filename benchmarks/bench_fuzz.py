"""≥ 100 000 malformed payloads on every key a service subscribes to.

For each service (a real process behind a real router on loopback) and each key it
subscribes to, this sends ``--count`` payloads from services/harness/fuzz.py (random bytes, wrong
types, dtype as a list or an unknown string, 70-dimensional or huge shapes, NaN/∞,
truncated msgpack …), paced so that none is lost in transit, then one correct message,
and reports: payloads per second taken, rejections counted against sent, whether the
correct message still produced correct output, and the exit status on SIGTERM. The viewer
(state, health, tracked pose, registration, frames) keeps only the newest of most inputs,
so it counts what it looked at: at most what it was sent.

Run: ``.venv/bin/python benchmarks/bench_fuzz.py [--count 100000]
[--only estimator,monitor,viewer]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import Health, Observations, Odometry, SlamState, Truth  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus  # noqa: E402
from slamlens.services.harness.fuzz import bad_payloads, valid  # noqa: E402
from slamlens.services.harness.procs import spawn, stop  # noqa: E402

KEYS = Keys()
ROBOT = "robot1"


def _final(out: str, name: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: ")][-1]
    return json.loads(line.split(": ", 1)[1])


def _send(bus, key: str, kind, count: int, seed: int) -> tuple[int, float]:
    """Send ``count`` bad payloads, none lost in transit (this publisher blocks under
    congestion; slamlens' own never do): what is measured is the service, not the link."""
    import zenoh

    pub = bus.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    while not pub.matching_status:  # a new publisher may drop its puts before it matches
        time.sleep(0.01)
    started = time.monotonic()
    n = 0
    for payload in bad_payloads(kind, np.random.default_rng(seed), count):
        pub.put(payload)
        n += 1
    pub.undeclare()
    return n, time.monotonic() - started


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def fuzz_estimator(ep: str, count: int) -> None:
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    bus = open_bus(BusSettings(connect=(ep,)))
    got: list[SlamState] = []
    bus.subscribe(KEYS.state(ROBOT), lambda k, p: got.append(SlamState.from_bytes(p)))
    bus.wait_for_subscriber(KEYS.odometry(ROBOT))
    try:
        for key, kind, seed in ((KEYS.odometry(ROBOT), Odometry, 1),
                                (KEYS.observations(ROBOT), Observations, 2)):
            n, took = _send(bus, key, kind, count, seed)
            print(f"estimator {key.rsplit('/', 1)[1]}: {n} payloads sent in {took:.1f} s "
                  f"({n / took:.0f}/s)")
        bus.publisher(KEYS.odometry(ROBOT)).put(valid(Odometry, robot=ROBOT).to_bytes())
        correct = _wait(lambda: any(s.step == "predict" for s in got), 120)
    finally:
        out, err = stop(est, timeout=30)
        bus.close()
    s = _final(out, "estimator")
    print(f"estimator: rejected {s['dropped']} of {2 * count}, correct state afterwards "
          f"{correct}, exit {est.returncode}, tracebacks {err.count('Traceback')}")


def fuzz_monitor(ep: str, count: int) -> None:
    mon = spawn("monitor", "--robot", ROBOT, "--connect", ep)
    mon.wait_for_line("monitor ready")
    bus = open_bus(BusSettings(connect=(ep,)))
    got: list[Health] = []
    bus.subscribe(KEYS.health(ROBOT), lambda k, p: got.append(Health.from_bytes(p)))
    bus.wait_for_subscriber(KEYS.state(ROBOT))
    try:
        for key, kind, seed in ((KEYS.state(ROBOT), SlamState, 3),
                                (KEYS.truth(ROBOT), Truth, 4),
                                (KEYS.tracked_by("overhead", ROBOT), Truth, 5)):
            n, took = _send(bus, key, kind, count, seed)
            print(f"monitor {key.rsplit('/', 1)[1]}: {n} payloads sent in {took:.1f} s "
                  f"({n / took:.0f}/s)")
        bus.publisher(KEYS.state(ROBOT)).put(valid(SlamState, robot=ROBOT).to_bytes())
        correct = _wait(lambda: any(h.seq == 1 and h.ok for h in got), 120)
    finally:
        out, err = stop(mon, timeout=30)
        bus.close()
    s = _final(out, "monitor")
    print(f"monitor: rejected {s['dropped']} of {3 * count}, correct health afterwards "
          f"{correct}, exit {mon.returncode}, tracebacks {err.count('Traceback')}")


def fuzz_viewer(ep: str, count: int) -> None:
    """The viewer keeps the newest state, frame, registration and tracked pose (latest
    wins) and a bounded FIFO of health: a payload replaced before the viewer looked at it
    is not decoded, so it counts at most what it was sent (the suite's test sends one at a
    time and checks exact counts)."""
    import tempfile
    import urllib.request

    import cv2

    from slamlens.common.messages import CameraFrame, Registration

    camera = "cam1"
    with tempfile.TemporaryDirectory() as recordings:
        viewer = spawn("viewer", "--robot", ROBOT, "--camera", camera, "--connect", ep,
                       "--http", "127.0.0.1:0", "--late-join-timeout-s", "0",
                       "--recordings-dir", recordings)
        url = viewer.wait_for_line("viewer ready").split()[-1]

        def status() -> dict:
            with urllib.request.urlopen(url + "/api/status", timeout=10) as response:
                return json.loads(response.read())

        bus = open_bus(BusSettings(connect=(ep,)))
        sent: dict[str, int] = {}
        try:
            for key, kind, seed, name in (
                    (KEYS.state(ROBOT), SlamState, 10, "state"),
                    (KEYS.health(ROBOT), Health, 11, "health"),
                    (KEYS.tracked_by("overhead", ROBOT), Truth, 12, "tracked"),
                    (KEYS.registration(camera, ROBOT), Registration, 13,
                     f"registration {camera}"),
                    (KEYS.frame(camera), CameraFrame, 14, f"frame {camera}")):
                n, took = _send(bus, key, kind, count, seed)
                sent[name] = n
                print(f"viewer {name}: {n} payloads sent in {took:.1f} s ({n / took:.0f}/s)")
            pubs = {k: bus.publisher(k) for k in (KEYS.registration(camera, ROBOT),
                                                  KEYS.frame(camera), KEYS.state(ROBOT))}
            for pub in pubs.values():
                pub.wait_matched()  # type: ignore[attr-defined]
            jpeg = cv2.imencode(".jpg", np.full((480, 640, 3), 90, np.uint8))[1].tobytes()
            good = [valid(Registration, robot=ROBOT, camera=camera).to_bytes(),
                    CameraFrame(camera=camera, seq=1, stamp=1.0, encoding="jpeg", width=640,
                                height=480, data=jpeg).to_bytes(),
                    valid(SlamState, robot=ROBOT, seq=41).to_bytes()]

            def drawn() -> bool:
                for pub, payload in zip(pubs.values(), good, strict=True):
                    pub.put(payload)  # (again until seen: a new route may drop a while)
                now = status()
                return ((now["state"] or {}).get("seq") == 41
                        and now["cameras"][0]["registration"] is not None)

            correct = _wait(drawn, 120)
            with urllib.request.urlopen(url + "/snapshot.png", timeout=30) as response:
                correct = correct and response.headers["X-State-Seq"] == "41"
            counted = status()["bad_messages"]
        finally:
            out, err = stop(viewer, timeout=30)
            bus.close()
    for name, n in sent.items():
        print(f"viewer {name}: counted {counted.get(name, 0)} of {n} sent (latest wins)")
    print(f"viewer: correct picture afterwards {correct}, exit {viewer.returncode}, "
          f"tracebacks {err.count('Traceback')}, log lines {len(err.splitlines())}")


SERVICES = {"estimator": fuzz_estimator, "monitor": fuzz_monitor, "viewer": fuzz_viewer}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=100_000, help="payloads per key")
    ap.add_argument("--only", default=",".join(SERVICES))
    args = ap.parse_args()
    ep = free_tcp_endpoint()
    router = spawn("router", "--listen", ep)
    router.wait_for_line("router ready")
    try:
        for name in args.only.split(","):
            SERVICES[name](ep, args.count)
    finally:
        stop(router)


if __name__ == "__main__":
    main()
