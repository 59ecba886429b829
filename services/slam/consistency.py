"""Monte-Carlo consistency of the estimator on a simulated world (NEES of the robot pose).

For each seed the simulator's events are applied to a fresh :class:`Estimator` in order,
and after every event the robot pose error e = (x − x̂, y − ŷ, wrap(θ − θ̂)) is scored by
NEES = eᵀ P_vv⁻¹ e against the truth at that stamp. Over M seeds the mean NEES times M is
χ²(3M)-distributed for a consistent filter, which gives the two-sided band used by the
tests and the plot in ``docs/consistency.md`` (Bar-Shalom, Li & Kirubarajan, §5.4).

Also used by the tests of the covariance theorem: :func:`run` can collect every state. It
scores any filter that applies the simulator's inputs and says its pose (:class:`PoseFilter`,
e.g. the dense invariant EKF of services/harness/dense_inekf.py), the Estimator by default.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy import stats

from slamlens.common.errors import ConfigError
from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Observations, Odometry, SlamState, Truth
from slamlens.services.slam.ekf import RefusedStepError
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.observe_report import ObserveReport
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.sim import Simulator
from slamlens.services.slam.world import World


class PoseFilter(Protocol):
    """What :func:`run` scores: a filter fed the simulator's inputs that says its pose."""

    @property
    def pose(self) -> np.ndarray: ...

    @property
    def pose_covariance(self) -> np.ndarray: ...

    def apply(self, message: Odometry | Observations) -> object: ...


@dataclass(frozen=True)
class Run:
    """One seed's run: NEES after every event (NaN while P_vv is singular)."""

    stamps: np.ndarray  #: float64[T], s
    steps: tuple[str, ...]  #: "predict" / "update" per event
    nees: np.ndarray  #: float64[T]
    states: tuple[SlamState, ...]  #: every state, when collected (else empty)
    #: inputs the filter's guard refused (skipped, as the estimator service skips them)
    refused: int = 0

    def nees_run(self) -> tuple[np.ndarray, np.ndarray]:
        return self.stamps, self.nees


def world_settings(world: World, *, linearisation: str = "standard",
                   update_iterations: int = 1) -> EstimatorSettings:
    """The estimator settings whose noise is exactly the world's (a consistent filter)."""
    return EstimatorSettings(
        sigma_v=world.noise.sigma_v, sigma_w=world.noise.sigma_w,
        sigma_range=world.noise.sigma_range, sigma_bearing=world.noise.sigma_bearing,
        linearisation=linearisation, update_iterations=update_iterations)


def run(world: World, *, seed: int, settings: EstimatorSettings | None = None,
        loops: int | None = None, anonymous: bool = False,
        collect_states: bool = False,
        make: Callable[[EstimatorSettings], PoseFilter] = Estimator) -> Run:
    """Apply one seeded simulation to a fresh filter (``make(settings)``, the Estimator by
    default); score the pose after each event. Collecting states needs the Estimator."""
    settings = settings or world_settings(world)
    sim = Simulator(world, seed=seed, loops=loops, anonymous=anonymous)
    est = make(settings)
    #: the filter whose states are collected (the Estimator's, when asked for)
    keeper = est if collect_states and isinstance(est, Estimator) else None
    if collect_states and keeper is None:
        raise ConfigError("only the Estimator makes states to collect")
    truth_pose: dict[float, np.ndarray] = {}
    stamps: list[float] = []
    steps: list[str] = []
    nees: list[float] = []
    states: list[SlamState] = []
    seq = refused = 0
    pending: list[tuple[str, float]] = []
    if keeper is not None:
        states.append(keeper.to_state(seq=0, stamp=0.0, step="init"))

    def score(step: str, stamp: float) -> None:
        e = truth_pose[stamp] - est.pose
        e[2] = wrap_angle(e[2])
        Pvv = est.pose_covariance  # the 3x3 block, without building the full matrix
        try:
            value = float(e @ np.linalg.solve(Pvv, e))
        except np.linalg.LinAlgError:
            value = math.nan
        stamps.append(stamp)
        steps.append(step)
        nees.append(value if np.linalg.cond(Pvv) < 1e12 else math.nan)

    for event in sim.events():
        if isinstance(event, Truth):
            truth_pose[event.stamp] = np.array(event.pose)
            for step, stamp in pending:  # the odometry of this stamp came just before
                score(step, stamp)
            pending.clear()
            continue
        seq += 1
        report: ObserveReport | None = None
        step = "predict" if isinstance(event, Odometry) else "update"
        try:
            if keeper is None:
                est.apply(event)
            else:
                report = keeper.apply(event)
        except RefusedStepError:  # the service counts it and goes on: so does the run
            refused += 1
        if keeper is not None:
            states.append(keeper.to_state(seq=seq, stamp=event.stamp, step=step,
                                          report=report))
        if event.stamp in truth_pose:
            score(step, event.stamp)
        else:
            pending.append((step, event.stamp))
    return Run(np.array(stamps), tuple(steps), np.array(nees), tuple(states), refused)


@dataclass(frozen=True)
class MonteCarlo:
    """Mean NEES over seeds, per event, with its χ² band."""

    stamps: np.ndarray
    mean_nees: np.ndarray
    lower: float
    upper: float
    seeds: int
    dof: int = 3

    @property
    def inside(self) -> np.ndarray:
        ok = np.isfinite(self.mean_nees)
        return ok & (self.mean_nees >= self.lower) & (self.mean_nees <= self.upper)

    @property
    def fraction_inside(self) -> float:
        finite = np.isfinite(self.mean_nees)
        return float(np.mean(self.inside[finite]))

    @property
    def time_average(self) -> float:
        return float(np.nanmean(self.mean_nees))


def monte_carlo(world: World, seeds: Iterable[int], *, loops: int | None = None,
                confidence: float = 0.95, linearisation: str = "standard",
                update_iterations: int = 1) -> MonteCarlo:
    """Average NEES over ``seeds``; the band is the two-sided ``confidence`` χ²(3M)/M band."""
    settings = world_settings(world, linearisation=linearisation,
                              update_iterations=update_iterations)
    return combine([run(world, seed=s, loops=loops, settings=settings).nees_run()
                    for s in seeds], confidence=confidence)


def combine(runs: Sequence[tuple[np.ndarray, np.ndarray]], *,
            confidence: float = 0.95) -> MonteCarlo:
    """The Monte-Carlo mean of runs given as (stamps, NEES) of the same world and length
    (the shortest decides), with its χ²(3M)/M band."""
    M = len(runs)
    length = min(len(nees) for _, nees in runs)
    mean = np.mean(np.stack([nees[:length] for _, nees in runs]), axis=0)
    alpha = 1.0 - confidence
    lower = float(stats.chi2.ppf(alpha / 2, 3 * M) / M)
    upper = float(stats.chi2.ppf(1 - alpha / 2, 3 * M) / M)
    return MonteCarlo(runs[0][0][:length], mean, lower, upper, M)
