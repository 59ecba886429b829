"""Recording targets, real processes over Zenoh on loopback.

1. **Recording costs the estimator nothing measurable.** The paper run (``slamlens sim
   --rate 0``, paced on the estimator) with the synthetic overhead camera publishing JPEG
   frames (``slamlens registration --source synthetic``), with and without ``slamlens
   record`` recording everything (frames, states, health, the Foxglove channels).
   Alternating runs; the estimator's time is the sim's wall time (it stays a window ahead
   of the estimator). Target: median with ≤ 1.05× median without.
2. **The recorder keeps up at ≥ 100× real time without frames.** Every bus sample of a
   recorded paper run (no camera) written again through the recorder's own write path
   (``Recorder.write``: the MCAP writer, the Foxglove scene at the default 10 Hz), in one
   process, timed: robot seconds per wall second. Baseline in the same run: the same with
   ``--no-foxglove`` (the raw channels only). Also the live recorder's lag (log time −
   publish time of the states) in the runs of 1.
3. **Playing a whole MRCLAM robot run at --rate 0 drives the estimator at full speed.**
   ``slamlens replay ../shared/data/mrclam6 --rate 0`` into a fresh estimator (the
   baseline) against ``slamlens play RUN.mcap --inputs-only --rate 0`` of the same run,
   recorded once, into a fresh estimator; alternating. Target: play ≤ 1.05× replay.

Run: ``.venv/bin/python benchmarks/bench_recording.py [--repeats 5] [--only 1,2,3]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mcap.reader import make_reader  # noqa: E402

from slamlens.common.bus import Sample  # noqa: E402
from slamlens.common.inprocess_bus import InProcessBus  # noqa: E402
from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import peek_fields  # noqa: E402
from slamlens.common.session import free_tcp_endpoint  # noqa: E402
from slamlens.services.harness.procs import Service, spawn, stop  # noqa: E402
from slamlens.services.recorder.record import Recorder  # noqa: E402
from slamlens.services.recorder.settings import RecordSettings  # noqa: E402

KEYS = Keys()
ROBOT = "robot1"
CAMERA = "overhead"
MRCLAM = REPO.parent / "shared" / "data" / "mrclam6"


def _router() -> tuple[Service, str]:
    ep = free_tcp_endpoint()
    proc = spawn("router", "--listen", ep)
    proc.wait_for_line("router ready")
    return proc, ep


def _wall(out: str, name: str) -> float:
    line = next(ln for ln in out.splitlines() if ln.startswith(f"{name} done: "))
    return float(line.rsplit(" in ", 1)[1].split(" s")[0])


def paper_run(*, record: Path | None, camera: bool) -> dict:
    router, ep = _router()
    procs: list[Service] = []
    try:
        est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
        est.wait_for_line("estimator ready")
        procs.append(est)
        if camera:
            cam = spawn("registration", "--camera", CAMERA, "--robot", ROBOT, "--source",
                        "synthetic", "--connect", ep)
            cam.wait_for_line("registration ready")
            procs.append(cam)
        rec = None
        if record is not None:
            rec = spawn("record", str(record), "--overwrite", "--no-progress", "--connect",
                        ep)
            rec.wait_for_line("record ready")
        sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--seed", "1", "--connect", ep)
        out, err = sim.communicate(timeout=600)
        assert sim.returncode == 0 and "all applied" in out, out + err
        result = {"sim_s": _wall(out, "sim")}
        if rec is not None:
            # let the recorder (nice 10) catch up: the file stops growing for 3 flushes
            assert record is not None
            last, still = -1, time.monotonic()
            while time.monotonic() - still < 3.0:
                size = record.stat().st_size
                if size != last:
                    last, still = size, time.monotonic()
                time.sleep(0.2)
            rec_out, _ = stop(rec)
            line = next(ln for ln in rec_out.splitlines() if ln.startswith("record stopped"))
            result["record"] = json.loads(line.split(": ", 1)[1])
            result["lag_ms"] = _lags(record)
        return result
    finally:
        for p in reversed(procs):
            stop(p)
        stop(router)


def _lags(path: Path) -> dict:
    with path.open("rb") as f:
        lags = [(m.log_time - m.publish_time) / 1e6 for _, _, m in
                make_reader(f).iter_messages(topics=[KEYS.state(ROBOT)])]
    lags.sort()
    return {"median": statistics.median(lags), "p99": lags[int(0.99 * (len(lags) - 1))],
            "max": lags[-1]}


def target_1(repeats: int, tmp: Path) -> None:
    print("1. the paper run with camera frames, estimator time with / without the recorder")
    without, with_ = [], []
    last = None
    for i in range(repeats):
        for recording in ((False, True) if i % 2 == 0 else (True, False)):
            r = paper_run(record=tmp / "frames.mcap" if recording else None, camera=True)
            (with_ if recording else without).append(r["sim_s"])
            if recording:
                last = r
            print(f"   run {i + 1} {'with' if recording else 'without'} recorder: "
                  f"{r['sim_s']:.3f} s", flush=True)
    a, b = statistics.median(without), statistics.median(with_)
    print(f"   median without {a:.3f} s, with {b:.3f} s: ratio {b / a:.3f} (target ≤ 1.05)")
    assert last is not None
    print(f"   the last recording: {last['record']}; state lag (log − publish) "
          f"{last['lag_ms']['median']:.1f} ms median, {last['lag_ms']['p99']:.1f} ms p99")


def _samples(path: Path) -> tuple[list[Sample], float]:
    """The bus samples of a recording (keys, payloads, Zenoh times) and its robot span."""
    out: list[Sample] = []
    stamps: list[float] = []
    with path.open("rb") as f:
        for _, channel, m in make_reader(f).iter_messages(log_time_order=True):
            if channel.message_encoding != "msgpack":
                continue
            out.append(Sample(channel.topic, bytes(m.data), source="bench",
                              time=len(out) + 1))
            if channel.topic == KEYS.state(ROBOT):
                stamps.append(float(peek_fields(m.data, ("stamp",))["stamp"]))
    return out, max(stamps) - min(stamps)


def _write_all(samples: list[Sample], out: Path, *, foxglove: bool) -> float:
    settings = RecordSettings(path=str(out), overwrite=True, foxglove=foxglove,
                              progress=False)
    recorder = Recorder(InProcessBus(), settings=settings, prefix="slamlens")
    t0 = time.perf_counter()
    for s in samples:
        recorder.write(s)
    recorder.close()
    return time.perf_counter() - t0


def target_2(repeats: int, tmp: Path) -> None:
    print("2. the recorder's write path on the paper run without frames (in one process)")
    source = tmp / "paper.mcap"
    r = paper_run(record=source, camera=False)
    print(f"   recorded live: {r['record']}; state lag {r['lag_ms']['median']:.1f} ms median, "
          f"{r['lag_ms']['p99']:.1f} ms p99, {r['lag_ms']['max']:.1f} ms max")
    samples, span = _samples(source)
    full, raw = [], []
    for i in range(repeats):
        for fox in ((True, False) if i % 2 == 0 else (False, True)):
            wall = _write_all(samples, tmp / "again.mcap", foxglove=fox)
            (full if fox else raw).append(wall)
    a, b = statistics.median(raw), statistics.median(full)
    print(f"   {len(samples)} samples, {span:.1f} s of robot time")
    print(f"   raw channels only: {a:.3f} s = {span / a:.0f}× real time")
    print(f"   with the Foxglove channels: {b:.3f} s = {span / b:.0f}× real time "
          f"(target ≥ 100×); {b / a:.2f}× the raw-only time")


def _mrclam_estimator(play: Path | None) -> float:
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    try:
        t0 = time.monotonic()
        if play is None:
            proc = spawn("replay", str(MRCLAM), "--format", "mrclam", "--robot-index", "1",
                         "--robot", ROBOT, "--rate", "0", "--connect", ep)
            name = "replay"
        else:
            proc = spawn("play", str(play), "--inputs-only", "--rate", "0", "--control", "",
                         "--connect", ep)
            name = "play"
        out, err = proc.communicate(timeout=1800)
        wall = time.monotonic() - t0
        assert proc.returncode == 0 and "all applied by the estimator" in out, out + err
        assert f"{name} done" in out, out
        return wall
    finally:
        stop(est)
        stop(router)


def target_3(repeats: int, tmp: Path) -> None:
    print("3. a whole MRCLAM robot run at --rate 0 into a fresh estimator: replay vs play")
    path = tmp / "mrclam.mcap"
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    # one key expression: one subscriber, so odometry and observations are written in the
    # order they arrived (two expressions are two queues, interleaved as they are taken)
    rec = spawn("record", str(path), "--overwrite", "--no-progress", "--no-foxglove",
                "--robot", ROBOT, "--connect", ep)
    rec.wait_for_line("record ready")
    try:
        replay = spawn("replay", str(MRCLAM), "--format", "mrclam", "--robot-index", "1",
                       "--robot", ROBOT, "--rate", "0", "--connect", ep)
        out, err = replay.communicate(timeout=1800)
        assert replay.returncode == 0 and "all applied" in out, out + err
    finally:
        rec_out, _ = stop(rec)
        stop(est)
        stop(router)
    print(f"   recorded: {rec_out.strip().splitlines()[-1]}")
    replays, plays = [], []
    for i in range(repeats):
        for playing in ((False, True) if i % 2 == 0 else (True, False)):
            wall = _mrclam_estimator(path if playing else None)
            (plays if playing else replays).append(wall)
            print(f"   run {i + 1} {'play' if playing else 'replay'}: {wall:.2f} s", flush=True)
    a, b = statistics.median(replays), statistics.median(plays)
    print(f"   median replay {a:.2f} s, play --inputs-only {b:.2f} s: ratio {b / a:.3f} "
          f"(target ≤ 1.05)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--only", default="1,2,3")
    args = parser.parse_args()
    only = {int(x) for x in args.only.split(",")}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if 1 in only:
            target_1(args.repeats, tmp)
        if 2 in only:
            target_2(args.repeats, tmp)
        if 3 in only:
            target_3(max(1, args.repeats // 2 + 1), tmp)


if __name__ == "__main__":
    main()
