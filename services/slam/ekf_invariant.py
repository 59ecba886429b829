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
  0 on θ — the covariance carried to the error at the new estimate.

Both are held back like the standard update's downdate (``ekf.update(defer=True)``): the
J's of a batch compose to I + U eθᵀ (U = Σu, since eθᵀu = 0), each held-back V becomes
J V = V + u V_θ (:func:`carry`), the next update reads P = J L Jᵀ − Σ V Vᵀ through them
(five columns and the diagonal, O(mN)), and :func:`ekf.flush` applies it all as one
symmetric rank-2k pass, L + U wᵀ + w Uᵀ − Σ V Vᵀ with w = L eθ + (L_θθ/2) U
(:func:`~slamlens.services.slam.ekf_storage.turn_lower`, BLAS ``dsyr2k``): one pass over
P a batch, as the standard filter's.

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
from slamlens.services.slam.ekf_storage import held_diagonal
from slamlens.services.slam.models import wrap as _wrap


def update(x: np.ndarray, L: np.ndarray, n: int, j: int, *, z_range: float,
           z_bearing: float, var_range: float, var_bearing: float, ws: ekf.Workspace,
           gate: float = 0.0, guard: ekf.Guard | None = None
           ) -> tuple[float, float, float, float, float]:
    """The invariant update with one observation of landmark ``j``, in place (module
    docstring); what :func:`ekf.update` returns and raises, and, like it, nothing written
    when it raises. Like the others' downdates, P's step to the new estimate is held back
    in ``ws`` (:func:`carry`) until :func:`ekf.flush`."""
    N = 3 + 2 * n
    if ws.deferred + 2 >= ws.pending.shape[0]:
        ekf.flush(L, N, ws)  # so that ekf.update holds this one back too
    prior = x[:N].copy()
    out = ekf.update(x, L, n, j, z_range=z_range, z_bearing=z_bearing, var_range=var_range,
                     var_bearing=var_bearing, ws=ws, gate=gate, guard=guard, defer=True)
    u = retract(x, prior, N)
    if guard is None:
        carry(ws, N, u)
        return out
    m = ws.deferred
    held, turn = ws.pending[:m, :N].copy(), ws.turn[:N].copy()
    carry(ws, N, u)
    try:
        _check(L, N, x, ws, j)
    except ekf.RefusedStepError:
        x[:N] = prior
        ws.pending[:m, :N] = held
        ws.turn[:N] = turn
        ws.turned = bool(turn.any())
        ws.deferred = m - 2  # this update's V, held back by ekf.update, dropped
        raise
    return out


def carry(ws: ekf.Workspace, N: int, u: np.ndarray) -> None:
    """Hold back P ← J P Jᵀ, J = I + u eθᵀ, with P = J₀ L J₀ᵀ − Σ V Vᵀ as ``ws`` holds it:
    the J's compose to I + (U + u) eθᵀ (eθᵀu = 0) and each held V becomes J V = V + u V_θ."""
    m = ws.deferred
    if m:
        held = ws.pending[:m, :N]
        held += np.outer(held[:, 2], u)
    ws.turn[:N] += u
    ws.turned = True


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


@np.errstate(over="ignore", invalid="ignore")
def _check(L: np.ndarray, N: int, x: np.ndarray, ws: ekf.Workspace, j: int) -> None:
    """The guard (:class:`ekf.Guard`) on what the steps after the standard update make:
    the state and P's variances, diag(J L Jᵀ − Σ V Vᵀ), finite (J P Jᵀ is a congruence
    with det J = 1, so no variance goes negative but by rounding, and each covariance is
    bounded by its two variances)."""
    if not float(np.abs(x[:N]).max()) <= ekf.STATE_LIMIT:
        raise ekf.RefusedStepError("non-finite", f"update of landmark {j} would make the "
                                                 "state non-finite")
    diag = held_diagonal(L, N, ws.pending[:ws.deferred], ws.turn[:N])
    if not float(np.abs(diag).max()) <= ekf.COVARIANCE_LIMIT:
        raise ekf.RefusedStepError("non-finite", f"update of landmark {j} would make P "
                                                 "non-finite")
