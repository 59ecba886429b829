"""A dense right-invariant EKF for 2-D range-bearing SLAM (Barrau & Bonnabel, "An EKF-SLAM
algorithm with consistency properties", 2015): the measurement of docs/consistency.md's
"The invariant EKF", not the shipped estimator.

The state X = (θ, p, l₁ … lₙ) is an element of SE_{1+n}(2) and its error is right-invariant,
X = exp(ξ)·X̂ with ξ = (ξx, ξy, ξθ, ξl₁ …) in the rows of the standard filter's state. To
first order the standard error δ = x − x̂ is

  δθ = ξθ,  δp = ξp + ξθ·Ω p̂,  δl = ξl + ξθ·Ω l̂,   Ω = [[0, −1], [1, 0]],

so δ = T(x̂)·ξ with T = I + c eθᵀ, c = (Ω p̂, 0, Ω l̂₁, …). In ξ:

* **Predict** (v, ω held for dt, the standard model): the mean as the standard filter moves
  it; F = I exactly; the speed noise enters ξp along (cos θ̂, sin θ̂)·dt, the turn noise ξθ
  by dt and every translation t by −Ω t̂′·dt (its adjoint), so P += G Q Gᵀ with G of
  n × 2 — summed over the predicts between two updates (the landmarks do not move) and
  added once before P is next read: O(1) a predict.
* **Update** of landmark j: d = l̂ⱼ − p̂; H has no θ column — range (−dᵀ, dᵀ)/r on (p, lⱼ),
  bearing (Ω d)ᵀ(−1, 1)/r² — so H·N = 0 for global translation and rotation about the
  origin (N constant in ξ) whatever the estimate; K, P as the EKF; the mean moves by
  X̂ ← exp(Kν)·X̂: every translation t ← R(α) t + V(α) δξ_t, θ ← θ + α (α = δξθ).
* **New landmark** ℓ = p + r·(cos, sin)(θ + φ): ξℓ = ξp + Gz δz (no θ term).

The pose covariance it reports is the standard one, T P Tᵀ's robot block, which the
scoring's NEES compares with the truth. Equal to the standard EKF in standard coordinates
but for two steps after each update (the mean's exponential retraction and P ← J P Jᵀ,
J = T(x̂⁺)·T(x̂⁻)⁻¹ = I + Ω(x̂⁺ − x̂⁻) eθᵀ), which is how a sparse implementation would do it
at the standard update's O(n²).
"""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam.noise_model import NoiseModel
from slamlens.services.slam.settings import EstimatorSettings

CAPACITY = 400  #: landmarks the matrices are sized for


class DenseInvariantEkf:
    """The right-invariant EKF of the module docstring over [x, y, θ, mx, my, …]."""

    def __init__(self, settings: EstimatorSettings, capacity: int = CAPACITY) -> None:
        if any(settings.initial_pose_sigma):
            raise ValueError("an uncertain initial pose is not modelled here")
        if settings.sigma_distance or settings.sigma_turn or \
                settings.sigma_heading_per_distance or settings.update_iterations > 1:
            raise ValueError("the opt-in motion terms and the iterated update are not "
                             "modelled here (the standard model's σv, σω only)")
        self.s, self.noise = settings, NoiseModel.of(settings)
        size = 3 + 2 * capacity
        self.x, self.P = np.zeros(size), np.zeros((size, size))
        self.x[:3] = settings.initial_pose
        self.n = 3
        self.index: dict[int, int] = {}  #: landmark id → first row of its block
        self.gated = 0
        # the predicts' noise not yet added to P (landmarks do not move between updates,
        # so a run of predicts adds A to the robot block, c·bᵀ across and s·b bᵀ to the map,
        # b = (l₁y, −l₁x, …): O(1) a predict, O(n²) once before P is next read)
        self._A, self._c, self._s = np.zeros((3, 3)), np.zeros(3), 0.0

    def apply(self, message: Odometry | Observations) -> list[tuple[np.ndarray, np.ndarray]]:
        """One input; the (ν, S) of the observations applied."""
        if isinstance(message, Odometry):
            self.predict(message.v, message.w, message.dt)
            return []
        return self.observe(message.ids.tolist(), message.ranges.tolist(),
                            message.bearings.tolist())

    def predict(self, v: float, w: float, dt: float) -> None:
        x, th = self.x, float(self.x[2])
        x[0] += v * dt * math.cos(th)
        x[1] += v * dt * math.sin(th)
        x[2] = float(wrap_angle(th + w * dt))
        speed = np.array([dt * math.cos(th), dt * math.sin(th), 0.0])  # the speed noise
        turn = np.array([x[1] * dt, -x[0] * dt, dt])  # the turn noise: −Ω p̂′·dt, dt …
        qv, qw = self.noise.var_v, self.noise.var_w  # … and −Ω l̂·dt on every landmark
        self._A += qv * np.outer(speed, speed) + qw * np.outer(turn, turn)
        self._c += qw * dt * turn
        self._s += qw * dt * dt

    def flush(self) -> None:
        """Add the pending predicts' noise to P (module docstring: P += G Q Gᵀ each)."""
        if not (self._s or self._A.any()):
            return
        x, P, n = self.x, self.P, self.n
        b = np.empty(n - 3)
        b[0::2], b[1::2] = x[4:n + 1:2], -x[3:n:2]
        P[:3, :3] += self._A
        cross = np.outer(self._c, b)
        P[:3, 3:n] += cross
        P[3:n, :3] += cross.T
        P[3:n, 3:n] += self._s * np.outer(b, b)
        self._A, self._c, self._s = np.zeros((3, 3)), np.zeros(3), 0.0

    def observe(self, ids: list[int], ranges: list[float],
                bearings: list[float]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Updates in message order, then the new landmarks (FEJ's and OC's order)."""
        applied: list[tuple[np.ndarray, np.ndarray]] = []
        new: list[tuple[int, float, float]] = []
        for lid, zr, zb in zip(ids, ranges, bearings, strict=True):
            if lid not in self.index:
                if all(lid != k for k, _, _ in new):
                    new.append((lid, zr, zb))
                continue
            done = self.update(lid, zr, zb)
            if done is not None:
                applied.append(done)
        for lid, zr, zb in new:
            self.initialise(lid, zr, zb)
        return applied

    def update(self, lid: int, z_range: float,
               z_bearing: float) -> tuple[np.ndarray, np.ndarray] | None:
        self.flush()
        x, P, n, a = self.x, self.P, self.n, self.index[lid]
        dx, dy = x[a] - x[0], x[a + 1] - x[1]
        q = dx * dx + dy * dy
        r = math.sqrt(q)
        nu = np.array([z_range - r, float(wrap_angle(z_bearing - (math.atan2(dy, dx) - x[2])))])
        rows = [0, 1, a, a + 1]  # H's nonzero columns (none for θ)
        H = np.array([[-dx / r, -dy / r, dx / r, dy / r],
                      [dy / q, -dx / q, -dy / q, dx / q]])
        PHt = P[:n, rows] @ H.T
        S = H @ PHt[rows] + np.diag([self.noise.range_variance(z_range, z_bearing),
                                     self.noise.var_b])
        inv_ls = np.linalg.inv(np.linalg.cholesky(S))  # S = L_S L_Sᵀ
        u = inv_ls @ nu  # ‖u‖² = νᵀ S⁻¹ ν
        gate = self.s.innovation_gate_chi2
        if gate and float(u @ u) > gate:
            self.gated += 1
            return None
        V = PHt @ inv_ls.T  # K = V L_S⁻¹, so Kν = V u and K S Kᵀ = V Vᵀ (symmetric)
        self.retract(V @ u)
        P[:n, :n] -= V @ V.T
        return nu, S

    def retract(self, d: np.ndarray) -> None:
        """X̂ ← exp(d)·X̂ on SE_{1+n}(2)."""
        x, n, al = self.x, self.n, float(d[2])
        c, s = math.cos(al), math.sin(al)
        if abs(al) < 1e-9:
            V = np.eye(2)
        else:
            V = np.array([[s / al, -(1 - c) / al], [(1 - c) / al, s / al]])
        rows = np.r_[0, np.arange(3, n, 2)]
        points = np.column_stack([x[rows], x[rows + 1]])
        steps = np.column_stack([d[rows], d[rows + 1]])
        moved = points @ np.array([[c, -s], [s, c]]).T + steps @ V.T
        x[rows], x[rows + 1] = moved[:, 0], moved[:, 1]
        x[2] = float(wrap_angle(float(x[2]) + al))

    def initialise(self, lid: int, z_range: float, z_bearing: float) -> None:
        self.flush()
        x, P, n, a = self.x, self.P, self.n, self.n
        c, s = math.cos(x[2] + z_bearing), math.sin(x[2] + z_bearing)
        x[a], x[a + 1] = x[0] + z_range * c, x[1] + z_range * s
        Gz = np.array([[c, -z_range * s], [s, z_range * c]])
        R = np.diag([self.noise.range_variance(z_range, z_bearing), self.noise.var_b])
        P[a:a + 2, :n] = P[0:2, :n]
        P[:n, a:a + 2] = P[a:a + 2, :n].T
        P[a:a + 2, a:a + 2] = P[0:2, 0:2] + Gz @ R @ Gz.T
        self.index[lid] = a
        self.n += 2

    def transform(self, rows: int | None = None) -> np.ndarray:
        """T(x̂): the standard error from the invariant one, δ = T ξ (its first ``rows``
        rows and columns: 3 = the robot's block)."""
        x, n = self.x, self.n if rows is None else rows
        T = np.eye(n)
        T[0, 2], T[1, 2] = -x[1], x[0]
        T[3:n:2, 2] = -x[4:n + 1:2]
        T[4:n:2, 2] = x[3:n:2]
        return T

    @property
    def pose(self) -> np.ndarray:
        return self.x[:3].copy()

    @property
    def pose_covariance(self) -> np.ndarray:
        """The robot block of T P Tᵀ (the standard error's covariance)."""
        T = self.transform(3)
        return T @ (self.P[:3, :3] + self._A) @ T.T

    def covariance(self) -> np.ndarray:
        """The whole standard-error covariance T P Tᵀ."""
        self.flush()
        T = self.transform()
        n = self.n
        return T @ self.P[:n, :n] @ T.T

    def landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        ids = sorted(self.index, key=lambda k: self.index[k])
        return (np.array(ids, dtype=np.int64),
                np.array([self.x[self.index[i]:self.index[i] + 2] for i in ids]).reshape(-1, 2))
