"""Leave-one-robot-out figures for ``slamlens tune``, and the choice of a profile by them.

A profile fitted on some robots is judged on a robot it was not fitted on: for each robot
of the dataset, the whole fit (residuals, then the NEES scale: :func:`tuning.tune`) is made
on the others and the estimator with that profile is scored on the one left out — pose NEES
(time average and 100-state windows) and landmark RMSE after a rigid fit
(:mod:`slamlens.services.slam.scoring`). Each *candidate* (a linearisation, a motion
model and what the NEES scale multiplies) is cross-validated so; the one chosen is the one
whose held-out robots meet the targets most often (NEES in [1, 6], landmark RMSE after a
rigid fit ≤ 0.10 m), ties broken by the mean |ln(NEES / 3)| of the held-out robots. The
profile shipped is then fitted on all the robots with the chosen candidate; its
leave-one-out figures are what a lab can expect on a robot it has not fitted
(docs/estimator.md, "Tuning").

No I/O besides reading the dataset.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace

from slamlens.common.errors import ConfigError
from slamlens.services.slam.mrclam import MrclamRun
from slamlens.services.slam.scoring import (
    NEES_WINDOW,
    POSE_DOF,
    Evaluation,
    Progress,
    evaluate_all,
    event_count,
)
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.tuning import TuneResult, settings_with, tune

#: what a held-out robot must show (docs/estimator.md)
NEES_RANGE = (1.0, 6.0)
RIGID_RMSE_MAX = 0.10  #: m

#: ``progress(what, pass_number, scale, events)``: a callable told the events of that pass
#: as they go (of ``events`` in all), or None; pass 0 scores the robot left out
FoldProgress = Callable[[str, int, float, int], Progress | None]


@dataclass(frozen=True)
class Candidate:
    """One way to fit a profile."""

    linearisation: str  #: standard or fej (EstimatorSettings.linearisation)
    motion_model: str = "spec"  #: spec or distance (tuning.fit_noise)
    update_iterations: int = 1  #: EstimatorSettings.update_iterations (1 = the EKF)
    scale: str = "motion"  #: what the NEES scale multiplies: motion or all (tuning.tune)

    @property
    def estimator(self) -> str:
        """The estimator it fits for, e.g. "oc" or "oc, iterated (K = 10)"."""
        if self.update_iterations > 1:
            return f"{self.linearisation}, iterated (K = {self.update_iterations})"
        return self.linearisation

    @property
    def label(self) -> str:
        return f"{self.estimator}, {self.motion_model} motion model, {self.scale} σ scaled"


@dataclass
class Fold:
    """One robot left out: the profile fitted on the others, and its figures there."""

    held_out: str  #: robot name
    result: TuneResult  #: fitted on the other robots (its ``after``: in-sample figures)
    test: Evaluation  #: the held-out robot with that profile


def meets(e: Evaluation) -> bool:
    """The targets for a robot a profile was not fitted on."""
    return (NEES_RANGE[0] <= e.nees_mean <= NEES_RANGE[1]
            and e.landmark_rmse_rigid <= RIGID_RMSE_MAX)


@dataclass
class CrossValidation:
    """A candidate's leave-one-robot-out folds."""

    candidate: Candidate
    folds: list[Fold]

    @property
    def held_out(self) -> list[Evaluation]:
        return [f.test for f in self.folds]

    @property
    def meeting(self) -> int:
        """Held-out robots that meet the targets."""
        return sum(meets(e) for e in self.held_out)

    @property
    def spread(self) -> float:
        """Mean |ln(NEES / 3)| over the held-out robots (0: every one consistent)."""
        logs = [abs(math.log(e.nees_mean / POSE_DOF)) if e.nees_mean > 0 else math.inf
                for e in self.held_out]
        return sum(logs) / len(logs) if logs else math.inf

    def rank(self) -> tuple[int, float]:
        return -self.meeting, self.spread


def cross_validate(runs: Sequence[MrclamRun], candidate: Candidate, *,
                   gate_chi2: float = 13.82, base: EstimatorSettings | None = None,
                   progress: FoldProgress | None = None,
                   executor: Executor | None = None) -> CrossValidation:
    """Leave each robot out in turn (module docstring); at least two robots."""
    if len(runs) < 2:
        raise ConfigError("leave-one-robot-out needs at least two robots")
    settings = replace(base or EstimatorSettings(), linearisation=candidate.linearisation,
                       update_iterations=candidate.update_iterations)
    events = [event_count(r) for r in runs] if progress is not None else [0] * len(runs)
    folds = []
    for k, held in enumerate(runs):
        train = [r for j, r in enumerate(runs) if j != k]
        what = f"{candidate.estimator}, {candidate.scale} σ, {held.robot} left out"
        total = sum(events) - events[k]

        def tick(number: int, scale: float, what: str = what,
                 total: int = total) -> Progress | None:
            return None if progress is None else progress(what, number, scale, total)

        result = tune(train, motion_model=candidate.motion_model, gate_chi2=gate_chi2,
                      base=settings, scaled=candidate.scale, progress=tick,
                      executor=executor)
        test = evaluate_all([held], settings_with(settings, result.values), executor=executor,
                            progress=None if progress is None else progress(
                                what, 0, result.scale, events[k]))[0]
        folds.append(Fold(held.robot, result, test))
    return CrossValidation(candidate, folds)


def choose(results: Sequence[CrossValidation]) -> CrossValidation:
    """The candidate whose held-out robots meet the targets most often (then the smallest
    spread of their NEES around 3)."""
    return min(results, key=lambda r: r.rank())


def report(results: Sequence[CrossValidation], chosen: CrossValidation) -> list[str]:
    """The leave-one-robot-out table, one line per candidate and robot, and the choice."""
    lo, hi = NEES_RANGE
    width = max(34, *(len(r.candidate.label) for r in results))
    lines = [f"leave-one-robot-out: each robot scored with the profile fitted on the others "
             f"(targets: NEES in [{lo:g}, {hi:g}], landmark RMSE after a rigid fit ≤ "
             f"{RIGID_RMSE_MAX:g} m)",
             f"{'candidate':<{width}} {'left out':>9} {'NEES':>7} {'windows':>8} {'rigid m':>8} "
             f"{'rot°':>6} {'NIS':>5} {'gated':>6} {'scale c':>8}  meets"]
    for r in results:
        for f in r.folds:
            e = f.test
            lines.append(
                f"{r.candidate.label:<{width}} {f.held_out:>9} {e.nees_mean:>7.2f} "
                f"{e.window_fraction(NEES_WINDOW):>8.0%} {e.landmark_rmse_rigid:>8.3f} "
                f"{e.map_rotation_deg:>6.1f} {e.nis_mean:>5.2f} "
                f"{e.counts.get('gated', 0):>6.0f} {f.result.scale:>8.3f}  "
                f"{'yes' if meets(e) else 'NO'}")
        lines.append(f"{r.candidate.label:<{width}} {'':>9} {r.meeting} of {len(r.folds)} meet "
                     f"the targets; mean |ln(NEES/3)| {r.spread:.2f}")
    lines.append(f"chosen: {chosen.candidate.label} ({chosen.meeting} of "
                 f"{len(chosen.folds)} held-out robots meet the targets)")
    return lines
