"""The iterated update's iteration: Gauss-Newton on one observation's MAP cost, with step
control (docs/estimator.md, "The iterated update"). Pure: five numbers in, five out.

An update with one observation z of landmark j moves the state to the minimiser of

    J(δ) = ½ δᵀ P⁻¹ δ + ½ ‖z − h(x̂ + δ)‖²_R⁻¹.

The EKF takes one Gauss-Newton step from δ = 0 (H at the prior x̂). Each step linearised at
an iterate lands on δ = P Hᵀ S⁻¹ ν = P g, with g non-zero only on the five entries h reads
(robot x, y, θ and the landmark's x, y), and so does every point between two of them. So an
iterate is known by two five-vectors: g and the five entries of P g (the ``step``, which
the update computes anyway), and J there costs O(1): ½ g·step + ½ ‖z − h(x̂ + step)‖²_R⁻¹
(the prior term δᵀ P⁻¹ δ = (P g)ᵀ P⁻¹ (P g) = gᵀ P g). The iteration relinearises at the
current point, takes the step to where that lands if J decreases, else halves it back
towards the current point until J does (damped Gauss-Newton), and stops when a
linearisation lands where it was taken (the fixed point: the MAP estimate, a stationary
point of J) or its budget is spent: the update is then the one linearised at the lowest J
found — never a point J rates worse than the prior.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: the iteration stops when a linearisation lands this close (m, rad) to where it was taken
TOLERANCE = 1e-9
#: halvings of a step that would raise the cost before the iteration gives up
MAX_HALVINGS = 30
#: a step whose cost is higher by no more than this (relative) is taken: near the fixed
#: point J's changes are rounding, and refusing them would stall the iteration there
ROUNDING = 1e-12


@dataclass(frozen=True)
class Landing:
    """Where one linearisation lands: u = L_S⁻¹ ν (the kernel's Vᵀ is that H's), and the
    five entries of the step P g and of g."""

    u0: float
    u1: float
    step: np.ndarray
    g: np.ndarray


def g_of(h0: tuple[float, float, float], h1: tuple[float, float, float],
         y0: float, y1: float) -> np.ndarray:
    """g = Hᵀ y on the five entries, H = [Hv | −Hv[:, :2]] (rows h0, h1 on the robot)."""
    return np.array([h0[0] * y0 + h1[0] * y1, h0[1] * y0 + h1[1] * y1,
                     h0[2] * y0 + h1[2] * y1, -(h0[0] * y0 + h1[0] * y1),
                     -(h0[1] * y0 + h1[1] * y1)])


def cost(step: np.ndarray, g: np.ndarray, residual: tuple[float, float], var_range: float,
         var_bearing: float) -> float:
    """J at the iterate x̂ + P g (its five entries x̂ + ``step``), with ``residual`` the
    (range, bearing) z − h there, bearing wrapped (module docstring)."""
    e_r, e_b = residual
    return 0.5 * float(g @ step) + 0.5 * (e_r * e_r / var_range + e_b * e_b / var_bearing)


def iterate(first: Landing, relinearise: Callable[[np.ndarray], Landing],
            cost_at: Callable[[np.ndarray, np.ndarray], float], iterations: int) -> Landing:
    """The landing of the last linearisation, from ``first`` (the EKF's, linearised at the
    prior), relinearising at most ``iterations`` − 1 times: at the fixed point if it was
    reached, else at the lowest-J point found (module docstring)."""
    here_step, here_g = np.zeros(5), np.zeros(5)
    here_cost = cost_at(here_step, here_g)
    landing = first
    for _ in range(iterations - 1):
        if float(np.abs(landing.step - here_step).max()) <= TOLERANCE:
            break  # the fixed point
        moved = _descend(here_step, here_g, here_cost, landing, cost_at)
        if moved is None:
            break  # no point towards the landing lowers J: linearised where it is lowest
        here_step, here_g, here_cost = moved
        landing = relinearise(here_step)
    return landing


def _descend(step: np.ndarray, g: np.ndarray, now: float, landing: Landing,
             cost_at: Callable[[np.ndarray, np.ndarray], float]
             ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The landing, or the first point halfway back towards ``step`` that does not raise
    J (beyond rounding)."""
    t = 1.0
    for _ in range(MAX_HALVINGS):
        new_step = step + t * (landing.step - step)
        new_g = g + t * (landing.g - g)
        value = cost_at(new_step, new_g)
        if value <= now + ROUNDING * max(1.0, abs(now)):  # not higher, beyond rounding
            return new_step, new_g, value
        t *= 0.5
    return None
