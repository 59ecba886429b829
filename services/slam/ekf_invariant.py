"""The invariant EKF's update (``slamlens estimator --linearisation invariant``; Barrau &
Bonnabel, "An EKF-SLAM algorithm with consistency properties", 2015), in the standard
error the rest of the estimator keeps (docs/estimator.md, "The invariant EKF").

The invariant filter takes the state X = (θ, p, ℓ₁ … ℓₙ) as an element of SE_{1+n}(2) with
the right-invariant error X = exp(ξ)·X̂. To first order the standard error δ = x − x̂ is
δ = T(x̂)·ξ, T = I + c eθᵀ, c = (Ω p̂, 0, Ω ℓ̂₁, …), Ω = [[0, −1], [1, 0]]. Written in δ
(P = T P_ξ Tᵀ) its predict, its H and its new-landmark rows are the standard EKF's at the
latest estimates; an update differs in two steps after the standard one (x̂⁻ → x̂⁻ + Kν,
P → P − K S Kᵀ):

* the mean moves by the group's exponential, X̂⁺ = exp(T(x̂⁻)⁻¹ Kν)·X̂⁻: with α = (Kν)_θ
  every translation t̂ → R(α) t̂ + V(α)(Δt − α Ω t̂) and θ̂ → θ̂ + α (O(n));
* P → J P Jᵀ, J = T(x̂⁺) T(x̂⁻)⁻¹ = I + u eθᵀ, u = Ω(x̂⁺ − x̂⁻) on each translation and
  0 on θ — the covariance carried to the error at the new estimate. With the downdate
  folded in: P → P − V Vᵀ + u wᵀ + w uᵀ, w = P'eθ + (P'_θθ/2) u (P' = P − V Vᵀ), one
  symmetric rank-2k pass over P (:func:`~slamlens.services.slam.ekf_storage.rank2k_lower`,
  k = 3), the standard update's O(n²).

In ξ no update gains information along global translation and rotation about the origin
(H N = 0 at any estimate): at the estimates, N(x̂) = T N_ξ, the directions stay
unobservable without first estimates. A state of this filter says so in its diagnostics
(``linearisation.invariant``); the monitor then checks its theorems in ξ
(docs/monitor.md). No I/O.
"""

from __future__ import annotations

import math

import numpy as np

from slamlens.services.slam import ekf
from slamlens.services.slam.ekf_storage import rank2k_lower, robot_columns
from slamlens.services.slam.models import wrap as _wrap


def update(x: np.ndarray, L: np.ndarray, n: int, j: int, *, z_range: float,
           z_bearing: float, var_range: float, var_bearing: float, ws: ekf.Workspace,
           gate: float = 0.0, guard: ekf.Guard | None = None
           ) -> tuple[float, float, float, float, float]:
    """The invariant update with one observation of landmark ``j``, in place (module
    docstring); what :func:`ekf.update` returns and raises, and, like it, nothing written
    when it raises. Downdates held back by earlier updates are applied first."""
    N = 3 + 2 * n
    ekf.flush(L, N, ws)
    prior = x[:N].copy()
    out = ekf.update(x, L, n, j, z_range=z_range, z_bearing=z_bearing, var_range=var_range,
                     var_bearing=var_bearing, ws=ws, gate=gate, guard=guard, defer=True)
    vt = ws.pending[0:2, :N]  # the standard update's V ᵀ, its downdate held back
    u = retract(x, prior, N)
    at, bt = _factors(L, N, ws, vt, u)
    if guard is not None:
        try:
            _check(L, N, x, vt, at[0], bt[0], j)
        except ekf.RefusedStepError:
            x[:N] = prior
            ws.deferred = 0
            raise
    rank2k_lower(L, at, bt, N, args=ws.syrk)
    ws.deferred = 0
    return out


def retract(x: np.ndarray, prior: np.ndarray, N: int) -> np.ndarray:
    """x[:N] (= x̂⁻ + Kν on entry, ``prior`` = x̂⁻) becomes exp(T(x̂⁻)⁻¹ Kν)·x̂⁻; returns
    u = Ω(x̂⁺ − x̂⁻) on each translation, 0 on θ (J's column)."""
    alpha = _wrap(float(x[2]) - float(prior[2]))
    c, s = math.cos(alpha), math.sin(alpha)
    if abs(alpha) < 1e-9:  # V(α) = [[s/α, −(1−c)/α], [(1−c)/α, s/α]] → I
        v0, v1 = 1.0 - alpha * alpha / 6.0, 0.5 * alpha
    else:
        v0, v1 = s / alpha, (1.0 - c) / alpha
    u = np.zeros(N)
    # the robot's translation (scalars), then every landmark's (strided views)
    for tx, ty, nx_, ny_, ux, uy in (
            (float(prior[0]), float(prior[1]), x[0:1], x[1:2], u[0:1], u[1:2]),
            (prior[3:N:2], prior[4:N:2], x[3:N:2], x[4:N:2], u[3:N:2], u[4:N:2])):
        ex = nx_ - tx + alpha * ty  # ξ_t = Δt − α Ω t̂
        ey = ny_ - ty - alpha * tx
        nx = c * tx - s * ty + v0 * ex - v1 * ey
        ny = s * tx + c * ty + v1 * ex + v0 * ey
        ux[...] = ty - ny
        uy[...] = nx - tx
        nx_[...] = nx
        ny_[...] = ny
    x[2] = _wrap(float(prior[2]) + alpha)
    return u


def _factors(L: np.ndarray, N: int, ws: ekf.Workspace, vt: np.ndarray,
             u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A, B (as rows) with J (P − V Vᵀ) Jᵀ = P + A Bᵀ + B Aᵀ (module docstring): A = [u,
    −v₁/2, −v₂/2], B = [w, v₁, v₂], w = P′eθ + (P′_θθ/2) u, P′ = P − V Vᵀ."""
    robot_columns(L, N, ws.cols)  # row θ of P is ws.cols[2]
    p = ws.cols[2, :N] - vt[:, 2] @ vt  # P′ eθ
    at = np.empty((3, N))
    bt = np.empty((3, N))
    at[0] = u
    np.multiply(vt, -0.5, out=at[1:3])
    np.multiply(u, 0.5 * float(p[2]), out=bt[0])
    bt[0] += p
    bt[1:3] = vt
    return at, bt


@np.errstate(over="ignore", invalid="ignore")
def _check(L: np.ndarray, N: int, x: np.ndarray, vt: np.ndarray, u: np.ndarray,
           w: np.ndarray, j: int) -> None:
    """The guard (:class:`ekf.Guard`) on what the steps after the standard update write:
    the state and the new variances, diag(P′) + 2 u∘w, finite (J P′ Jᵀ is a congruence
    with det J = 1, so no variance goes negative but by rounding, and each covariance is
    bounded by its two variances)."""
    if not float(np.abs(x[:N]).max()) <= ekf.STATE_LIMIT:
        raise ekf.RefusedStepError("non-finite", f"update of landmark {j} would make the "
                                                 "state non-finite")
    diag = np.diagonal(L)[:N] - (vt * vt).sum(axis=0) + 2.0 * u * w
    if not float(np.abs(diag).max()) <= ekf.COVARIANCE_LIMIT:
        raise ekf.RefusedStepError("non-finite", f"update of landmark {j} would make P "
                                                 "non-finite")
