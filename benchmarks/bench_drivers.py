"""Speed of the robot drivers' cores: simulator, MRCLAM replay, serial parser.

Each figure is the median of several repeats, with a baseline measured in the same run:
the cost of merely constructing the same messages (the floor any driver pays), or numpy's
``loadtxt`` on the same files. Run: ``.venv/bin/python benchmarks/bench_drivers.py``.
"""

from __future__ import annotations

import random
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slamlens.common.messages import Observations, Odometry, Truth
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.serial_link import SerialParser, encode
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import load_world

MRCLAM = Path(__file__).parents[1] / "../shared/data/mrclam6"


def median_s(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def rebuild(events: list) -> None:
    """Construct the same messages again from their fields: the floor of any driver."""
    for e in events:
        if isinstance(e, Odometry):
            Odometry(robot=e.robot, stamp=e.stamp, dt=e.dt, v=e.v, w=e.w)
        elif isinstance(e, Truth):
            Truth(robot=e.robot, stamp=e.stamp, pose=e.pose, landmark_ids=e.landmark_ids,
                  landmarks=e.landmarks)
        else:
            Observations(robot=e.robot, stamp=e.stamp, ids=e.ids, ranges=e.ranges,
                         bearings=e.bearings)


def bench_sim(name: str, repeats: int = 7) -> None:
    world = load_world(name)
    events = list(Simulator(world).events())
    full = median_s(lambda: list(Simulator(world, seed=1).events()), repeats)
    floor = median_s(lambda: rebuild(events), repeats)
    sim = Simulator(world)
    print(f"sim {name:6s}: {len(events)} events, {sim.duration_s:.1f} s simulated; "
          f"generate {full * 1e3:.1f} ms (median of {repeats}); message floor "
          f"{floor * 1e3:.1f} ms; ratio {full / floor:.2f}; "
          f"{sim.duration_s / full:.0f}x real time")


def bench_mrclam(repeats: int = 3) -> None:
    if not (MRCLAM / "Barcodes.dat").is_file():
        print(f"mrclam: data missing at {MRCLAM}")
        return
    load = median_s(lambda: load_mrclam(MRCLAM, robot=1), repeats)
    baseline = median_s(lambda: [np.loadtxt(MRCLAM / f"Robot1_{f}.dat")
                                 for f in ("Odometry", "Measurement", "Groundtruth")], repeats)
    run = load_mrclam(MRCLAM, robot=1)
    events = list(run.events())
    stream = median_s(lambda: sum(1 for _ in run.events()), repeats)
    floor = median_s(lambda: rebuild(events), repeats)
    print(f"mrclam robot1: load {load * 1e3:.0f} ms vs np.loadtxt {baseline * 1e3:.0f} ms "
          f"(ratio {load / baseline:.2f}); {len(events)} events in {stream * 1e3:.0f} ms vs "
          f"message floor {floor * 1e3:.0f} ms (ratio {stream / floor:.2f}); "
          f"{run.duration_s / stream:.0f}x real time")


def bench_serial(repeats: int = 5) -> None:
    rng = random.Random(0)
    messages: list[Odometry | Observations] = []
    for i in range(5000):
        if i % 2:
            messages.append(Odometry(robot="r", stamp=i * 0.01, dt=0.01,
                                     v=rng.uniform(-1, 1), w=rng.uniform(-1, 1)))
        else:
            k = rng.randrange(0, 8)
            messages.append(Observations(
                robot="r", stamp=i * 0.01, ids=[rng.randrange(100) for _ in range(k)],
                ranges=[rng.uniform(0, 5) for _ in range(k)],
                bearings=[rng.uniform(-1.5, 1.5) for _ in range(k)]))
    stream = b"".join(encode(m) for m in messages)
    chunks = [stream[i:i + 256] for i in range(0, len(stream), 256)]

    def parse() -> None:
        parser = SerialParser("r")
        for chunk in chunks:
            parser.feed(chunk)

    parse_s = median_s(parse, repeats)
    floor = median_s(lambda: rebuild(messages), repeats)
    print(f"serial parser: {len(messages)} records, {len(stream) / 1e6:.2f} MB in "
          f"{parse_s * 1e3:.0f} ms = {len(stream) / parse_s / 1e6:.1f} MB/s, "
          f"{len(messages) / parse_s / 1e3:.0f} k records/s (115200 baud is 0.0115 MB/s); "
          f"message floor {floor * 1e3:.0f} ms (ratio {parse_s / floor:.2f})")


if __name__ == "__main__":
    bench_sim("paper")
    bench_sim("grid")
    bench_mrclam()
    bench_serial()
