"""An independent EKF-SLAM, written from docs/estimator.md ("What it does", the models)
alone: dense state, dense (3+2n)² Jacobians, the textbook formulas. The estimator under
test must end where this ends, to 1e-9.

    predict:  x' = x + v·dt·cos θ,  y' = y + v·dt·sin θ,  θ' = wrap(θ + ω·dt)
              P ← F P Fᵀ + G M Gᵀ,  M = diag(σv², σω²)
    update:   h = (√q, atan2(dy, dx) − θ),  ν = z − h (bearing wrapped),
              S = H P Hᵀ + R,  K = P Hᵀ S⁻¹,  x ← x + K ν,  P ← P − K S Kᵀ (symmetrised)
    new:      m = (x + r cos α, y + r sin α), α = θ + φ; P grows by the augmentation
              Jacobian J = [[I, 0], [Gv, 0]] and Gz R Gzᵀ
θ is wrapped to [-π, π) after every step; a batch is applied one observation at a time, a
known id updates, an unknown id is initialised (and not also used to update).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def wrap(angle: float) -> float:
    """An angle in [-π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class DenseEkf:
    sigma_v: float
    sigma_w: float
    sigma_range: float
    sigma_bearing: float
    x: np.ndarray = field(default_factory=lambda: np.zeros(3))
    P: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    ids: list[int] = field(default_factory=list)
    steps: int = 0  #: inputs applied (the state's seq)

    @property
    def R(self) -> np.ndarray:
        return np.diag([self.sigma_range ** 2, self.sigma_bearing ** 2])

    def predict(self, v: float, w: float, dt: float) -> None:
        N = self.x.size
        th = self.x[2]
        F = np.eye(N)
        F[0, 2] = -v * dt * math.sin(th)
        F[1, 2] = v * dt * math.cos(th)
        G = np.zeros((N, 2))
        G[0, 0] = dt * math.cos(th)
        G[1, 0] = dt * math.sin(th)
        G[2, 1] = dt
        M = np.diag([self.sigma_v ** 2, self.sigma_w ** 2])
        self.x[0] += v * dt * math.cos(th)
        self.x[1] += v * dt * math.sin(th)
        self.x[2] = wrap(th + w * dt)
        self.P = F @ self.P @ F.T + G @ M @ G.T
        self.steps += 1

    def observe(self, ids: list[int], ranges: list[float], bearings: list[float]) -> None:
        for lid, r, b in zip(ids, ranges, bearings, strict=True):
            if lid in self.ids:
                self._update(self.ids.index(lid), r, b)
            else:
                self._initialise(lid, r, b)
        self.steps += 1

    def _update(self, j: int, r: float, b: float) -> None:
        N = self.x.size
        i = 3 + 2 * j
        dx, dy = self.x[i] - self.x[0], self.x[i + 1] - self.x[1]
        q = dx * dx + dy * dy
        sq = math.sqrt(q)
        H = np.zeros((2, N))
        H[:, 0:3] = [[-dx / sq, -dy / sq, 0.0], [dy / q, -dx / q, -1.0]]
        H[:, i:i + 2] = [[dx / sq, dy / sq], [-dy / q, dx / q]]
        nu = np.array([r - sq, wrap(b - (math.atan2(dy, dx) - self.x[2]))])
        S = H @ self.P @ H.T + self.R
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ nu
        self.x[2] = wrap(self.x[2])
        P = self.P - K @ S @ K.T
        self.P = (P + P.T) / 2.0

    def _initialise(self, lid: int, r: float, b: float) -> None:
        N = self.x.size
        a = self.x[2] + b
        c, s = math.cos(a), math.sin(a)
        Gv = np.array([[1.0, 0.0, -r * s], [0.0, 1.0, r * c]])
        Gz = np.array([[c, -r * s], [s, r * c]])
        J = np.zeros((N + 2, N))
        J[:N, :N] = np.eye(N)
        J[N:, 0:3] = Gv
        Q = np.zeros((N + 2, N + 2))
        Q[N:, N:] = Gz @ self.R @ Gz.T
        self.P = J @ self.P @ J.T + Q
        self.x = np.concatenate([self.x, [self.x[0] + r * c, self.x[1] + r * s]])
        self.ids.append(lid)

    # -- as a state --------------------------------------------------------------------
    @property
    def pose(self) -> np.ndarray:
        return self.x[0:3]

    @property
    def landmarks(self) -> np.ndarray:
        return self.x[3:].reshape(-1, 2)


def assert_state_equals(state: dict, ekf: DenseEkf, tol: float = 1e-9) -> None:
    """The estimator's state (decoded SlamState fields) is the oracle's, to ``tol``; the
    failure names every difference."""
    wrong = []
    if int(state["seq"]) != ekf.steps:
        wrong.append(f"seq {state['seq']}, the oracle applied {ekf.steps} inputs")
    ids = [int(i) for i in state["landmark_ids"]]
    if ids != ekf.ids:
        wrong.append(f"landmark ids {ids}, the oracle's {ekf.ids}")
    pose = np.asarray(state["pose"], dtype=float)
    dpose = np.abs(pose - ekf.pose)
    dpose[2] = abs(wrap(float(pose[2] - ekf.pose[2])))
    if not dpose.max() <= tol:
        wrong.append(f"pose {pose} vs the oracle's {ekf.pose}: {dpose.max():.3g} apart")
    if ids == ekf.ids:
        dmap = float(np.max(np.abs(state["landmarks"] - ekf.landmarks), initial=0.0))
        if not dmap <= tol:
            wrong.append(f"landmarks up to {dmap:.3g} m from the oracle's")
        dcov = float(np.max(np.abs(state["covariance"] - ekf.P)))
        if not dcov <= tol:
            wrong.append(f"covariance up to {dcov:.3g} from the oracle's")
    assert not wrong, "the final state is not the oracle's: " + "; ".join(wrong)
