"""Issue 11's figures on real data: UTIAS MRCLAM dataset 6, robots 1 and 3.

For each robot, three rows measured in the same run:

1. ``defaults``  — the estimator's defaults (the simulator's noise), offline: the baseline;
2. ``profile``   — ``deploy/mrclam.toml``, offline (an Estimator fed the dataset directly);
3. ``processes`` — ``deploy/mrclam.toml`` through the real processes at ``--rate 0``: router,
   ``slamlens estimator``, ``slamlens monitor``, ``slamlens replay``
   (services/harness/mrclam_pipeline.py),
   every state received and scored; and the monitor's verdicts.

Figures: time-averaged pose NEES (3 expected), the fraction of 100-state windows whose mean
lies in the 95 % band [0.22, 9.35], absolute landmark RMSE and after a rigid fit, pose and
heading RMSE, and dead reckoning's RMSE over the same stamps. ``--plots DIR`` also writes
``mrclam_nees.png``, ``mrclam_map.png`` and ``mrclam_errors.png`` (docs/consistency.md).

Run: ``.venv/bin/python benchmarks/bench_mrclam.py [--robots 1,3] [--plots docs/figures]
[--no-processes]`` (about 4 min on 2 shared cores).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.config import load_settings  # noqa: E402
from slamlens.services.harness.mrclam_pipeline import DATA, PROFILE, run_pipeline  # noqa: E402
from slamlens.services.slam import tuning  # noqa: E402
from slamlens.services.slam.mrclam import load_mrclam  # noqa: E402
from slamlens.services.slam.settings import EstimatorSettings  # noqa: E402

HEADER = (f"{'robot':>6} {'run':>9} {'NEES':>7} {'windows':>8} {'states':>7} {'lm RMSE':>8} "
          f"{'rigid':>6} {'rot°':>6} {'pose':>6} {'head°':>6} {'DR pose':>8} {'DR head°':>8} "
          f"{'gated':>6} {'wall s':>7}")


def row(robot: int, name: str, e: tuning.Evaluation, wall: float) -> str:
    dr_pos, dr_head = e.dead_reckoning_rmse()
    return (f"{robot:>6} {name:>9} {e.nees_mean:>7.2f} {e.window_fraction():>8.1%} "
            f"{e.state_fraction:>7.1%} {e.landmark_rmse:>8.3f} {e.landmark_rmse_rigid:>6.3f} "
            f"{e.map_rotation_deg:>6.1f} {e.pose_rmse:>6.3f} {e.heading_rmse_deg:>6.1f} "
            f"{dr_pos:>8.3f} {dr_head:>8.1f} {e.counts.get('gated', 0):>6.0f} {wall:>7.1f}")


def plots(directory: Path, results: dict[int, dict[str, tuning.Evaluation]]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    written = []
    lo, hi = tuning.nees_band()
    robots = sorted(results)

    fig, axes = plt.subplots(len(robots), 1, figsize=(9, 3.2 * len(robots)), squeeze=False)
    for ax, robot in zip(axes[:, 0], robots, strict=True):
        for name, colour in (("defaults", "tab:red"), ("processes", "tab:blue")):
            e = results[robot].get(name)
            if e is None:
                continue
            finite = np.isfinite(e.nees)
            w = e.windows(100)
            t = e.stamps[finite][:w.size * 100].reshape(-1, 100).mean(axis=1) - e.stamps[0]
            ax.semilogy(t, w, color=colour, lw=1.2,
                        label=f"{name}: mean {e.nees_mean:.1f}, "
                              f"{e.window_fraction():.0%} of windows in band")
        ax.axhspan(lo, hi, color="tab:green", alpha=0.12, label="95 % band of a window mean")
        ax.axhline(3.0, color="k", lw=0.8, ls="--", label="expected (3)")
        ax.set_title(f"MRCLAM dataset 6, robot {robot}: pose NEES, means of 100 states")
        ax.set_xlabel("dataset time since start, s")
        ax.set_ylabel("NEES")
        ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    path = directory / "mrclam_nees.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    written.append(path)

    fig, axes = plt.subplots(1, len(robots), figsize=(6 * len(robots), 5.5), squeeze=False)
    for ax, robot in zip(axes[0], robots, strict=True):
        e = results[robot]["processes"]
        truth = tuning.TruthTrack.from_mrclam(load_mrclam(DATA, robot))
        ax.plot(truth.poses[:, 0], truth.poses[:, 1], color="0.6", lw=0.8, label="truth")
        if e.poses is not None:
            ax.plot(e.poses[:, 0], e.poses[:, 1], color="tab:blue", lw=0.8, label="estimate")
        ax.scatter(truth.landmarks[:, 0], truth.landmarks[:, 1], marker="x", color="k",
                   label="true landmarks")
        if e.landmarks is not None:
            ax.scatter(e.landmarks[:, 0], e.landmarks[:, 1], facecolors="none",
                       edgecolors="tab:blue", label="estimated landmarks")
        ax.set_aspect("equal")
        ax.set_title(f"robot {robot} (map frame): landmark RMSE {e.landmark_rmse:.2f} m, "
                     f"{e.landmark_rmse_rigid:.3f} m after a rigid fit", fontsize=9)
        ax.set_xlabel("x, m")
        ax.set_ylabel("y, m")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = directory / "mrclam_map.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    written.append(path)

    fig, axes = plt.subplots(len(robots), 2, figsize=(11, 3.0 * len(robots)), squeeze=False)
    for (ax_p, ax_h), robot in zip(axes, robots, strict=True):
        e = results[robot]["processes"]
        t = e.stamps - e.stamps[0]
        pos = np.hypot(e.errors[:, 0], e.errors[:, 1])
        ax_p.plot(t, pos, color="tab:blue", lw=0.8, label="estimate")
        if e.sigmas is not None:
            ax_p.plot(t, 2 * np.hypot(e.sigmas[:, 0], e.sigmas[:, 1]), color="tab:blue",
                      lw=0.6, ls=":", label="2σ (position)")
        if e.dead_reckoning is not None and len(e.dead_reckoning) == len(t):
            ax_p.plot(t, np.hypot(e.dead_reckoning[:, 0], e.dead_reckoning[:, 1]),
                      color="tab:red", lw=0.8, label="dead reckoning")
        ax_p.set_yscale("log")
        ax_p.set_title(f"robot {robot}: position error, m", fontsize=9)
        ax_p.legend(fontsize=7)
        ax_h.plot(t, np.degrees(np.abs(e.errors[:, 2])), color="tab:blue", lw=0.8,
                  label="estimate")
        if e.sigmas is not None:
            ax_h.plot(t, 2 * np.degrees(e.sigmas[:, 2]), color="tab:blue", lw=0.6, ls=":",
                      label="2σ")
        ax_h.set_title(f"robot {robot}: |heading error|, degrees", fontsize=9)
        ax_h.legend(fontsize=7)
        for ax in (ax_p, ax_h):
            ax.set_xlabel("dataset time since start, s")
    fig.tight_layout()
    path = directory / "mrclam_errors.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    written.append(path)
    return written


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", default="1,3")
    parser.add_argument("--plots", default="", metavar="DIR")
    parser.add_argument("--no-processes", action="store_true",
                        help="offline rows only (fast; no acceptance figures)")
    parser.add_argument("--json", action="store_true", help="also print the figures as JSON")
    args = parser.parse_args()
    robots = [int(r) for r in args.robots.split(",")]
    profile = load_settings(EstimatorSettings, PROFILE)
    print(f"profile {PROFILE.relative_to(REPO)}; data {DATA}")
    print(HEADER)
    results: dict[int, dict[str, tuning.Evaluation]] = {}
    summaries = []
    for robot in robots:
        run = load_mrclam(DATA, robot)
        results[robot] = {}
        for name, settings in (("defaults", EstimatorSettings()), ("profile", profile)):
            t = time.monotonic()
            e = tuning.evaluate(run, settings)
            wall = time.monotonic() - t
            results[robot][name] = e
            print(row(robot, name, e, wall), flush=True)
            summaries.append({"robot": robot, "run": name, **e.summary(), "wall_s": wall})
        if args.no_processes:
            continue
        r = run_pipeline(robot)
        results[robot]["processes"] = r.evaluation
        print(row(robot, "processes", r.evaluation, r.wall_s), flush=True)
        verdicts = ", ".join(f"{k} {v}" for k, v in sorted(r.verdicts.items()))
        print(f"{'':>17}monitor: {verdicts} (states by Health verdict); estimator fault seen: "
              f"{r.monitor['estimator_fault_seen']}; {r.states} states received of "
              f"{r.estimator['seq']}; {run.duration_s / r.wall_s:.1f}× real time", flush=True)
        summaries.append({"robot": robot, "run": "processes", **r.evaluation.summary(),
                          "wall_s": r.wall_s, "verdicts": r.verdicts})
    ok = all(math.isfinite(s["nees_mean"]) for s in summaries)
    for robot in robots:
        e = results[robot].get("processes") or results[robot]["profile"]
        base = results[robot]["defaults"]
        verdict = ("PASS" if e.nees_mean <= 6 and e.window_fraction() >= 0.8
                   and e.landmark_rmse_rigid <= 0.10 else "FAIL")
        print(f"{verdict}  robot {robot}: NEES {e.nees_mean:.2f} ≤ 6, windows "
              f"{e.window_fraction():.0%} ≥ 80 %, rigid landmark RMSE "
              f"{e.landmark_rmse_rigid:.3f} ≤ 0.10 m (defaults: NEES {base.nees_mean:.1f}, "
              f"ratio {base.nees_mean / e.nees_mean:.1f}×)")
    if args.json:
        print(json.dumps(summaries))
    if args.plots:
        for path in plots(Path(args.plots), results if not args.no_processes else {
                k: {**v, "processes": v["profile"]} for k, v in results.items()}):
            print(f"wrote {path}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
