"""The monitor's check of the unobservable directions (docs/monitor.md, "Spurious
information in an unobservable direction").

Range-bearing SLAM cannot observe where the whole picture — robot and map together — sits
in the map frame: a global translation (x, y) and a rotation about the origin change no
measurement. A filter whose linearised system keeps those three directions unobservable
(FEJ, docs/estimator.md) never *gains* information in them: with N(k) the directions at the
filter's linearisation points, the 3×3 information I(k) = N(k)ᵀ P(k)⁻¹ N(k) is
non-increasing in the Loewner order from state to state (updates add nothing along N,
predictions only add noise, a new landmark appends a Schur complement). The standard EKF's
Jacobians break that, and I grows at its updates: the spurious information that makes it
overconfident in the map's heading.

The invariant EKF (``linearisation.invariant``) keeps them unobservable at its latest
estimates (:mod:`~slamlens.services.monitor.invariant`): N is taken at the state's own.
For FEJ the monitor rebuilds N from the states alone, as FEJ chooses it: the robot row at the pose
of the last *predict* (or init) state, each landmark's row at its estimate in the first
state that has it; so it needs every state from the one where a landmark appeared (it
says when it cannot: ``unobservable_unknown``). I is computed from the Cholesky factor of
sym(P) + tol·I that the PSD screen makes anyway, refined against P itself until the
correction is negligible: O(N²) per state, no factorisation of its own.

Pure: arrays in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg
from scipy.linalg import lapack

from slamlens.common.messages import SlamState, Violation

#: refinement steps at most, and the relative size of the last correction that says the
#: information is determined (else P is too close to singular along N: skipped, like NEES)
REFINE_STEPS = 6
REFINE_RTOL = 1e-10
#: the diagnostics keys by which an estimator says it linearises at first estimates, and
#: that it is the invariant EKF (:mod:`~slamlens.services.monitor.invariant`)
FEJ_FLAG = "linearisation.fej"
INVARIANT_FLAG = "linearisation.invariant"


def declares_fej(state: SlamState) -> bool:
    return _declares(state, FEJ_FLAG)


def declares_invariant(state: SlamState) -> bool:
    return _declares(state, INVARIANT_FLAG)


def _declares(state: SlamState, flag: str) -> bool:
    return bool(state.diagnostics and state.diagnostics.get(flag, 0.0) == 1.0)


def null_space(robot_xy: np.ndarray, first: np.ndarray) -> np.ndarray:
    """N [(3+2n), 3]: global x, global y and the rotation about the map origin, at the
    robot point ``robot_xy`` and the landmark points ``first`` [n, 2] (state order)."""
    n = first.shape[0]
    out = np.zeros((3 + 2 * n, 3))
    out[0, 0] = out[1, 1] = out[2, 2] = 1.0
    out[0, 2], out[1, 2] = -robot_xy[1], robot_xy[0]
    if n:
        out[3::2, 0] = 1.0
        out[4::2, 1] = 1.0
        out[3::2, 2] = -first[:, 1]
        out[4::2, 2] = first[:, 0]
    return out


def information(P: np.ndarray, factor: np.ndarray, N: np.ndarray) -> np.ndarray | None:
    """Nᵀ P⁻¹ N from ``factor``, the lower Cholesky factor of sym(P) + tol·I: the solve is
    refined against sym(P) (each step O(N²); it converges by tol/(λ + tol) a step); None
    when it does not converge (P singular or nearly so along N). LAPACK's ``dpotrs`` on the
    factor's transpose (Fortran order as it lies: no copy), sym(P)·y as two products
    (no symmetric copy of P)."""
    upper = factor.T  # Lᵀ, the upper factor of the same matrix
    y, info = lapack.dpotrs(upper, N, lower=0)
    for _ in range(REFINE_STEPS):
        if info != 0:
            return None
        step, info = lapack.dpotrs(upper, N - 0.5 * (P @ y + P.T @ y), lower=0)
        y += step
        size, scale = float(np.abs(step).max()), float(np.abs(y).max())
        if not (math.isfinite(size) and math.isfinite(scale)):
            return None
        if size <= REFINE_RTOL * scale:
            out = N.T @ y
            return 0.5 * (out + out.T)
    return None


def relative_growth(before: np.ndarray, after: np.ndarray) -> float:
    """max over directions c of cᵀ·after·c / cᵀ·before·c − 1: how much the information
    grew in the direction where it grew most, as a fraction (≤ 0: it did not grow)."""
    try:
        w = linalg.eigh(after, before, eigvals_only=True, check_finite=False)
    except (linalg.LinAlgError, ValueError):
        return math.nan
    return float(w[-1]) - 1.0


def heading_sd_deg(info: np.ndarray) -> float:
    """σ of the global rotation given the map's shape (from I⁻¹), degrees."""
    try:
        var = float(np.linalg.inv(info)[2, 2])
    except np.linalg.LinAlgError:
        return math.nan
    return math.degrees(math.sqrt(var)) if var > 0 else math.nan


class RobotPoint:
    """p̂(k|k−1) as the states show it: the pose of the last predict (or init) state,
    known while every state since was received."""

    def __init__(self) -> None:
        self.seq: int | None = None  #: of the last state seen
        self.xy: np.ndarray | None = None

    def copy(self) -> RobotPoint:
        out = RobotPoint()
        out.seq, out.xy = self.seq, self.xy
        return out

    def contiguous(self, state: SlamState) -> bool:
        return self.seq is not None and state.seq in (self.seq, self.seq + 1)

    def before(self, state: SlamState) -> np.ndarray | None:
        """The point ``state``'s own predict linearised at (None if unknown)."""
        return self.xy if self.contiguous(state) else None

    def advance(self, state: SlamState) -> None:
        if state.step in ("predict", "init"):
            self.xy = np.array(state.pose[:2], dtype=float)
        elif not self.contiguous(state):
            self.xy = None
        self.seq = state.seq


def predict_points(robot: RobotPoint, prevs: list[SlamState | None],
                   run: list[SlamState]) -> list[np.ndarray | None]:
    """For each state of ``run`` (each after ``prevs[k]``, ``robot`` standing at
    ``prevs[0]``): the position its prediction's Fx is measured from — the previous state's
    for the standard EKF, the robot point for FEJ (``linearisation.fej``); None where that
    is unknown (FEJ after a gap)."""
    tracker = robot.copy()
    out: list[np.ndarray | None] = []
    for p, x in zip(prevs, run, strict=True):
        if declares_fej(x):
            out.append(tracker.before(x))
        else:
            out.append(None if p is None else np.asarray(p.pose[:2], dtype=float))
        tracker.advance(x)
    return out


@dataclass
class Finding:
    """What :meth:`UnobservableCheck.step` found for one state."""

    growth: float | None = None  #: relative growth since ``since`` (None: not compared)
    since: int | None = None  #: seq of the state compared with
    sd_before: float = math.nan  #: σ of the global heading then, degrees
    sd_now: float = math.nan
    statistics: dict[str, float] = field(default_factory=dict)

    def violation(self, state: SlamState, *, rtol: float, theorem: bool) -> Violation | None:
        """The violation, if the information grew beyond ``rtol`` and the monitor holds
        the estimator to the theorem (FEJ says it keeps the directions unobservable, or
        ``check_unobservable = always``); else None (the growth stays a statistic)."""
        if not theorem or self.growth is None or not self.growth > rtol:
            return None
        return Violation(
            kind="unobservable", ids=(), step=state.seq, value=self.growth, bound=rtol,
            phase=state.step,
            detail=f"information in the unobservable directions grew by {self.growth:.3g} "
                   f"(×{1 + self.growth:.4g}) since seq {self.since}: the map's global "
                   f"heading σ {self.sd_before:.3g}° → {self.sd_now:.3g}° with its shape "
                   f"given")


class UnobservableCheck:
    """The information in the unobservable directions along one run (module docstring)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.robot = RobotPoint()
        self._first: dict[int, tuple[float, float]] = {}
        self._unknown: set[int] = set()  #: landmarks first seen after a gap
        self._last: tuple[int, np.ndarray] | None = None  #: (seq, I) last determined

    def advance(self, state: SlamState) -> None:
        """Follow the linearisation points through ``state`` (every state, in order)."""
        contiguous = self.robot.contiguous(state) or (self.robot.seq is None
                                                      and state.step == "init")
        for lid, xy in zip(state.landmark_ids.tolist(), state.landmarks.tolist(),
                           strict=True):
            if lid not in self._first and lid not in self._unknown:
                if contiguous:
                    self._first[lid] = (float(xy[0]), float(xy[1]))
                else:
                    self._unknown.add(lid)
        self.robot.advance(state)

    def step(self, state: SlamState, factor: np.ndarray | None) -> Finding:
        """I of ``state`` (after :meth:`advance`) against the last state where it was
        determined; ``factor`` is the PSD screen's Cholesky factor (None: P not PD)."""
        out = Finding()
        ids = state.landmark_ids.tolist()
        invariant = declares_invariant(state)
        unknown = 0 if invariant else sum(1 for i in ids if i in self._unknown)
        if unknown:
            out.statistics["unobservable_unknown"] = float(unknown)
        # a state whose I cannot be had is skipped, not a break of the chain: I is
        # non-increasing along every state, so the next one compares with the last known
        if invariant:  # N at the state's own estimates (invariant.py)
            points = null_space(np.asarray(state.pose[:2], dtype=float), state.landmarks)
        elif factor is None or unknown or self.robot.xy is None:
            return out
        else:
            first = np.array([self._first[i] for i in ids], dtype=float).reshape(-1, 2)
            points = null_space(self.robot.xy, first)
        if factor is None:
            return out
        info = information(state.covariance, factor, points)
        if info is None:
            return out
        out.sd_now = heading_sd_deg(info)
        if math.isfinite(out.sd_now):
            out.statistics["unobservable_heading_sd_deg"] = out.sd_now
        if self._last is not None:
            out.since, before = self._last
            out.growth = relative_growth(before, info)
            out.sd_before = heading_sd_deg(before)
            if math.isfinite(out.growth):
                out.statistics["unobservable_growth"] = out.growth
        self._last = (state.seq, info)
        return out
