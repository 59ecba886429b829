"""Regenerate the Monte-Carlo NEES figures of docs/consistency.md.

* ``docs/figures/nees.png``: the standard filter on the paper scenario's default run;
* ``docs/figures/nees_linearisation.png`` (``--compare``): standard, FEJ, OC, and OC with
  the iterated update (``--linearisation fej|oc``, ``--update-iterations 10``,
  docs/estimator.md) on the paper scenario (3 loops and 15) and a
  long run of the large world (1000 landmarks, its 2 loops), each over ``--seeds`` seeds,
  with the χ² band; and the table of docs/consistency.md ("Linearisation"), printed;
* ``docs/figures/nees_invariant.png`` (``--compare --filters invariant --output …``): the
  invariant EKF (``--linearisation invariant``) on the same runs (10.5 min on 2 cores).

Run: ``.venv/bin/python docs/make_consistency_plot.py [--seeds 20]`` or ``… --compare
[--seeds 50] [--large-seeds 50] [--processes 2] [--cache DIR]`` (about 90 min on 2 cores,
most of it the large world's 150 runs; the runs are cached in DIR, so a second call only
draws).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.services.slam.consistency import (  # noqa: E402
    MonteCarlo,
    combine,
    monte_carlo,
    run,
    world_settings,
)
from slamlens.services.slam.world import load_world  # noqa: E402

#: (label, world, loops) of the comparison
CASES = (("paper, 3 loops (54 s)", "paper", 3), ("paper, 15 loops (272 s)", "paper", 15),
         ("large, 2 loops (880 s, n = 1000)", "large", 2))
#: the filters compared: a linearisation, "+iterated" with the iterated update
#: (``update_iterations`` = :data:`ITERATIONS`, docs/estimator.md)
LINEARISATIONS = ("standard", "fej", "oc", "oc+iterated", "invariant")
COLOURS = dict(zip(LINEARISATIONS, ("tab:red", "tab:blue", "tab:purple", "tab:orange",
                                    "tab:brown"), strict=True))
ITERATIONS = 10
#: the mean leaves the band "for good" when it stays out this many events in a row
OUT_RUN = 50


def one(args: tuple[str, int, int, str]) -> tuple[np.ndarray, np.ndarray]:
    world_name, loops, seed, linearisation = args
    import logging

    logging.disable(logging.WARNING)  # a diverging filter refuses updates by the thousand
    world = load_world(world_name)
    base, _, iterated = linearisation.partition("+")
    settings = world_settings(world, linearisation=base,
                              update_iterations=ITERATIONS if iterated else 1)
    r = run(world, seed=seed, loops=loops, settings=settings)
    return r.stamps, r.nees


def runs_of(world: str, loops: int, linearisation: str, seeds: int, processes: int,
            cache: Path | None, cached_only: bool = False
            ) -> tuple[MonteCarlo, list[tuple[np.ndarray, np.ndarray]]]:
    """The runs of seeds 0 … seeds−1, each kept in ``cache`` as it finishes (a second call,
    or one cut short and started again, computes only the seeds it lacks; with
    ``cached_only`` it computes none and uses the seeds the cache holds)."""
    def path(seed: int) -> Path | None:
        return None if cache is None else cache / f"{world}-{loops}-{linearisation}-{seed}.npz"

    runs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    todo = []
    for seed in range(seeds):
        p = path(seed)
        if p is not None and p.exists():
            data = np.load(p)
            runs[seed] = (data["stamps"], data["nees"])
        elif not cached_only:
            todo.append(seed)
    with ProcessPoolExecutor(processes) as pool:
        futures = {pool.submit(one, (world, loops, seed, linearisation)): seed
                   for seed in todo}
        for future in as_completed(futures):
            seed = futures[future]
            runs[seed] = future.result()
            p = path(seed)
            if p is not None:
                np.savez(p, stamps=runs[seed][0], nees=runs[seed][1])
    kept = [runs[s] for s in sorted(runs)]
    return combine(kept), kept


def non_finite_seeds(runs: list[tuple[np.ndarray, np.ndarray]]) -> int:
    """Seeds whose NEES became non-finite after the first second (P_vv no longer
    invertible: the filter broke down)."""
    return sum(bool(np.any(~np.isfinite(nees) & (stamps > 1.0))) for stamps, nees in runs)


def first_out(mc: MonteCarlo, run_length: int = OUT_RUN) -> float | None:
    """The stamp from which the mean NEES stays outside the band for ``run_length`` events
    in a row (None: it never does)."""
    out = ~mc.inside  # (NaN and ∞ are outside)
    streak = 0
    for k, o in enumerate(out.tolist()):
        streak = streak + 1 if o else 0
        if streak == run_length:
            return float(mc.stamps[k - run_length + 1])
    return None


def fifths(mc: MonteCarlo) -> list[float]:
    q = len(mc.mean_nees) // 5
    return [float(np.nanmean(mc.mean_nees[i * q:(i + 1) * q])) for i in range(5)]


def compare(seeds: int, processes: int, cache: Path | None, output: Path,
            large_seeds: int | None = None, cached_only: bool = False,
            filters: tuple[str, ...] = LINEARISATIONS) -> None:
    fig, axes = plt.subplots(len(CASES), 1, figsize=(9, 3.3 * len(CASES)), dpi=100)
    print("| run | linearisation | seeds (non-finite) | events inside the band | time average "
          "| mean per fifth of the run | leaves the band for good (≥ 50 events) at |")
    print("|---|---|---|---|---|---|---|")
    for ax, (label, world, loops) in zip(axes, CASES, strict=True):
        n = large_seeds if world == "large" and large_seeds else seeds
        band = None
        for linearisation in filters:
            colour = COLOURS[linearisation]
            mc, kept = runs_of(world, loops, linearisation, n, processes, cache, cached_only)
            band = (mc.lower, mc.upper)
            shown = np.clip(mc.mean_nees, 1e-2, 1e6)
            ax.semilogy(mc.stamps, shown, lw=0.7, color=colour,
                        label=f"{linearisation} ({mc.seeds} seeds): "
                              f"{100 * mc.fraction_inside:.0f} % inside")
            out = first_out(mc)
            where = "never" if out is None else f"{out:.1f} s"
            print(f"| {label} | {linearisation} | {mc.seeds} ({non_finite_seeds(kept)}) | "
                  f"{100 * mc.fraction_inside:.1f} % | "
                  f"{_fmt(float(np.nanmean(mc.mean_nees)))} | "
                  f"{', '.join(_fmt(v) for v in fifths(mc))} | {where} |", flush=True)
        assert band is not None
        ax.axhspan(*band, color="tab:green", alpha=0.18,
                   label=f"95 % χ² band [{band[0]:.2f}, {band[1]:.2f}] (last line's seeds)")
        ax.axhline(3.0, color="k", lw=0.6, ls=":")
        ax.set_title(f"{label}: mean robot-pose NEES over the seeds", fontsize=10)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("NEES (log)")
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(output)
    print(f"wrote {output}")


def _fmt(v: float) -> str:
    if not math.isfinite(v):
        return "∞"
    return f"{v:.3g}" if v < 1e4 else f"{v:.1e}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=None,
                        help="seeds per run (20; 50 with --compare)")
    parser.add_argument("--compare", action="store_true",
                        help="standard, FEJ, OC and OC iterated: nees_linearisation.png and "
                             "the table")
    parser.add_argument("--processes", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--cache", default="", metavar="DIR",
                        help="keep the runs of --compare here (and reuse them)")
    parser.add_argument("--large-seeds", type=int, default=None,
                        help="--compare: seeds of the large world's run (default: --seeds; "
                             "a run there costs about a minute of one core)")
    parser.add_argument("--cached-only", action="store_true",
                        help="--compare: draw from the runs --cache holds, computing none "
                             "(each row says how many seeds it has)")
    parser.add_argument("--filters", default=",".join(LINEARISATIONS[:4]),
                        help="--compare: the filters drawn, of "
                             f"{', '.join(LINEARISATIONS)} (docs/figures/nees_invariant.png: "
                             "--filters invariant)")
    parser.add_argument("--output", default="")
    args = parser.parse_args()
    filters = tuple(f for f in args.filters.split(",") if f)
    unknown = [f for f in filters if f not in LINEARISATIONS]
    if unknown or not filters:
        parser.error(f"--filters: {unknown or 'none'}; choose from {', '.join(LINEARISATIONS)}")
    figures = REPO / "docs" / "figures"
    if args.compare:
        cache = Path(args.cache) if args.cache else None
        if cache is not None:
            cache.mkdir(parents=True, exist_ok=True)
        compare(args.seeds or 50, args.processes, cache,
                Path(args.output or figures / "nees_linearisation.png"), args.large_seeds,
                args.cached_only, filters)
        return
    output = args.output or str(figures / "nees.png")
    mc = monte_carlo(load_world("paper"), range(args.seeds or 20))
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
    fig.savefig(output)
    print(f"wrote {output}: {100 * mc.fraction_inside:.1f} % inside, "
          f"time average {mc.time_average:.3f}")


if __name__ == "__main__":
    main()
