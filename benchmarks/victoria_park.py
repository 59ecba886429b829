"""Victoria Park (GTSAM's file, its own noise: deploy/victoria_park.toml) under the monitor,
every state checked — a second real dataset, one no slamlens profile was fitted on.

For each linearisation the profile runs on an Estimator fed the file (each step played as
two Odometry, docs/drivers.md) and a Monitor in this process with its default settings
checks every state; there is no ground truth, so the verdict rests on the NIS and the
covariance theorems. Printed per linearisation: the map's size, the NIS (mean, median:
2 and 1.39 for a consistent filter), the share of the monitor's NIS windows below and above
their band, the Healths by verdict, the kinds of violation that stood, and whether any
estimator fault was seen. Drawn (``--out``): the OC map and path over odometry alone, and
the NIS window means against their band with the verdict.

``--snapshot PNG`` instead runs the park through the real processes at ``--rate 0`` (router,
estimator with the profile, viewer, ``slamlens replay --format victoria-park``), prints the
replay's final line (every input applied, its wall time) and saves the viewer's
``/snapshot.png`` of the last state: the map view, 151 trees, their pairs' P_d.

``--grid`` instead runs the OC estimator alone (no monitor) with the profile's sensor σ and
motion σ scaled over a grid, and with a χ² gate: is there a white-noise model whose NIS is
in its band? Printed per setting: NIS mean and median, and the share of consecutive
50-update windows whose mean NIS is below / above the 95 % band of a χ²₁₀₀ / 50.

Run: ``.venv/bin/python benchmarks/victoria_park.py [--out docs/figures/victoria_park.png]
[--jobs 2]`` (about 2.5 min of one core per linearisation: the monitor checks each
state of a map of up to 151 trees; 4 min on 2 cores).
"""

from __future__ import annotations

import argparse
import math
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from slamlens.common.config import load_settings
from slamlens.common.messages import Health, Odometry
from slamlens.services.harness.monitored import monitored
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import quadratic_forms_2x2
from slamlens.services.slam import models
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.observe_report import ObserveReport
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.victoria_park import load_victoria_park

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "victoria_park" / "victoria_park_gtsam.txt"
PROFILE = REPO / "deploy" / "victoria_park.toml"
LINEARISATIONS = ("standard", "fej", "oc")


@dataclass
class ParkRun:
    """One linearisation's run, reduced to what the table and the figure need."""

    linearisation: str
    t: list[float] = field(default_factory=list)
    nis_window: list[tuple[float, float, float]] = field(default_factory=list)  #: mean, lo, hi
    verdicts: list[str] = field(default_factory=list)
    kinds: Counter = field(default_factory=Counter)  #: violation kinds standing, per Health
    nis: list[float] = field(default_factory=list)
    path: list[tuple[float, float]] = field(default_factory=list)
    odometry_path: list[tuple[float, float]] = field(default_factory=list)
    landmarks: np.ndarray | None = None
    fault_seen: bool = False

    def add(self, t: float, health: Health) -> None:
        s = health.statistics
        self.t.append(t)
        self.nis_window.append((s.get("nis_window_mean", math.nan),
                                s.get("nis_window_lo", math.nan),
                                s.get("nis_window_hi", math.nan)))
        self.verdicts.append(health.verdict)
        self.kinds.update({v.kind for v in health.standing})
        self.fault_seen |= health.verdict == "fault"


def nis_of(report: ObserveReport) -> np.ndarray:
    """The NIS of an update's innovations, as the monitor computes it."""
    return quadratic_forms_2x2(report.innovations, report.innovation_covariances)


def park_run(linearisation: str) -> ParkRun:
    """The profile with ``linearisation`` over the whole file, every state checked."""
    run = load_victoria_park(DATA)
    est = Estimator(replace(load_settings(EstimatorSettings, PROFILE, {"robot": run.robot}),
                            linearisation=linearisation))
    out = ParkRun(linearisation)
    dead = np.zeros(3)
    for message, report, health in monitored(est, Monitor(MonitorSettings()), run.events()):
        if report is not None:
            out.nis.extend(nis_of(report).tolist())
        if isinstance(message, Odometry):
            dead = models.motion(dead, v=message.v, w=message.w, dt=message.dt)
            out.odometry_path.append((dead[0], dead[1]))
            out.path.append((est.pose[0], est.pose[1]))
        out.add(message.stamp, health)
    out.landmarks = np.array(est.landmarks)
    return out


def summary(r: ParkRun) -> str:
    window = np.array(r.nis_window)
    known = np.isfinite(window[:, 0])
    below = np.mean(window[known, 0] < window[known, 1]) if known.any() else math.nan
    above = np.mean(window[known, 0] > window[known, 2]) if known.any() else math.nan
    nis = np.array(r.nis)
    verdicts = ", ".join(f"{k} {n}" for k, n in sorted(Counter(r.verdicts).items()))
    kinds = ", ".join(f"{k} {n}" for k, n in r.kinds.most_common())
    return (f"{r.linearisation:>8}: n {len(r.landmarks) if r.landmarks is not None else 0}, "
            f"{nis.size} updates, NIS mean {nis.mean():.2f} median {np.median(nis):.2f} "
            f"(2, 1.39 expected); Healths with the NIS window below its band {below:.0%}, "
            f"above {above:.0%}; verdicts: {verdicts}; standing: {kinds or 'none'}; "
            f"estimator fault seen: {r.fault_seen}")


def draw(runs: list[ParkRun], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    oc = next(r for r in runs if r.linearisation == "oc")
    fig = plt.figure(figsize=(10, 8))
    ax = fig.add_subplot(2, 1, 1)
    odo, path = np.array(oc.odometry_path), np.array(oc.path)
    ax.plot(odo[:, 0], odo[:, 1], color="0.6", lw=0.6, label="odometry alone")
    ax.plot(path[:, 0], path[:, 1], color="tab:blue", lw=0.8, label="OC estimate")
    if oc.landmarks is not None:
        ax.plot(oc.landmarks[:, 0], oc.landmarks[:, 1], "+", color="tab:green", ms=5,
                label=f"{len(oc.landmarks)} trees (OC map)")
    ax.set_aspect("equal")
    ax.set_title("Victoria Park, GTSAM's file and noise (deploy/victoria_park.toml)",
                 fontsize=9)
    ax.legend(fontsize=7, loc="lower left")
    ax = fig.add_subplot(2, 1, 2)
    for r, colour in zip(runs, ("tab:red", "tab:orange", "tab:blue"), strict=False):
        w = np.array(r.nis_window)
        ax.semilogy(r.t, w[:, 0], color=colour, lw=0.7, label=f"{r.linearisation}: NIS "
                                                               "window mean")
    w = np.array(oc.nis_window)
    ax.fill_between(oc.t, w[:, 1], w[:, 2], color="tab:blue", alpha=0.12, lw=0,
                    label="the band (95 %)")
    ax.fill_between(oc.t, 0, 1, where=np.array(oc.verdicts) != "ok",
                    transform=ax.get_xaxis_transform(), color="tab:red", alpha=0.12, lw=0,
                    step="post", label="OC: 'inconsistent tuning'")
    ax.set_xlabel("s (0.2 s a pose step, nominal)")
    ax.set_ylabel("NIS window mean")
    ax.legend(fontsize=7, ncol=3, loc="upper left")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


GRID = [(sensor, motion, 0.0) for sensor in (1.0, 0.5, 0.3, 0.2) for motion in (1.0, 2.0, 4.0)]
GRID += [(1.0, 1.0, 13.82), (0.5, 2.0, 13.82)]  #: (sensor σ ×, motion σ ×, gate χ²)


def grid_row(setting: tuple[float, float, float]) -> str:
    """One setting of ``--grid`` (module docstring)."""
    from scipy.stats import chi2

    sensor, motion, gate = setting
    s = load_settings(EstimatorSettings, PROFILE, {"robot": "park"})
    est = Estimator(replace(s, sigma_range=s.sigma_range * sensor,
                            sigma_bearing=s.sigma_bearing * sensor, sigma_v=s.sigma_v * motion,
                            sigma_w=s.sigma_w * motion, innovation_gate_chi2=gate))
    nis: list[float] = []
    for message in load_victoria_park(DATA).events():
        report = est.apply(message)
        if report is not None:
            nis.extend(nis_of(report).tolist())
    values = np.array(nis)
    windows = values[:values.size // 50 * 50].reshape(-1, 50).mean(axis=1)
    lo, hi = chi2.ppf([0.025, 0.975], 100) / 50
    return (f"sensor σ ×{sensor:<4g} motion σ ×{motion:<3g} gate {gate or 'none':>5}: "
            f"{values.size} updates, {est.gated} gated, NIS mean {values.mean():.2f} median "
            f"{np.median(values):.2f}; windows below {np.mean(windows < lo):.0%}, above "
            f"{np.mean(windows > hi):.0%}; final pose ({est.pose[0]:.1f}, {est.pose[1]:.1f}) m")


def snapshot(out: Path) -> None:
    """The processes' run and the viewer's picture of it (module docstring)."""
    import urllib.request

    from slamlens.common.session import free_tcp_endpoint
    from slamlens.services.harness.procs import spawn, stop

    endpoint = free_tcp_endpoint()
    procs = [spawn("router", "--listen", endpoint)]
    try:
        procs[0].wait_for_line("router ready", timeout=30)
        procs.append(spawn("estimator", "--config", str(PROFILE), "--robot", "park",
                           "--connect", endpoint))
        procs.append(spawn("viewer", "--robot", "park", "--http", "127.0.0.1:0",
                           "--connect", endpoint))
        procs[1].wait_for_line("estimator ready", timeout=60)
        url = procs[2].wait_for_line("viewer ready", timeout=60).split()[-1].rstrip("/")
        replay = spawn("replay", str(DATA), "--format", "victoria-park", "--robot", "park",
                       "--rate", "0", "--connect", endpoint)
        procs.append(replay)
        print(replay.wait_for_line("replay done", timeout=600).strip(), flush=True)
        # the snapshot waits (up to 3 s) for a picture of the newest inputs
        png = urllib.request.urlopen(f"{url}/snapshot.png", timeout=60).read()
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(png)
        print(f"wrote {out}")
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                stop(proc)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default=str(REPO / "docs" / "figures" / "victoria_park.png"))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--grid", action="store_true", help="the noise grid (no monitor)")
    parser.add_argument("--snapshot", default="", metavar="PNG",
                        help="the processes' run and the viewer's picture, saved here")
    args = parser.parse_args()
    if args.snapshot:
        snapshot(Path(args.snapshot))
        return 0
    if args.grid:
        with ProcessPoolExecutor(max(1, args.jobs)) as pool:
            for line in pool.map(grid_row, GRID):
                print(line, flush=True)
        return 0
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        runs = list(pool.map(park_run, LINEARISATIONS))
    for r in runs:
        print(summary(r), flush=True)
    draw(runs, Path(args.out))
    print(f"wrote {args.out}")
    return 1 if any(r.fault_seen for r in runs) else 0


if __name__ == "__main__":
    raise SystemExit(main())
