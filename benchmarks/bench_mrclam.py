"""Consistency on real data: UTIAS MRCLAM dataset 6, all five robots, through the real
processes at ``--rate 0`` (router, ``slamlens estimator``, ``slamlens monitor``, ``slamlens
replay``: services/harness/mrclam_pipeline.py), every input applied and every state scored.

For each robot K, in one run:

1. ``before``   — the profile shipped before the re-fit (benchmarks/profiles/
   mrclam6_before.toml: standard EKF, fitted on robots 1 and 3): today's figures;
2. ``left out`` — the profile fitted on the *other* four robots (``slamlens tune … --folds
   DIR`` writes them: DIR/without-robotK.toml; benchmarks/profiles/ holds the ones of the
   shipped profile): what a lab can expect on a robot it did not fit — the targets;
3. ``shipped``  — deploy/mrclam.toml (fitted on all five), with the monitor's verdicts.

Figures: time-averaged pose NEES (3 expected), the fraction of 100-state windows whose
mean lies in the 95 % band [0.22, 9.35], absolute landmark RMSE and after a rigid fit, the
map's rotation, pose and heading RMSE, gated observations, dead reckoning's RMSE, and the
monitor's verdicts (states under an estimator fault; "tuning" states by what stands).
Targets (docs/consistency.md): left out NEES in [1, 6], landmark RMSE after a rigid fit
≤ 0.10 m; better than before (NEES nearer 3, in ratio, and a rigid-fit RMSE no worse than
before + 0.01 m); shipped: never an estimator fault, "tuning" only with NEES standing
(also where the dataset has no ground truth — robot 1's last 128 s — where the truth's
latest word on the pose covariance stands, docs/monitor.md).
``--offline`` adds the same profiles on an Estimator fed the dataset directly (fast).
``--plots DIR`` writes mrclam_nees.png, mrclam_map.png, mrclam_errors.png.

Run: ``.venv/bin/python benchmarks/bench_mrclam.py [--robots 1,2,3,4,5] [--plots
docs/figures] [--offline] [--before-offline] [--folds DIR] [--only shipped] [--json]``
(about 15 pipeline runs: 30–60 min on 2 shared cores; ``--before-offline``: 10; ``--only
shipped``: 5, the shipped profile's figures and the monitor's verdicts alone).
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
from slamlens.services.harness.mrclam_pipeline import (  # noqa: E402
    DATA,
    FOLDS,
    PROFILE,
    PipelineResult,
    run_pipeline,
)
from slamlens.services.slam import scoring  # noqa: E402
from slamlens.services.slam.mrclam import load_mrclam  # noqa: E402
from slamlens.services.slam.settings import EstimatorSettings  # noqa: E402

BEFORE = REPO / "benchmarks" / "profiles" / "mrclam6_before.toml"
HEADER = (f"{'robot':>6} {'run':>9} {'NEES':>7} {'windows':>8} {'states':>7} {'lm RMSE':>8} "
          f"{'rigid':>6} {'rot°':>6} {'pose':>6} {'head°':>6} {'DR pose':>8} {'DR head°':>8} "
          f"{'gated':>6} {'wall s':>7}")
ROWS = ("before", "left out", "shipped")


def row(robot: int, name: str, e: scoring.Evaluation, wall: float) -> str:
    dr_pos, dr_head = e.dead_reckoning_rmse()
    return (f"{robot:>6} {name:>9} {e.nees_mean:>7.2f} {e.window_fraction():>8.1%} "
            f"{e.state_fraction:>7.1%} {e.landmark_rmse:>8.3f} {e.landmark_rmse_rigid:>6.3f} "
            f"{e.map_rotation_deg:>6.1f} {e.pose_rmse:>6.3f} {e.heading_rmse_deg:>6.1f} "
            f"{dr_pos:>8.3f} {dr_head:>8.1f} {e.counts.get('gated', 0):>6.0f} {wall:>7.1f}")


def monitor_line(r: PipelineResult, duration_s: float) -> str:
    verdicts = ", ".join(f"{k} {v}" for k, v in sorted(r.verdicts.items()))
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(r.tuning_kinds.items())) or "none"
    timid = r.monitor.get("states_ok_with_timid_nis", 0)
    return (f"{'':>17}monitor: {verdicts} (Healths by verdict); tuning with standing: {kinds}; "
            f"ok with a NIS window below its band standing: {timid}; "
            f"estimator fault seen: {r.monitor['estimator_fault_seen']}; {r.states} states "
            f"received of {r.estimator['seq']}; {duration_s / r.wall_s:.1f}× real time")


def profiles_for(robot: int, folds: Path) -> dict[str, Path]:
    return {"before": BEFORE, "left out": folds / f"without-robot{robot}.toml",
            "shipped": PROFILE}


def nearer(e: scoring.Evaluation, base: scoring.Evaluation) -> bool:
    """Better than ``base``: NEES nearer 3 in ratio, rigid-fit RMSE no worse + 0.01 m."""
    return (abs(math.log(e.nees_mean / 3)) < abs(math.log(base.nees_mean / 3))
            and e.landmark_rmse_rigid <= base.landmark_rmse_rigid + 0.01)


def left_out_checks(robot: int, e: scoring.Evaluation,
                    base: scoring.Evaluation) -> list[tuple[str, bool]]:
    """The targets of a robot left out, against its figures before the re-fit."""
    return [
        (f"robot {robot} left out: NEES {e.nees_mean:.2f} in [1, 6]",
         1.0 <= e.nees_mean <= 6.0),
        (f"robot {robot} left out: landmark RMSE after a rigid fit "
         f"{e.landmark_rmse_rigid:.3f} ≤ 0.10 m", e.landmark_rmse_rigid <= 0.10),
        (f"robot {robot} left out better than before (NEES {base.nees_mean:.2f} → "
         f"{e.nees_mean:.2f}, rigid {base.landmark_rmse_rigid:.3f} → "
         f"{e.landmark_rmse_rigid:.3f} m)", nearer(e, base)),
    ]


def verdicts(robots: list[int], results: dict[int, dict[str, scoring.Evaluation]],
             pipes: dict[int, PipelineResult]) -> bool:
    ok = True
    for robot in robots:
        checks = []
        if "left out" in results[robot] and "before" in results[robot]:
            checks = left_out_checks(robot, results[robot]["left out"],
                                     results[robot]["before"])
        pipe = pipes.get(robot)
        if pipe is not None:
            without = sum(v for k, v in pipe.tuning_kinds.items()
                          if "nees" not in k.split("+"))
            with_truth = pipe.tuning_without_nees_with_truth
            checks += [
                (f"robot {robot} shipped: no estimator fault "
                 f"({pipe.verdicts.get('fault', 0)} fault Healths)",
                 pipe.verdicts.get("fault", 0) == 0
                 and not pipe.monitor["estimator_fault_seen"]),
                (f"robot {robot} shipped: 'tuning' only with NEES standing ({without} "
                 f"'tuning' Healths without, {with_truth} of them where the dataset has a "
                 "truth)", without == 0),
            ]
        for name, passed in checks:
            print(f"{'PASS' if passed else 'FAIL'}  {name}")
            ok &= passed
    return ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--folds", default=str(FOLDS), metavar="DIR",
                        help="where without-robotK.toml are (slamlens tune --folds)")
    parser.add_argument("--plots", default="", metavar="DIR")
    parser.add_argument("--offline", action="store_true",
                        help="also each profile on an Estimator fed the dataset directly")
    parser.add_argument("--json", action="store_true", help="also print the figures as JSON")
    parser.add_argument("--before-offline", action="store_true",
                        help="score the 'before' profile on an Estimator fed the dataset "
                             "directly, not through the processes (the same figures; five "
                             "pipeline runs fewer)")
    parser.add_argument("--only", choices=("before", "left out", "shipped"), default=None,
                        help="run this profile alone (its checks only)")
    args = parser.parse_args()
    if args.only is not None and args.plots:
        parser.error("--plots draws every profile: leave out --only")
    robots = [int(r) for r in args.robots.split(",")]
    folds = Path(args.folds)
    print(f"data {DATA}; before {BEFORE.relative_to(REPO)}; left out {folds}/without-robotK."
          f"toml; shipped {PROFILE.relative_to(REPO)}")
    print(HEADER)
    results: dict[int, dict[str, scoring.Evaluation]] = {}
    pipes: dict[int, PipelineResult] = {}
    summaries = []
    for robot in robots:
        run = load_mrclam(DATA, robot)
        results[robot] = {}
        for name, profile in profiles_for(robot, folds).items():
            if args.only is not None and name != args.only:
                continue
            if args.offline:
                t = time.monotonic()
                e = scoring.evaluate(run, load_settings(EstimatorSettings, profile))
                print(row(robot, f"{name[:6]} off", e, time.monotonic() - t), flush=True)
            if name == "before" and args.before_offline:
                t = time.monotonic()
                e = scoring.evaluate(run, load_settings(EstimatorSettings, profile))
                results[robot][name] = e
                print(row(robot, "before off", e, time.monotonic() - t), flush=True)
                summaries.append({"robot": robot, "run": "before (offline)", **e.summary()})
                continue
            r = run_pipeline(robot, profile=profile)
            results[robot][name] = r.evaluation
            print(row(robot, name, r.evaluation, r.wall_s), flush=True)
            if name == "shipped":
                pipes[robot] = r
                print(monitor_line(r, run.duration_s), flush=True)
            summaries.append({"robot": robot, "run": name, **r.evaluation.summary(),
                              "wall_s": r.wall_s, "verdicts": r.verdicts,
                              "tuning_kinds": r.tuning_kinds})
    ok = verdicts(robots, results, pipes)
    if args.json:
        print(json.dumps(summaries))
    if args.plots:
        for path in plots(Path(args.plots), results):
            print(f"wrote {path}")
    return 0 if ok else 1


def plots(directory: Path, results: dict[int, dict[str, scoring.Evaluation]]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    written = []
    lo, hi = scoring.nees_band()
    robots = sorted(results)

    fig, axes = plt.subplots(len(robots), 1, figsize=(9, 2.6 * len(robots)), squeeze=False)
    for ax, robot in zip(axes[:, 0], robots, strict=True):
        for name, colour in (("before", "tab:red"), ("left out", "tab:blue")):
            e = results[robot].get(name)
            if e is None:
                continue
            finite = np.isfinite(e.nees)
            w = e.windows(100)
            t = e.stamps[finite][:w.size * 100].reshape(-1, 100).mean(axis=1) - e.stamps[0]
            ax.semilogy(t, w, color=colour, lw=1.0,
                        label=f"{name}: mean {e.nees_mean:.1f}, "
                              f"{e.window_fraction():.0%} of windows in band")
        ax.axhspan(lo, hi, color="tab:green", alpha=0.12, label="95 % band of a window mean")
        ax.axhline(3.0, color="k", lw=0.8, ls="--")
        ax.set_title(f"MRCLAM dataset 6, robot {robot}: pose NEES, means of 100 states",
                     fontsize=9)
        ax.set_xlabel("dataset time since start, s")
        ax.set_ylabel("NEES")
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    written.append(_save(fig, directory / "mrclam_nees.png"))

    fig, axes = plt.subplots(1, len(robots), figsize=(4.2 * len(robots), 4.4), squeeze=False)
    for ax, robot in zip(axes[0], robots, strict=True):
        e = results[robot]["left out"]
        truth = scoring.TruthTrack.from_mrclam(load_mrclam(DATA, robot))
        ax.plot(truth.poses[:, 0], truth.poses[:, 1], color="0.6", lw=0.6, label="truth")
        if e.poses is not None:
            ax.plot(e.poses[:, 0], e.poses[:, 1], color="tab:blue", lw=0.6, label="estimate")
        ax.scatter(truth.landmarks[:, 0], truth.landmarks[:, 1], marker="x", color="k",
                   label="true landmarks")
        if e.landmarks is not None:
            ax.scatter(e.landmarks[:, 0], e.landmarks[:, 1], facecolors="none",
                       edgecolors="tab:blue", label="estimated")
        ax.set_aspect("equal")
        ax.set_title(f"robot {robot} left out: landmarks {e.landmark_rmse:.2f} m, "
                     f"{e.landmark_rmse_rigid:.3f} m rigid", fontsize=8)
        ax.legend(fontsize=6)
    fig.tight_layout()
    written.append(_save(fig, directory / "mrclam_map.png"))

    fig, axes = plt.subplots(len(robots), 2, figsize=(11, 2.4 * len(robots)), squeeze=False)
    for (ax_p, ax_h), robot in zip(axes, robots, strict=True):
        e = results[robot]["left out"]
        t = e.stamps - e.stamps[0]
        ax_p.plot(t, np.hypot(e.errors[:, 0], e.errors[:, 1]), color="tab:blue", lw=0.6,
                  label="estimate")
        if e.sigmas is not None:
            ax_p.plot(t, 2 * np.hypot(e.sigmas[:, 0], e.sigmas[:, 1]), color="tab:blue",
                      lw=0.5, ls=":", label="2σ (position)")
        if e.dead_reckoning is not None and len(e.dead_reckoning) == len(t):
            ax_p.plot(t, np.hypot(e.dead_reckoning[:, 0], e.dead_reckoning[:, 1]),
                      color="tab:red", lw=0.6, label="dead reckoning")
        ax_p.set_yscale("log")
        ax_p.set_title(f"robot {robot} left out: position error, m", fontsize=8)
        ax_p.legend(fontsize=6)
        ax_h.plot(t, np.degrees(np.abs(e.errors[:, 2])), color="tab:blue", lw=0.6,
                  label="estimate")
        if e.sigmas is not None:
            ax_h.plot(t, 2 * np.degrees(e.sigmas[:, 2]), color="tab:blue", lw=0.5, ls=":",
                      label="2σ")
        ax_h.set_title(f"robot {robot} left out: |heading error|, degrees", fontsize=8)
        ax_h.legend(fontsize=6)
    fig.tight_layout()
    written.append(_save(fig, directory / "mrclam_errors.png"))
    return written


def _save(fig, path: Path) -> Path:  # type: ignore[no-untyped-def]
    fig.savefig(path, dpi=80)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


if __name__ == "__main__":
    sys.exit(main())
