"""The monitor's verdict on UTIAS MRCLAM dataset 6, robot by robot, over time, drawn.

For each robot the shipped profile (deploy/mrclam.toml) runs on an Estimator fed the dataset
directly, and a Monitor in this process with its default settings checks every state, with
the dataset's ground truth (the monitor service's own checks, in the order the processes
give them; ``benchmarks/bench_mrclam.py --only shipped`` runs the same through the real
processes and counts the same verdicts). It prints, per robot, the Healths by verdict and
those with a NIS window below its band standing (docs/monitor.md, "The verdict": listed,
not "tuning", while the pose NEES is in its band), and draws each robot's sliding NIS and
pose NEES window means against their bands, shading where the verdict was "tuning", where
a timid NIS stood under "ok", and where the dataset has no ground truth over the last
3 s (robot 1's last 128 s, a 2 s gap of robot 4's and the 3 s after it): there the truth's
latest word on the pose covariance stands (docs/monitor.md, "The verdict"). The check (the
target of docs/benchmarks.md): never "estimator fault", and "inconsistent tuning" only
while a NEES window stands, the truth or not. It prints the NIS band's measured dependence
at the end of each run (τ_50, docs/monitor.md).

Run: ``.venv/bin/python benchmarks/mrclam_verdict.py [--robots 1,2,3,4,5] [--out
docs/figures/mrclam_verdict.png] [--jobs 2]`` (about 45 s of one core per robot).
"""

from __future__ import annotations

import argparse
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamlens.common.config import load_settings
from slamlens.common.messages import Health
from slamlens.common.verdict import conservative
from slamlens.services.harness.monitored import monitored
from slamlens.services.harness.mrclam_pipeline import DATA, PROFILE, TRUTH_SPAN_S
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.scoring import TruthTrack
from slamlens.services.slam.settings import EstimatorSettings

REPO = Path(__file__).resolve().parents[1]
SERIES = ("nis_window_mean", "nis_window_lo", "nis_window_hi", "nees_pose_window_mean",
          "nees_pose_window_lo", "nees_pose_window_hi")


@dataclass
class Timeline:
    """One robot's Healths, reduced to what the figure and the counts need."""

    robot: int
    t: list[float] = field(default_factory=list)  #: s from the run's start
    series: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in SERIES})
    verdicts: list[str] = field(default_factory=list)
    conservative: list[bool] = field(default_factory=list)  #: "ok", a timid NIS standing
    truth: list[bool] = field(default_factory=list)  #: the dataset has a truth there
    #: a Health the target refuses: a fault, or "tuning" with no NEES window standing
    refused: list[bool] = field(default_factory=list)
    nis_tau: float = 1.0  #: the NIS band's τ at the end of the run

    def add(self, t: float, health: Health, truth: bool) -> None:
        self.t.append(t)
        self.truth.append(truth)
        for key in SERIES:
            self.series[key].append(health.statistics.get(key, np.nan))
        self.verdicts.append(health.verdict)
        self.conservative.append(conservative(health))
        nees = any(v.kind == "nees" for v in health.standing)
        self.refused.append(health.verdict == "fault"
                            or (health.verdict == "tuning" and not nees))
        self.nis_tau = health.statistics.get("nis_tau", self.nis_tau)


def timeline(robot: int) -> Timeline:
    """The shipped profile on ``robot``, every state checked (module docstring)."""
    run = load_mrclam(DATA, robot, robot_name=f"robot{robot}")
    est = Estimator(load_settings(EstimatorSettings, PROFILE, {"robot": f"robot{robot}"}))
    track = TruthTrack.from_mrclam(run)
    out = Timeline(robot)
    for message, _report, health in monitored(est, Monitor(MonitorSettings()),
                                               run.events(truth=True)):
        out.add(message.stamp - run.t0, health,
                track.covers(message.stamp, before_s=TRUTH_SPAN_S))
    return out


def not_ok(line: Timeline) -> int:
    """Healths not "ok" (the target: none)."""
    return sum(v != "ok" for v in line.verdicts)


def not_ok_with_truth(line: Timeline) -> int:
    """Healths not "ok" where the dataset has a ground truth."""
    return sum(v != "ok" and t for v, t in zip(line.verdicts, line.truth, strict=True))


def summary(line: Timeline) -> str:
    verdicts = Counter(line.verdicts)
    timid_ok = sum(line.conservative)
    no_truth = len(line.truth) - sum(line.truth)
    return (f"robot {line.robot}: {len(line.verdicts)} Healths: "
            + ", ".join(f"{k} {n}" for k, n in sorted(verdicts.items()))
            + f" ({not_ok(line)} not 'ok', {not_ok_with_truth(line)} of them where the "
              f"dataset has a truth; {no_truth} Healths where it has none)"
            + f"; a NIS window below its band standing under 'ok' in {timid_ok} "
              f"({timid_ok / max(1, len(line.verdicts)):.1%}); {sum(line.refused)} refused "
              f"by the target (a fault, or 'tuning' with no NEES window standing); NIS τ_50 "
              f"at the end {line.nis_tau:.2f}")


def title(line: Timeline) -> str:
    verdicts = ", ".join(f"{k} {n}" for k, n in sorted(Counter(line.verdicts).items()))
    share = sum(line.conservative) / max(1, len(line.verdicts))
    return (f"MRCLAM dataset 6, robot {line.robot}, deploy/mrclam.toml: {verdicts} "
            f"({not_ok(line)} not 'ok'); a timid NIS "
            f"under 'ok' in {share:.1%}")


def draw(lines: list[Timeline], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(lines), 1, figsize=(10, 2.4 * len(lines)), squeeze=False)
    for ax, line in zip(axes[:, 0], lines, strict=True):
        t = np.asarray(line.t)
        s = {k: np.asarray(v) for k, v in line.series.items()}
        for name, colour, label in (("nis", "tab:blue", "NIS"),
                                    ("nees_pose", "tab:orange", "pose NEES")):
            ax.semilogy(t, s[f"{name}_window_mean"], color=colour, lw=0.8,
                        label=f"{label}: window mean")
            ax.fill_between(t, s[f"{name}_window_lo"], s[f"{name}_window_hi"], color=colour,
                            alpha=0.10, lw=0, label=f"{label}: its band")
        xaxis = ax.get_xaxis_transform()
        verdict = np.asarray(line.verdicts)
        ax.fill_between(t, 0, 1, where=np.asarray(line.conservative), transform=xaxis,
                        color="tab:green", alpha=0.3, lw=0, step="post",
                        label="'ok' with a NIS window below its band standing")
        ax.fill_between(t, 0, 1, where=verdict != "ok", transform=xaxis, color="tab:red",
                        alpha=0.25, lw=0, step="post", label="'tuning' or 'fault'")
        ax.fill_between(t, 0, 0.06, where=~np.asarray(line.truth), transform=xaxis,
                        color="0.3", alpha=0.6, lw=0, step="post",
                        label="no ground truth in the dataset")
        ax.set_title(title(line), fontsize=8)
        ax.set_ylabel("window mean")
        ax.set_xlim(0, t[-1] if t.size else 1)
        ax.set_ylim(1e-2, 60)  # the pose NEES band reaches 1.5e-4: its floor is off the axis
    axes[-1, 0].set_xlabel("s from the start of the run")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", fontsize=7, ncol=3)
    fig.tight_layout(rect=(0, 0.6 / fig.get_figheight(), 1, 1))  # 0.6 in for the legend
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--out", default=str(REPO / "docs" / "figures" / "mrclam_verdict.png"))
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    robots = [int(r) for r in args.robots.split(",")]
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        lines = list(pool.map(timeline, robots))
    for line in lines:
        print(summary(line), flush=True)
    draw(lines, Path(args.out))
    print(f"wrote {args.out}")
    return 0 if not any(any(line.refused) for line in lines) else 1


if __name__ == "__main__":
    raise SystemExit(main())
