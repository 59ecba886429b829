"""The AR page end to end: browser frame → overlay shown, frames a second, and how far the
overlay lands from the truth with the phone's default camera model.

Debian's Chromium plays the synthetic head-mounted walk (services/harness/ar_video.py, 1280×720) as
its camera; a viewer (in-process) and ``slamlens registration --source browser`` (a real
process) on loopback Zenoh; the robot's state is the paper world's 15 features, all pairs
drawn (the default view). The page measures, per frame, the time from taking it off the
video to showing its answer (``window.slamlensAr.overlayLatencies``). Runs in one session:

* **baseline**: no registration service and ``ar_wait_s`` 0, so each frame comes back as it
  went at once: the page, the websocket and the viewer without registration or drawing;
* **AR, calibrated**: the video's true intrinsics as the phone's calibration;
* **AR, default model**: no calibration (``--browser-hfov`` 67°; the video is 75° wide),
  with the cones' distance from the truth (px) as the browser test measures it.

    .venv/bin/python benchmarks/bench_ar.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.session import (  # noqa: E402
    BusSettings,
    free_tcp_endpoint,
    open_bus,
    router_settings,
)
from slamlens.services.harness.ar_rig import (  # noqa: E402
    CONES_ONLY,
    cone_offsets,
    open_ar_page,
    post_settings,
    shown_picture,
    start_rig,
)
from slamlens.services.harness.ar_video import read_index, render_walk  # noqa: E402
from slamlens.services.visualiser.ar import ArLimits  # noqa: E402


def measure(page, seconds: float) -> dict[str, float]:
    page.wait_for_function("window.slamlensAr.answered >= 20", timeout=120000)
    start = page.evaluate("""() => { const a = window.slamlensAr;
        a.latencies.length = 0; a.overlayLatencies.length = 0;
        return [a.answered, a.overlays]; }""")
    t0 = time.monotonic()
    page.wait_for_timeout(seconds * 1000)  # the measuring window (not a synchronisation)
    end = page.evaluate("[window.slamlensAr.answered, window.slamlensAr.overlays]")
    elapsed = time.monotonic() - t0
    lat = page.evaluate("window.slamlensAr.latencies") or [float("nan")]
    over = page.evaluate("window.slamlensAr.overlayLatencies") or [float("nan")]
    timings = page.evaluate("window.slamlensAr.timings")[-200:]
    parts = {part: statistics.median(t[part] for t in timings) if timings else float("nan")
             for part in ("encode", "server", "draw", "show")}
    notes = page.evaluate("window.slamlensAr.notes")
    return {"parts": parts, "notes": notes, "fps": (end[0] - start[0]) / elapsed,
            "overlay_fps": (end[1] - start[1]) / elapsed,
            "latency_ms": statistics.median(lat[-200:]),
            "overlay_latency_ms": statistics.median(over[-200:]),
            "overlay_p90_ms": float(np.percentile(over[-200:], 90))}


def offsets(page, video, samples: int = 6) -> list[float]:
    client = page.evaluate("window.slamlensAr.client")
    url = page.url.split("/ar")[0]
    post_settings(url, client, CONES_ONLY)
    found: list[float] = []
    seen: set[int] = set()
    while len(seen) < samples:
        answered = page.evaluate("window.slamlensAr.answered")
        page.wait_for_function(f"window.slamlensAr.answered > {answered}", timeout=30000)
        image, last = shown_picture(page)
        index = read_index(image)
        if not last or not last["overlay"] or index is None or index in seen:
            continue
        seen.add(index)
        found += [o for o in cone_offsets(video, index, image) if np.isfinite(o)]
    return found


def run(label: str, video, *, calibrated: bool, registration: bool, seconds: float,
        with_offsets: bool, query: str = "") -> None:
    endpoint = free_tcp_endpoint()
    router = open_bus(router_settings([endpoint]))
    buses = []

    def make_client():
        bus = open_bus(BusSettings(connect=(endpoint,)))
        buses.append(bus)
        return bus

    try:
        with tempfile.TemporaryDirectory() as tmp:
            # without registration each frame is answered at once, as it went
            limits = None if registration else ArLimits(wait_s=0.0)
            rig_iter = start_rig(make_client, endpoint, Path(tmp), video,
                                 calibrated=calibrated, registration=registration,
                                 limits=limits)
            rig = next(rig_iter)
            p, browser, page, _errors = open_ar_page(rig.y4m, rig.url, query=query)
            try:
                result = measure(page, seconds)
                line = (f"{label:28s} {result['fps']:5.1f} fps answered, "
                        f"{result['overlay_fps']:5.1f} with the overlay; latency median "
                        f"{result['latency_ms']:6.1f} ms, overlay "
                        f"{result['overlay_latency_ms']:6.1f} ms "
                        f"(p90 {result['overlay_p90_ms']:.0f}); "
                        + ", ".join(f"{k} {v:.1f}" for k, v in result["parts"].items()
                                    if np.isfinite(v)))
                if registration and result["notes"]:
                    line += f"; without an overlay (since the start): {result['notes']}"
                if with_offsets:
                    found = offsets(page, video)
                    line += (f"; cones from the truth median {np.median(found):.2f} px, "
                             f"max {np.max(found):.2f} px ({len(found)} cones)")
                print(line, flush=True)
            finally:
                browser.close()
                p.stop()
                try:
                    next(rig_iter)
                except StopIteration:
                    pass
    finally:
        for bus in buses:
            bus.close()
        router.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--inflight", type=int, default=0,
                        help="the page's frames in flight (its ?inflight=; 0: its default)")
    parser.add_argument("--only", choices=("baseline", "calibrated", "default"),
                        help="one run only")
    args = parser.parse_args()
    query = f"&inflight={args.inflight}" if args.inflight else ""
    video = render_walk(48, arc_deg=60.0)
    print("1280x720, n = 15, all pairs; medians over the window"
          + (f"; {args.inflight} frames in flight" if args.inflight else ""), flush=True)
    if args.only in (None, "baseline"):
        run("baseline (no registration)", video, calibrated=True, registration=False,
            seconds=args.seconds, with_offsets=False, query=query)
    if args.only in (None, "calibrated"):
        run("AR, calibrated", video, calibrated=True, registration=True,
            seconds=args.seconds, with_offsets=True, query=query)
    if args.only in (None, "default"):
        run("AR, default phone model", video, calibrated=False, registration=True,
            seconds=args.seconds, with_offsets=True, query=query)


if __name__ == "__main__":
    main()
