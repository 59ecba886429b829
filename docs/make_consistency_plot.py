"""Regenerate docs/figures/nees.png: Monte-Carlo NEES of the robot pose, paper scenario.

Run: ``.venv/bin/python docs/make_consistency_plot.py [--seeds 20]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.services.slam.consistency import monte_carlo  # noqa: E402
from slamlens.services.slam.world import load_world  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--output", default=str(REPO / "docs" / "figures" / "nees.png"))
    args = parser.parse_args()
    mc = monte_carlo(load_world("paper"), range(args.seeds))
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=110)
    ax.plot(mc.stamps, mc.mean_nees, lw=0.8, color="tab:blue",
            label=f"mean NEES over {mc.seeds} seeds")
    ax.axhline(3.0, color="k", lw=0.8, ls=":", label="expected (3 dof)")
    ax.axhspan(mc.lower, mc.upper, color="tab:green", alpha=0.15,
               label=f"95 % χ² band [{mc.lower:.2f}, {mc.upper:.2f}]")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("robot pose NEES")
    ax.set_title(f"Paper scenario, default run: {100 * mc.fraction_inside:.1f} % of events "
                 f"inside the band, time average {mc.time_average:.2f}")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_ylim(0, max(6.0, float(mc.upper) * 1.4))
    fig.tight_layout()
    fig.savefig(args.output)
    print(f"wrote {args.output}: {100 * mc.fraction_inside:.1f} % inside, "
          f"time average {mc.time_average:.3f}")


if __name__ == "__main__":
    main()
