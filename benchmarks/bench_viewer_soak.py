"""Viewer soak: many clients, many distinct settings; memory and fairness.

``slamlens viewer`` runs as a real process (map view, 1280x720, default limits), fed a
paper-like state (n = 15) at 30 Hz over loopback Zenoh. Websocket clients in this process
behave like the page (a frame, then ``next``):

1. **start**: one default-view client for a few seconds; its RSS (``VmRSS``) is the start;
2. **baseline**: the default-view clients alone: their frame rate without competition;
3. **load** (``--seconds``, 300 = 5 minutes): 50 clients at once, the default-view ones
   plus clients that each ask for new settings every so often, so that ``--settings``
   (300) distinct settings are asked in all; RSS sampled every second;
4. **leave**: every client goes; RSS is sampled until it is back within 20 % of the start
   (or ``--leave-seconds`` pass).

Printed: the default-view clients' fps (median over clients, and the 5th percentile of
their 5 s windows) under load and in the baseline (the ratio), the other clients' fps,
the RSS at start / peak / after they left, the documented bound, and the time to return.
Targets: default-view clients ≥ 15 fps; peak RSS under the bound of docs/viewer.md; RSS
back within 20 % of the start after the clients leave.

Run: ``.venv/bin/python benchmarks/bench_viewer_soak.py`` (5 minutes), or
``--seconds 30 --settings 60`` for a quick check. The machine is shared: quote medians.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import aiohttp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_render import paper_like_state  # noqa: E402

from slamlens.common.keys import Keys  # noqa: E402
from slamlens.common.messages import SlamState  # noqa: E402
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus, router_settings  # noqa: E402

REPO = Path(os.environ.get("SLAMLENS_REPO", Path(__file__).resolve().parents[1]))
KEYS = Keys()
ROBOT = "bench"
MODES = ("all", "inter", "minmeanmax")
PICTURE_MB = 1280 * 720 * 3 / 1e6  # the BGR picture one view holds (plus its JPEG)


# ------------------------------------------------------------------------------ the viewer
class Viewer:
    """``slamlens viewer`` as a real process, and its memory."""

    def __init__(self, endpoint: str, *extra: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "slamlens.services", "viewer", "--robot", ROBOT,
             "--connect", endpoint,
             "--http", "127.0.0.1:0", "-q", "--late-join-timeout-s", "0", *extra],
            cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("viewer ready"):
            self.stop()
            raise RuntimeError(f"viewer did not start: {line!r}")
        self.url = line.split()[-1]

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise RuntimeError("no VmRSS")

    def stop(self) -> str:
        self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
        return err


class Sampler(threading.Thread):
    """VmRSS once a second, with the phase it was taken in."""

    def __init__(self, viewer: Viewer) -> None:
        super().__init__(daemon=True)
        self.viewer = viewer
        self.phase = "start"
        self.samples: list[tuple[float, str, float]] = []
        self.stopped = threading.Event()

    def run(self) -> None:
        while not self.stopped.is_set():
            self.samples.append((time.monotonic(), self.phase, self.viewer.rss_mb()))
            self.stopped.wait(1.0)

    def of(self, phase: str) -> list[float]:
        return [rss for _, p, rss in self.samples if p == phase]


def publish_states(endpoint: str, stop: threading.Event, rate_hz: float = 30.0) -> None:
    """A paper-like state, the robot moving on a circle, at ``rate_hz`` until ``stop``."""
    base = paper_like_state(15)
    bus = open_bus(BusSettings(connect=(endpoint,)))
    pub = bus.publisher(KEYS.state(ROBOT))
    pub.wait_matched(10.0)  # type: ignore[attr-defined]
    t0, k = time.perf_counter(), 0
    try:
        while not stop.is_set():
            k += 1
            angle = 0.05 * k
            pub.put(SlamState(robot=ROBOT, seq=k, stamp=k / rate_hz, step="update",
                              pose=np.array([0.6 * np.cos(angle), 0.6 * np.sin(angle), angle]),
                              landmark_ids=base.landmark_ids, landmarks=base.landmarks,
                              covariance=base.covariance).to_bytes())
            delay = t0 + k / rate_hz - time.perf_counter()
            if delay > 0:
                stop.wait(delay)
    finally:
        bus.close()


# ------------------------------------------------------------------------------ clients
@dataclass
class Client:
    """One tab: a websocket of the page's kind, and its frames' arrival times."""

    name: str
    default_view: bool
    arrivals: list[float] = field(default_factory=list)
    refused: int = 0  #: settings changes the viewer refused (503: at its limits)

    def fps(self, t0: float, t1: float) -> float:
        return sum(1 for t in self.arrivals if t0 <= t < t1) / (t1 - t0)

    def windows(self, t0: float, t1: float, width: float = 5.0) -> list[float]:
        edges = np.arange(t0, t1 - width + 1e-9, width)
        return [self.fps(a, a + width) for a in edges]


async def stream(session: aiohttp.ClientSession, url: str, client: Client,
                 stop: asyncio.Event) -> None:
    ws_url = url.replace("http://", "ws://") + f"/ws?client={client.name}"
    while not stop.is_set():
        try:
            async with session.ws_connect(ws_url, max_msg_size=0, heartbeat=None) as ws:
                while not stop.is_set():
                    receive = asyncio.ensure_future(ws.receive())
                    halt = asyncio.ensure_future(stop.wait())
                    done, _ = await asyncio.wait({receive, halt},
                                                 return_when=asyncio.FIRST_COMPLETED)
                    if halt in done:
                        receive.cancel()
                        return
                    halt.cancel()
                    msg = receive.result()
                    if msg.type == aiohttp.WSMsgType.BINARY:
                        client.arrivals.append(time.monotonic())
                        await ws.send_str("next")
                    elif msg.type != aiohttp.WSMsgType.TEXT:
                        break  # closed: connect again
        except (aiohttp.ClientError, OSError):
            await asyncio.sleep(0.5)


async def change_settings(session: aiohttp.ClientSession, url: str, client: Client,
                          settings: list[dict], period_s: float, stop: asyncio.Event) -> None:
    """Ask for each of ``settings`` in turn, one every ``period_s``."""
    for change in settings:
        async with session.post(f"{url}/api/settings?client={client.name}",
                                json=change) as reply:
            if reply.status == 503:
                client.refused += 1
            elif reply.status != 200:
                raise RuntimeError(f"settings {change}: {reply.status} {await reply.text()}")
        try:
            await asyncio.wait_for(stop.wait(), period_s)
            return
        except TimeoutError:
            pass


def distinct_settings(count: int) -> list[dict]:
    return [{"scale": round(1.0 + 0.01 * (i + 1), 3), "mode": MODES[i % 3]}
            for i in range(count)]


async def run_clients(url: str, clients: list[Client], *, seconds: float,
                      settings: list[dict]) -> tuple[float, float]:
    """The clients for ``seconds``; the others share ``settings`` out, in turn."""
    stop = asyncio.Event()
    others = [c for c in clients if not c.default_view]
    per_client = [settings[i::len(others)] for i in range(len(others))] if others else []
    period = seconds / max(1, max((len(p) for p in per_client), default=1))
    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(connector=connector) as session:
        tasks = [asyncio.create_task(stream(session, url, c, stop)) for c in clients]
        tasks += [asyncio.create_task(change_settings(session, url, c, s, period, stop))
                  for c, s in zip(others, per_client, strict=True)]
        t0 = time.monotonic()
        await asyncio.sleep(seconds)
        t1 = time.monotonic()
        stop.set()
        await asyncio.gather(*tasks)
    return t0, t1


def status_of(url: str) -> dict:
    import urllib.request

    with urllib.request.urlopen(url + "/api/status", timeout=10) as reply:
        return json.loads(reply.read())


# ------------------------------------------------------------------------------ the run
def memory_back_after(viewer: Viewer, start_rss: float, seconds: float) -> float | None:
    """Seconds until the viewer's RSS is within 20 % of ``start_rss`` (None: not within
    ``seconds``); a second more is waited either way before the end's figures."""
    left_at = time.monotonic()
    back_after = None
    while time.monotonic() - left_at < seconds:
        if viewer.rss_mb() <= 1.2 * start_rss:
            back_after = time.monotonic() - left_at
            break
        time.sleep(1.0)
    time.sleep(1.0)
    return back_after


@dataclass
class Figures:
    """What the soak measured (main), for the report."""

    start_rss: float
    load_rss: list[float]
    end_rss: float
    back_after: float | None
    base_fps: list[float]
    fps_default: list[float]
    windows: list[float]
    fps_other: list[float]
    refused: int
    loaded: dict
    final: dict
    bound: float


def print_report(args: argparse.Namespace, f: Figures) -> None:
    print(f"viewer soak: {args.clients} clients ({args.default_clients} on the default view), "
          f"{args.settings} distinct settings over {args.seconds:.0f} s, states at 30 Hz, "
          f"n = 15, 1280x720 map view")
    print(f"  default-view fps, load    : median {np.median(f.fps_default):5.1f} "
          f"(clients {min(f.fps_default):4.1f}-{max(f.fps_default):4.1f}; 5 s windows p5 "
          f"{np.percentile(f.windows, 5):4.1f})   target >= 15")
    print(f"  default-view fps, baseline: median {np.median(f.base_fps):5.1f} (alone, same run)"
          f"   ratio load/baseline {np.median(f.fps_default) / np.median(f.base_fps):4.2f}")
    print(f"  other clients' fps, load  : median {np.median(f.fps_other):5.2f} "
          f"({min(f.fps_other):4.2f}-{max(f.fps_other):4.2f}); settings changes refused "
          f"(503) {f.refused}")
    held = f.loaded.get("views") or {}  # (absent before the limits: to compare with old code)
    print(f"  viewer at the end of load : views kept {held.get('kept')}, evicted "
          f"{held.get('evicted')}, refused {held.get('refused')}, pictures "
          f"{held.get('picture_bytes', float('nan')) / 1e6:5.1f} MB")
    print(f"  RSS: start {f.start_rss:6.1f} MB, load median {np.median(f.load_rss):6.1f} / peak "
          f"{max(f.load_rss):6.1f} MB (bound {f.bound:6.1f} MB), "
          f"after leaving {f.end_rss:6.1f} MB "
          f"({f.end_rss / f.start_rss:4.2f} x start; within 20 % after "
          + (f"{f.back_after:4.1f} s)" if f.back_after is not None else "never)"))
    print(f"  views kept once everybody left: {(f.final.get('views') or {}).get('kept')}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="the load phase")
    parser.add_argument("--settings", type=int, default=300, help="distinct settings asked")
    parser.add_argument("--clients", type=int, default=50, help="simultaneous clients")
    parser.add_argument("--default-clients", type=int, default=10,
                        help="of them on the default view")
    parser.add_argument("--baseline-seconds", type=float, default=20.0)
    parser.add_argument("--leave-seconds", type=float, default=90.0,
                        help="how long to wait for the memory to come back")
    args = parser.parse_args()

    endpoint = free_tcp_endpoint()
    router = open_bus(router_settings([endpoint]))
    viewer = Viewer(endpoint)
    stop = threading.Event()
    publisher = threading.Thread(target=publish_states, args=(endpoint, stop), daemon=True)
    publisher.start()
    sampler = Sampler(viewer)
    max_views = 64  # ViewerConfig's default
    try:
        sampler.start()
        warm = [Client("warm", True)]
        asyncio.run(run_clients(viewer.url, warm, seconds=8.0, settings=[]))
        start_rss = float(np.median(sampler.of("start")[-4:]))

        sampler.phase = "baseline"
        base_clients = [Client(f"base{k}", True) for k in range(args.default_clients)]
        b0, b1 = asyncio.run(run_clients(viewer.url, base_clients,
                                         seconds=args.baseline_seconds, settings=[]))
        base_fps = [c.fps(b0 + 2, b1) for c in base_clients]

        sampler.phase = "load"
        clients = [Client(f"def{k}", True) for k in range(args.default_clients)]
        clients += [Client(f"tab{k}", False) for k in range(args.clients - args.default_clients)]
        t0, t1 = asyncio.run(run_clients(viewer.url, clients, seconds=args.seconds,
                                         settings=distinct_settings(args.settings)))
        loaded = status_of(viewer.url)
        defaults = [c for c in clients if c.default_view]
        others = [c for c in clients if not c.default_view]
        fps_default = [c.fps(t0 + 2, t1) for c in defaults]
        windows = [w for c in defaults for w in c.windows(t0 + 2, t1)]
        fps_other = [c.fps(t0 + 2, t1) for c in others]
        load_rss = sampler.of("load")

        sampler.phase = "leave"
        back_after = memory_back_after(viewer, start_rss, args.leave_seconds)
        end_rss = viewer.rss_mb()
        final = status_of(viewer.url)
    finally:
        sampler.stopped.set()
        stop.set()
        publisher.join(timeout=5)
        err = viewer.stop()
        router.close()

    print_report(args, Figures(
        start_rss=start_rss, load_rss=load_rss, end_rss=end_rss, back_after=back_after,
        base_fps=base_fps, fps_default=fps_default, windows=windows, fps_other=fps_other,
        refused=sum(c.refused for c in others), loaded=loaded, final=final,
        bound=start_rss + (max_views + 1) * PICTURE_MB * 1.5 + 100))
    if "Traceback" in err:
        print("viewer stderr had a traceback:\n" + err[-3000:])


if __name__ == "__main__":
    main()
