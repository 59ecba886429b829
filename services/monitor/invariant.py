"""The covariance theorems for the invariant EKF (docs/monitor.md, "The invariant EKF").

A state that says ``linearisation.invariant`` in its diagnostics comes from a filter whose
error is X = exp(ξ)·X̂ on SE_{1+n}(2), published, like every state, as the covariance of
the standard error δ = T(x̂)·ξ (T = I + c eθᵀ, c = (Ω p̂, 0, Ω ℓ̂₁, …), Ω = [[0, −1],
[1, 0]]). Its theorems hold in ξ: an update never makes P_ξ grow (P_ξ⁺ = P_ξ − K S Kᵀ) and
a new landmark appends rows, whereas in δ an update carries P to the new estimate
(P → J P Jᵀ, J = T(x̂⁺)T(x̂⁻)⁻¹), which may grow a landmark's block. A prediction is the
standard EKF's in δ (P_mm untouched) but adds the turn noise to every landmark in ξ. So:

* an update right after the state before it: the growth theorems compare the two states'
  P_ξ = T⁻¹ P T⁻ᵀ, each at its own estimates;
* a prediction right after the state before it: the standard theorems, in δ;
* after a gap (states missed) the steps between are unknown and neither holds: the growth
  is not checked (``growth_unchecked``).

The unobservable directions at a state's own estimates are T N_ξ, N_ξ constant
(:mod:`~slamlens.services.monitor.unobservable`, where the flag is read). Pure: arrays in,
arrays out.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from slamlens.common.errors import MessageError
from slamlens.common.messages import SlamState
from slamlens.services.monitor.unobservable import (
    INVARIANT_FLAG,
    declares_invariant,
    null_space,
)

__all__ = ["INVARIANT_FLAG", "compared", "declares_invariant", "invariant_covariance"]


def invariant_covariance(state: SlamState) -> np.ndarray:
    """P_ξ = T⁻¹ P T⁻ᵀ at the state's estimates: T⁻¹ = I − c eθᵀ, so P_ξ = P − c pᵀ − p cᵀ
    + P_θθ c cᵀ with p = P eθ (O(N²), no matrix product). c is the rotation about the
    origin at the estimates (:func:`null_space`'s third column) without its θ entry."""
    P = state.covariance
    c = null_space(np.asarray(state.pose[:2], dtype=float), state.landmarks)[:, 2].copy()
    c[2] = 0.0
    p = 0.5 * (P[:, 2] + P[2, :])
    out = P - np.outer(c, p)
    out -= np.outer(p, c)
    out += float(P[2, 2]) * np.outer(c, c)
    return out


def compared(prev: SlamState, state: SlamState
             ) -> tuple[SlamState, SlamState] | None:
    """The two states the growth theorems compare for ``state`` (module docstring): the
    states themselves (a prediction, or not the invariant EKF), their ξ forms (an update
    right after ``prev``), or None (after a gap: not checkable)."""
    if not declares_invariant(state):
        return prev, state
    if state.seq != prev.seq + 1:
        return None
    if state.step != "update":
        return prev, state
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            return (dataclasses.replace(prev, covariance=_frozen(invariant_covariance(prev))),
                    dataclasses.replace(state,
                                        covariance=_frozen(invariant_covariance(state))))
    except MessageError:  # not finite in ξ: the standard checks on δ say what is wrong
        return prev, state


def _frozen(P: np.ndarray) -> np.ndarray:
    P.setflags(write=False)  # a message's arrays are read-only
    return P
