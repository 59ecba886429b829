"""An independent invariant EKF, written from docs/estimator.md ("The invariant EKF") and
docs/protocol.md (``linearisation.invariant``) alone, on top of the dense textbook EKF of
kit_ekf.py: in the standard error δ = x − x̂ an update is the textbook one followed by

    the mean by the group's exponential:  ξ = T(x̂⁻)⁻¹ (x̂⁻ + Kν − x̂⁻),  α = ξ_θ,
        every translation t ← R(α) t + V(α) ξ_t,  θ ← θ + α,
        V(α) = [[sin α, −(1 − cos α)], [1 − cos α, sin α]] / α
    P carried to the new estimate:  P ← J P Jᵀ,  J = T(x̂⁺) T(x̂⁻)⁻¹,
        T(x̂) = I + c eθᵀ,  c = (−ŷ, x̂, 0, −m̂₁ᵧ, m̂₁ₓ, …)

with dense matrices and a dense solve; a batch's new landmarks are mapped after its
updates. Its prediction and new-landmark rows are the textbook ones.
"""

from __future__ import annotations

import math

import numpy as np
from kit_ekf import DenseEkf, wrap


def transform(x: np.ndarray) -> np.ndarray:
    """T(x̂): δ = T ξ."""
    T = np.eye(x.size)
    T[0, 2], T[1, 2] = -x[1], x[0]
    T[3::2, 2], T[4::2, 2] = -x[4::2], x[3::2]
    return T


def exp_times(xi: np.ndarray, x: np.ndarray) -> np.ndarray:
    """exp(ξ)·X̂ on SE_{1+n}(2), written from the group."""
    a = float(xi[2])
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    V = np.eye(2) if abs(a) < 1e-12 else np.array(
        [[math.sin(a), -(1 - math.cos(a))], [1 - math.cos(a), math.sin(a)]]) / a
    out = x.copy()
    for t in [0, *range(3, x.size, 2)]:
        out[t:t + 2] = rot @ x[t:t + 2] + V @ xi[t:t + 2]
    out[2] = wrap(float(x[2]) + a)
    return out


class DenseInvariantEkf(DenseEkf):
    def observe(self, ids: list[int], ranges: list[float], bearings: list[float]) -> None:
        new = []
        for lid, r, b in zip(ids, ranges, bearings, strict=True):
            if lid in self.ids:
                self._update(self.ids.index(lid), r, b)
            else:
                new.append((lid, r, b))
        assert len({lid for lid, _, _ in new}) == len(new), "a new landmark seen twice"
        for lid, r, b in new:
            self._initialise(lid, r, b)
        self.steps += 1

    def _update(self, j: int, r: float, b: float) -> None:
        before = self.x.copy()
        super()._update(j, r, b)  # x̂⁻ + Kν, P − K S Kᵀ
        delta = self.x - before
        delta[2] = wrap(float(delta[2]))
        T_before = transform(before)
        self.x = exp_times(np.linalg.solve(T_before, delta), before)
        J = transform(self.x) @ np.linalg.inv(T_before)
        P = J @ self.P @ J.T
        self.P = (P + P.T) / 2.0
