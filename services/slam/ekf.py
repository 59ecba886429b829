"""EKF-SLAM numerical core: the in-place kernels of the standard models (docs/estimator.md;
the models and their Jacobians as small functions: :mod:`slamlens.services.slam.models`).

The state is ``x = [x, y, θ, m1x, m1y, …]`` (N = 3 + 2n). Its covariance lives in the
lower triangle of a preallocated buffer ``L`` (:mod:`slamlens.services.slam.ekf_storage`:
the storage, :func:`symmetric` to materialise P, the BLAS ``dsyrk`` downdate).

The kernels (:func:`predict`, :func:`update`, :func:`initialise`) mutate ``x`` and ``L`` in
place: the covariance *is* the estimator's memory and a copy would cost a full pass. They
validate everything that can fail (a degenerate innovation covariance, a landmark on top of
the robot) before writing anything, so a refused call leaves the state as it was.
Dense (3+2n)² Jacobians are never built (docs/estimator.md "Cost").

**Where the Jacobians are evaluated.** By default at the latest estimates (docs/estimator.md, the
standard EKF). Each kernel also takes ``at``, the point of a First-Estimates-Jacobian EKF
(Huang, Mourikis & Roumeliotis 2010; docs/estimator.md): the robot's *propagated* position
p̂(k|k−1) and, for an update, the landmark's *first* estimate. The mean is always moved by
the models at the latest estimates; only F, H and the initialisation Jacobian change, in
the same closed forms, at the same cost. :func:`update` may iterate (``iterations``: the
iterated EKF, :mod:`slamlens.services.slam.ekf_iterated`), relinearising at its estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slamlens.common.errors import EstimationError
from slamlens.common.geometry import wrap_angle
from slamlens.services.slam import ekf_iterated
from slamlens.services.slam.ekf_storage import (
    SyrkArgs,
    downdate_lower,
    held_diagonal,
    landmark_columns,
    lower_from_symmetric,
    robot_columns,
    robot_rows_into,
    symmetric,
    symmetric_after_predict,
    turn_lower,
    turned_rows,
)
from slamlens.services.slam.models import wrap as _wrap


class SingularInnovationError(EstimationError):
    """The innovation covariance S is not positive definite (or h is undefined)."""


class RefusedStepError(EstimationError):
    """A step whose result would poison the filter: a non-finite state or covariance, or a
    variance driven below zero beyond the guard's tolerance. Nothing was written."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason  #: "non-finite" or "not-psd"

    def __reduce__(self) -> tuple[type[RefusedStepError], tuple[str, str]]:
        return type(self), (self.reason, str(self))  # picklable (a process pool's result)


class GatedObservationError(EstimationError):
    """An observation of a known landmark whose NIS is above the gate. Nothing was written;
    the innovation and S are attached for the diagnostics."""

    def __init__(self, nis: float, innovation: tuple[float, float, float, float, float]) -> None:
        super().__init__(f"NIS {nis:.3g} above the gate")
        self.nis = nis
        self.innovation = innovation  #: (ν_r, ν_φ, S_rr, S_rφ, S_φφ)


#: "Finite" for the guard: a state entry (m, rad) above this, or a covariance entry (m², …)
#: above its square, is refused — the next step multiplies such numbers and overflows.
STATE_LIMIT = 1e150
COVARIANCE_LIMIT = STATE_LIMIT * STATE_LIMIT


def _bounded(values: np.ndarray, limit: float) -> bool:
    """|every value| ≤ limit (False for NaN); two O(N) reductions, no temporary."""
    if not values.size:
        return True
    return bool(values.max() <= limit and values.min() >= -limit)


@dataclass(frozen=True)
class Guard:
    """What the kernels check before they write a step (docs/estimator.md, "A filter that
    cannot be poisoned"). Every check is O(N): the state and the entries a step writes must
    stay finite — within :data:`STATE_LIMIT` (state) and :data:`COVARIANCE_LIMIT` (P) — and,
    unless ``psd_rtol`` is None, no variance may go below −(``psd_rtol``·its old value +
    ``atol``) and the robot block stays PSD within it. ``psd_rtol = None`` keeps only the
    finiteness checks (the planted faults break PSD on purpose)."""

    psd_rtol: float | None = 1e-9
    atol: float = 1e-12


def _psd3(a00: float, a10: float, a11: float, a20: float, a21: float, a22: float,
          tol: float) -> bool:
    """Whether the symmetric 3×3 [[a00,·,·],[a10,a11,·],[a20,a21,a22]] + tol·I is PSD
    (a closed-form Cholesky; False for NaN)."""
    d0 = a00 + tol
    if not d0 > 0.0:
        return d0 == 0.0 and a10 == 0.0 and a20 == 0.0 and _psd2(a11, a21, a22, tol)
    l10, l20 = a10 / math.sqrt(d0), a20 / math.sqrt(d0)
    return _psd2(a11 - l10 * l10, a21 - l10 * l20, a22 - l20 * l20, tol)


def _psd2(a00: float, a10: float, a11: float, tol: float) -> bool:
    d0, d1 = a00 + tol, a11 + tol
    return d0 >= 0.0 and d1 >= 0.0 and d0 * d1 - a10 * a10 >= 0.0


#: updates whose downdates :func:`update` may hold back (``defer``) before it applies them
#: all at once: one pass over P for a whole batch instead of one per observation (a batch
#: of 4 at n = 1000: 2.2 ms against 5.5 ms one downdate each; benchmarks/bench_ekf.py).
MAX_DEFERRED = 8


@dataclass
class Workspace:
    """Scratch rows reused by every kernel call, so a call allocates (almost) nothing.

    ``cols`` holds five columns of the symmetric P as rows (robot x, y, θ and the two of
    one landmark); ``wt`` holds W ᵀ = (P Hᵀ)ᵀ; ``vt`` holds Vᵀ = (W L_S⁻ᵀ)ᵀ.
    """

    cols: np.ndarray  # (5, capacity)
    wt: np.ndarray  # (2, capacity)
    vt: np.ndarray  # (2, capacity)
    h5: np.ndarray  # (2, 5) the non-zero columns of H
    #: the V ᵀ rows of updates applied to x but not yet to L (:func:`update` with
    #: ``defer``; :func:`flush` applies them as one rank-2m downdate)
    pending: np.ndarray  # (2 · MAX_DEFERRED, capacity)
    #: the invariant EKF's held-back steps to the new estimates
    #: (:mod:`~slamlens.services.slam.ekf_invariant`): P = J L Jᵀ − Σ V Vᵀ with
    #: J = I + turn·eθᵀ while ``turned``; never set by the other filters
    turn: np.ndarray  # (capacity,)
    deferred: int = 0  #: rows of ``pending`` in use (2 per deferred update)
    turned: bool = False
    syrk: SyrkArgs = field(default_factory=SyrkArgs)  # one per workspace (thread)

    @classmethod
    def for_capacity(cls, capacity: int) -> Workspace:
        return cls(cols=np.zeros((5, capacity)), wt=np.zeros((2, capacity)),
                   vt=np.zeros((2, capacity)), h5=np.zeros((2, 5)),
                   pending=np.zeros((2 * MAX_DEFERRED, capacity)),
                   turn=np.zeros(capacity))

    @property
    def capacity(self) -> int:
        return int(self.cols.shape[1])


# ---------------------------------------------------------------------------------------
# kernels
# ---------------------------------------------------------------------------------------


def predict(x: np.ndarray, L: np.ndarray, n: int, *, v: float, w: float, dt: float,
            var_v: float, var_w: float, extra_qv: float = 0.0, extra_qw: float = 0.0,
            guard: Guard | None = None, ws: Workspace | None = None,
            at: tuple[float, float] | None = None) -> None:
    """docs/estimator.md prediction in place: O(n), only the robot rows/columns of P change.

    Fx's θ column is ∂(x', y')/∂θ = J·(p' − p) with p the latest position, or ``at`` (FEJ:
    the propagated position p̂(k|k−1), so that Fx carries the unobservable directions of
    step k onto those of step k + 1).

    ``var_v``, ``var_w`` are the odometry variances σv² (m²/s²), σω² (rad²/s²). ``extra_qv``
    (m²) and ``extra_qw`` (rad²) are opt-in variances added to this step's along-heading and
    heading noise (:meth:`Estimator.predict`'s distance and turn terms; 0 = the standard model).
    With a ``guard`` (and ``ws`` for scratch) the step is computed first and written only if
    it stays finite and P_vv stays PSD; else :class:`RefusedStepError`, nothing written.
    """
    N = 3 + 2 * n
    theta = float(x[2])
    c, s = math.cos(theta), math.sin(theta)
    d = v * dt
    fa, fb = -d * s, d * c  # Fx = I + fa·e0e2ᵀ + fb·e1e2ᵀ
    x0, x1, x2 = float(x[0]) + d * c, float(x[1]) + d * s, _wrap(theta + w * dt)
    if at is not None:
        fa, fb = at[1] - x1, x0 - at[0]

    p00, p10, p11 = float(L[0, 0]), float(L[1, 0]), float(L[1, 1])
    p20, p21, p22 = float(L[2, 0]), float(L[2, 1]), float(L[2, 2])
    qv, qw = var_v * dt * dt, var_w * dt * dt  # Fu M Fuᵀ = qv·(c, s, 0)(c, s, 0)ᵀ + qw·e2e2ᵀ
    qv += extra_qv
    qw += extra_qw
    n20 = p20 + fa * p22
    n21 = p21 + fb * p22
    n00 = p00 + fa * p20 + fa * n20 + qv * c * c
    n10 = p10 + fb * p20 + fa * n21 + qv * c * s
    n11 = p11 + fb * p21 + fb * n21 + qv * s * s
    n22 = p22 + qw
    if guard is not None:
        if not (max(abs(x0), abs(x1), abs(fa), abs(fb)) <= STATE_LIMIT and max(
                abs(n00), abs(n10), abs(n11), abs(n20), abs(n21), abs(n22)) <= COVARIANCE_LIMIT):
            raise RefusedStepError("non-finite", f"prediction (v={v!r}, w={w!r}, dt={dt!r}) "
                                                 "would make the pose or P_vv non-finite")
        if guard.psd_rtol is not None and not _psd3(
                n00, n10, n11, n20, n21, n22,
                guard.psd_rtol * max(n00, n11, n22) + guard.atol):
            raise RefusedStepError("not-psd", f"prediction (v={v!r}, w={w!r}, dt={dt!r}) "
                                              "would make P_vv indefinite")
    if n and guard is not None:
        # P_mv ← P_mv Fxᵀ computed into scratch and checked before it is written
        # (the same products and sums, so the same rounding, as the unguarded branch below)
        assert ws is not None, "a guarded predict needs the workspace"
        pm = L[3:N, 0:3]
        buf = ws.vt[:, :N - 3]
        np.multiply(pm[:, 2], fa, out=buf[0])
        buf[0] += pm[:, 0]
        np.multiply(pm[:, 2], fb, out=buf[1])
        buf[1] += pm[:, 1]
        if not _bounded(buf, COVARIANCE_LIMIT):
            raise RefusedStepError("non-finite", f"prediction (v={v!r}, w={w!r}, dt={dt!r}) "
                                                 "would make P_vm non-finite")
        pm[:, 0] = buf[0]
        pm[:, 1] = buf[1]
    x[0], x[1], x[2] = x0, x1, x2
    L[0:3, 0:3] = ((n00, n10, n20), (n10, n11, n21), (n20, n21, n22))
    if n and guard is None:
        # P_mv ← P_mv Fxᵀ: columns x and y gain fa, fb times column θ; one fused op each.
        pm = L[3:N, 0:3]
        theta_col = pm[:, 2]
        pm[:, 0] += fa * theta_col
        pm[:, 1] += fb * theta_col


Row = tuple[float, float, float]  #: one row of H on the robot (∂/∂x, ∂/∂y, ∂/∂θ)


def update(x: np.ndarray, L: np.ndarray, n: int, j: int, *, z_range: float,
           z_bearing: float, var_range: float, var_bearing: float,
           ws: Workspace, gate: float = 0.0, guard: Guard | None = None,
           defer: bool = False,
           at: tuple[float, float, float, float] | None = None,
           null: tuple[float, float, float, float] | None = None,
           iterations: int = 1) -> tuple[float, float, float, float, float]:
    """The update with one observation of landmark ``j`` (0-based state order), in place.

    Never builds H: it touches 5 columns of P. With W = P Hᵀ (N×2) and S = L_S L_Sᵀ
    (2×2 Cholesky, closed form), V = W L_S⁻ᵀ gives K S Kᵀ = W S⁻¹ Wᵀ = V Vᵀ and
    K ν = V (L_S⁻¹ ν): the downdate is a symmetric rank-2 dsyrk on the lower triangle.
    H is evaluated at the latest estimates, or with ``at`` = (robot x, y, landmark x, y) at
    those points (FEJ: the robot's propagated position and the landmark's first estimate);
    with ``null`` = (robot x, y, landmark x, y) it is then moved the least onto H N = 0, N
    the unobservable directions at those points (OC, :func:`_constrained`); the innovation
    ν = z − h(x̂) is always the latest estimates'. With ``iterations`` > 1 (and no ``at``)
    the update is relinearised at its own estimate up to that many times (:func:`_iterated`).

    Returns the innovation and its covariance ``(ν_r, ν_φ, S_rr, S_rφ, S_φφ)`` before the
    update. Raises :class:`SingularInnovationError` without touching the state when
    the landmark sits on the robot or S is not positive definite, and
    :class:`GatedObservationError` when ``gate`` > 0 and the NIS νᵀS⁻¹ν exceeds it. With a
    ``guard``, :class:`RefusedStepError` (nothing written) when the new state would not be
    finite or a variance would drop below zero beyond the tolerance: every P_ii − ‖V_i‖² is
    checked, O(N), before the downdate (:class:`Guard`).

    With ``defer`` the downdate of ``L`` is held back in ``ws`` (x is updated at once): the
    next updates read P through the held-back ones (5 columns and the diagonal, O(mN)), and
    :func:`flush` applies them all in one pass over P — the same sequential EKF, rounded in
    another order. Anything else that reads ``L`` must :func:`flush` first; an update
    flushes by itself when :data:`MAX_DEFERRED` are held.
    """
    N = 3 + 2 * n
    a = 3 + 2 * j
    prior = (float(x[0]), float(x[1]), float(x[2]), float(x[a]), float(x[a + 1]))
    nu_r, nu_b, h0, h1 = _innovation(prior, j, z_range, z_bearing, at)
    if null is not None:
        h0, h1 = _constrained(h0, null), _constrained(h1, null)
    s00, s01, s11, (i00, i10, i11) = _gain(L, N, a, ws, h0, h1, var_range, var_bearing, j)
    u0, u1 = i00 * nu_r, i10 * nu_r + i11 * nu_b
    if gate > 0.0:
        nis = u0 * u0 + u1 * u1  # νᵀ S⁻¹ ν = ‖L_S⁻¹ ν‖²
        if not nis <= gate:
            raise GatedObservationError(nis, (nu_r, nu_b, s00, s01, s11))
    if iterations > 1 and at is None:  # FEJ's H does not move: nothing to iterate
        u0, u1 = _iterated((u0, u1), (h0, h1), (i00, i10, i11), iterations, prior, j,
                           (z_range, z_bearing), (var_range, var_bearing), null, L, N, ws)
    vt = ws.vt[:, :N]
    m = ws.deferred
    xs = x[:N]
    if guard is not None:
        _check_update(L, N, xs, vt, u0, u1, guard, j, ws.pending[:m],
                      ws.turn[:N] if ws.turned else None)
    else:
        xs += u0 * vt[0]
        xs += u1 * vt[1]
    x[2] = _wrap(float(x[2]))
    if m == 0 and not defer:
        downdate_lower(L, ws.vt, N, args=ws.syrk)
        return nu_r, nu_b, s00, s01, s11
    ws.pending[m:m + 2, :N] = vt
    ws.deferred = m + 2
    if not defer or ws.deferred >= ws.pending.shape[0]:
        flush(L, N, ws)
    return nu_r, nu_b, s00, s01, s11


def _innovation(point: tuple[float, float, float, float, float], j: int, z_range: float,
                z_bearing: float, at: tuple[float, float, float, float] | None
                ) -> tuple[float, float, Row, Row]:
    """(ν_r, ν_φ) at ``point`` = (robot x, y, θ, landmark x, y) and H's robot rows h0, h1
    (range, bearing), each (∂/∂x, ∂/∂y, ∂/∂θ): H = [Hv | Hm] on columns (x, y, θ, mx, my)
    with Hm = −Hv[:, :2], Hv = [[−ux, −uy, 0], [gy, −gx, −1]], evaluated at ``point`` or at
    ``at``."""
    x0, x1, theta, mx, my = point
    dx, dy = mx - x0, my - x1
    q = dx * dx + dy * dy
    if not q > 0.0 or not math.isfinite(q):
        raise SingularInnovationError(f"landmark {j} is at the robot's position: h undefined")
    r = math.sqrt(q)
    nu_r = z_range - r
    nu_b = _wrap(z_bearing - (math.atan2(dy, dx) - theta))
    if at is not None:  # FEJ: H at the first estimate, seen from the propagated position
        dx, dy = at[2] - at[0], at[3] - at[1]
        q = dx * dx + dy * dy
        if not q > 0.0 or not math.isfinite(q):
            raise SingularInnovationError(f"landmark {j}'s first estimate is at the robot's "
                                          "propagated position: H undefined")
        r = math.sqrt(q)
    return nu_r, nu_b, (-dx / r, -dy / r, 0.0), (dy / q, -dx / q, -1.0)


def _gain(L: np.ndarray, N: int, a: int, ws: Workspace, h0: Row, h1: Row, var_range: float,
          var_bearing: float, j: int
          ) -> tuple[float, float, float, tuple[float, float, float]]:
    """S = H P Hᵀ + R (s00, s01, s11), L_S⁻¹ = [[i00, 0], [i10, i11]] (the last three) and
    Vᵀ = (W L_S⁻ᵀ)ᵀ = L_S⁻¹ H P in ``ws.vt``."""
    wt = _gain_rows(L, N, a, ws, h0, h1)
    w0x, w0y, w0t = float(wt[0, 0]), float(wt[0, 1]), float(wt[0, 2])
    w0m, w0n = float(wt[0, a]), float(wt[0, a + 1])
    w1x, w1y, w1t = float(wt[1, 0]), float(wt[1, 1]), float(wt[1, 2])
    w1m, w1n = float(wt[1, a]), float(wt[1, a + 1])
    # S = H (P Hᵀ) + R; the off-diagonal is taken from one side only: S is symmetric exactly.
    s00 = h0[0] * (w0x - w0m) + h0[1] * (w0y - w0n) + h0[2] * w0t + var_range
    s01 = h0[0] * (w1x - w1m) + h0[1] * (w1y - w1n) + h0[2] * w1t
    s11 = h1[0] * (w1x - w1m) + h1[1] * (w1y - w1n) + h1[2] * w1t + var_bearing
    i00, i10, i11 = _inverse_cholesky(s00, s01, s11, j)
    vt = ws.vt[:, :N]
    np.multiply(wt[0], i00, out=vt[0])
    np.multiply(wt[0], i10, out=vt[1])
    vt[1] += i11 * wt[1]
    return s00, s01, s11, (i00, i10, i11)


def _iterated(u: tuple[float, float], h: tuple[Row, Row],
              inv: tuple[float, float, float], iterations: int,
              prior: tuple[float, float, float, float, float], j: int, z: tuple[float, float],
              var: tuple[float, float], null: tuple[float, float, float, float] | None,
              L: np.ndarray, N: int, ws: Workspace) -> tuple[float, float]:
    """The iterated update (:mod:`~slamlens.services.slam.ekf_iterated`) from the EKF's
    ``u`` (its H rows ``h``, its L_S⁻¹ ``inv``; its Vᵀ in ``ws.vt``): the u of the last
    linearisation (at the fixed point, or the lowest J found), its Vᵀ in ``ws.vt``.
    OC (``null``): the iteration finds the MAP point with h's own Jacobians, and the
    update is then linearised there with H made blind to the unobservable directions."""
    a = 3 + 2 * j
    vt = ws.vt[:, :N]
    five = [0, 1, 2, a, a + 1]

    def landing(u0: float, u1: float, h0: Row, h1: Row,
                i: tuple[float, float, float]) -> ekf_iterated.Landing:
        y0, y1 = i[0] * u0 + i[1] * u1, i[2] * u1  # y = S⁻¹ν = L_S⁻ᵀ u
        return ekf_iterated.Landing(u0, u1, u0 * vt[0, five] + u1 * vt[1, five],
                                    ekf_iterated.g_of(h0, h1, y0, y1))

    def residual(step: np.ndarray) -> tuple[float, float, Row, Row]:  # z − h there, and H
        x0, x1, th, mx, my = (p + float(d) for p, d in zip(prior, step, strict=True))
        return _innovation((x0, x1, th, mx, my), j, z[0], z[1], None)

    def relinearise(step: np.ndarray, constrain: bool = False) -> ekf_iterated.Landing:
        nu_r, nu_b, h0, h1 = residual(step)
        if constrain and null is not None:
            h0, h1 = _constrained(h0, null), _constrained(h1, null)
        dx, dy = float(step[0] - step[3]), float(step[1] - step[4])
        nu_r += h0[0] * dx + h0[1] * dy + h0[2] * float(step[2])  # carried back to x̂:
        nu_b += h1[0] * dx + h1[1] * dy + h1[2] * float(step[2])  # ν = z − h(xᵢ) + H(xᵢ − x̂)
        *_, i = _gain(L, N, a, ws, h0, h1, var[0], var[1], j)
        return landing(i[0] * nu_r, i[1] * nu_r + i[2] * nu_b, h0, h1, i)

    def cost_at(step: np.ndarray, g: np.ndarray) -> float:
        return ekf_iterated.cost(step, g, residual(step)[:2], var[0], var[1])

    first = landing(u[0], u[1], h[0], h[1], inv) if null is None else relinearise(np.zeros(5))
    out = ekf_iterated.iterate(first, relinearise, cost_at, iterations)
    if null is not None:  # OC: the update linearised at the MAP point, H made blind there
        out = relinearise(out.step, constrain=True)
    return out.u0, out.u1


def _constrained(h: Row, null: tuple[float, float, float, float]) -> Row:
    """OC-EKF: the row of H nearest to ``h`` (Frobenius) with h N = 0, N the unobservable
    directions at ``null`` = (robot x, y, landmark x, y). h = [a, b, c, −a, −b] is already
    blind to translation; what remains is the rotation u' = [Dy/2, −Dx/2, 1, −Dy/2, Dx/2]
    (D = landmark − robot) made orthogonal to translation: h* = h − (h·u'/u'·u') u'."""
    dx, dy = null[2] - null[0], null[3] - null[1]
    alpha = (h[2] + h[0] * dy - h[1] * dx) / (1.0 + 0.5 * (dx * dx + dy * dy))
    return h[0] - 0.5 * alpha * dy, h[1] + 0.5 * alpha * dx, h[2] - alpha


def _gain_rows(L: np.ndarray, N: int, a: int, ws: Workspace, h0: Row, h1: Row) -> np.ndarray:
    """Wᵀ = H P (2×N, in ``ws.wt``) from the five columns of P that H touches (through the
    downdates held back in ``ws``: P = L − Σ V Vᵀ)."""
    cols = ws.cols
    robot_columns(L, N, cols)
    landmark_columns(L, N, a, cols[3:5])
    if ws.turned:  # the invariant EKF's held-back J: the five columns of J L Jᵀ
        turned_rows(cols[:, :N], ws.turn[:N], (0, 1, 2, a, a + 1))
    m = ws.deferred
    if m:  # P = L − Σ V Vᵀ of the held-back updates: its five columns
        held = ws.pending[:m]
        cols[:, :N] -= held[:, [0, 1, 2, a, a + 1]].T @ held[:, :N]
    h5 = ws.h5
    # H = [Hv | Hm] on columns (x, y, θ, mx, my); Hm = −Hv[:, :2].
    h5[0, 0], h5[0, 1], h5[0, 2], h5[0, 3], h5[0, 4] = h0[0], h0[1], h0[2], -h0[0], -h0[1]
    h5[1, 0], h5[1, 1], h5[1, 2], h5[1, 3], h5[1, 4] = h1[0], h1[1], h1[2], -h1[0], -h1[1]
    wt = ws.wt[:, :N]
    np.matmul(h5, cols[:, :N], out=wt)  # Wᵀ = H P (2×N)
    return wt


def _inverse_cholesky(s00: float, s01: float, s11: float,
                      j: int) -> tuple[float, float, float]:
    """L_S⁻¹ = [[i00, 0], [i10, i11]] of S = [[s00, s01], [s01, s11]] (closed form, no
    np.linalg on 2×2); :class:`SingularInnovationError` if S is not positive definite."""
    if not (s00 > 0.0 and math.isfinite(s00) and math.isfinite(s01) and math.isfinite(s11)):
        raise SingularInnovationError(f"innovation covariance of landmark {j} is not "
                                      f"positive definite (S_rr = {s00!r})")
    l00 = math.sqrt(s00)
    l10 = s01 / l00
    schur = s11 - l10 * l10
    if not schur > 1e-300:
        raise SingularInnovationError(f"innovation covariance of landmark {j} is not "
                                      f"positive definite (det S ≤ 0)")
    l11 = math.sqrt(schur)
    i00, i11 = 1.0 / l00, 1.0 / l11
    return i00, -l10 * i00 * i11, i11


def flush(L: np.ndarray, N: int, ws: Workspace) -> None:
    """Apply the downdates :func:`update` held back in ``ws`` (``defer``): one dsyrk of
    rank 2m on the lower triangle — with the invariant EKF's held-back J
    (``ws.turned``), L ← J L Jᵀ − Σ V Vᵀ as one rank-2k dsyr2k
    (:mod:`~slamlens.services.slam.ekf_invariant`). After it, ``L`` is the state's P
    again."""
    if ws.turned:
        turn_lower(L, ws.turn[:N], ws.pending[:ws.deferred], N, args=ws.syrk)
        ws.turn[:N] = 0.0
        ws.turned = False
        ws.deferred = 0
    elif ws.deferred:
        downdate_lower(L, ws.pending[:ws.deferred], N, args=ws.syrk)
        ws.deferred = 0


# a step absurd enough overflows in here: the checks see ∞ or NaN and refuse it, so numpy
# need not warn (the decorator costs 0.4 µs a call)
@np.errstate(over="ignore", invalid="ignore")
def _check_update(L: np.ndarray, N: int, xs: np.ndarray, vt: np.ndarray, u0: float,
                  u1: float, guard: Guard, j: int, held: np.ndarray,
                  turn: np.ndarray | None = None) -> None:
    """The guarded half of :func:`update`: checks the step (O(N), :class:`Guard`) and
    applies the state change x += V u; raises before writing anything.

    Few numpy calls (each costs about a microsecond whatever N): ≈ 10 µs at small N and
    6–8 % of the update at n = 1000 (benchmarks/bench_ekf.py)."""
    sq = (vt * vt).sum(axis=0)  # ‖V_i‖² = what the downdate takes from P_ii
    if guard.psd_rtol is None:
        if not float(sq.max()) <= COVARIANCE_LIMIT:  # V bounded, so V Vᵀ is (and not NaN)
            raise RefusedStepError("non-finite", f"update of landmark {j} would make P "
                                                 "non-finite")
    else:
        # ‖V_i‖² ≤ (1 + rtol)·P_ii + atol: no variance goes negative; it also bounds V (P_ii
        # ≤ COVARIANCE_LIMIT) and refuses NaN, so no separate finiteness test is needed
        diag = held_diagonal(L, N, held, turn)  # P_ii through the held-back steps
        excess = sq - diag * (1.0 + guard.psd_rtol)
        worst = float(excess.max())
        if not worst <= guard.atol:
            if not math.isfinite(worst):
                raise RefusedStepError("non-finite", f"update of landmark {j} would make P "
                                                     "non-finite")
            i = int(excess.argmax())
            raise RefusedStepError("not-psd", f"update of landmark {j} would make variance "
                                              f"{i} of P negative (by {worst:.3g})")
    # x + V u, with the rounding of the unguarded ``xs += u0·V₀; xs += u1·V₁``
    new = xs + u0 * vt[0]
    new += u1 * vt[1]
    if not _bounded(new, STATE_LIMIT):
        raise RefusedStepError("non-finite", f"update of landmark {j} would make the state "
                                             "non-finite")
    xs[...] = new


def initialise(x: np.ndarray, L: np.ndarray, n: int, *, z_range: float, z_bearing: float,
               var_range: float, var_bearing: float, ws: Workspace,
               guard: Guard | None = None, at: tuple[float, float] | None = None) -> None:
    """Append landmark n from (range, bearing) in place: rows N, N+1 of L, entries of x.

    The caller guarantees capacity (``L`` and ``x`` at least N + 2 long). Cross terms with
    the whole state are P_new,x = Gv P_v,x, which are row writes in lower storage: O(n).
    Gv's θ column is J·(m − p) with p the robot's latest position, or ``at`` (FEJ: its
    propagated position, so that the new landmark's rows of the unobservable directions
    are Gv times the robot's: docs/estimator.md).
    With a ``guard``, :class:`RefusedStepError` when the new rows or the landmark are not
    finite or its 2×2 block is not PSD; the rows written lie outside the state (n is the
    caller's), so a refusal leaves the state as it was.
    """
    N = 3 + 2 * n
    alpha = float(x[2]) + z_bearing
    c, s = math.cos(alpha), math.sin(alpha)
    g02, g12 = -z_range * s, z_range * c  # Gv = [[1, 0, g02], [0, 1, g12]]
    mx, my = float(x[0]) + z_range * c, float(x[1]) + z_range * s
    if at is not None:
        g02, g12 = at[1] - my, mx - at[0]
    rob = ws.cols[0:3]
    robot_columns(L, N, rob)
    new = L[N:N + 2, 0:N]
    # a landmark far enough away overflows these products: the guard below refuses it
    # (without one the caller asked for unchecked arithmetic), so numpy need not warn
    with np.errstate(over="ignore", invalid="ignore"):
        np.multiply(rob[2, :N], g02, out=new[0])
        new[0] += rob[0, :N]
        np.multiply(rob[2, :N], g12, out=new[1])
        new[1] += rob[1, :N]
    # Pmm = (Gv Pvv) Gvᵀ + Gz R Gzᵀ; (Gv Pvv) are the first three entries of the new rows.
    a0, a2 = float(new[0, 0]), float(new[0, 2])
    b0, b1, b2 = float(new[1, 0]), float(new[1, 1]), float(new[1, 2])
    rr, rb = var_range, var_bearing * z_range * z_range  # Gz R Gzᵀ = rr·ccᵀ + rb·ppᵀ
    m00 = a0 + a2 * g02 + rr * c * c + rb * s * s
    m10 = b0 + b2 * g02 + rr * c * s - rb * s * c
    m11 = b1 + b2 * g12 + rr * s * s + rb * c * c
    if guard is not None:
        if not (_bounded(new[:, :N], COVARIANCE_LIMIT)
                and max(abs(m00), abs(m10), abs(m11)) <= COVARIANCE_LIMIT
                and max(abs(mx), abs(my)) <= STATE_LIMIT):
            raise RefusedStepError("non-finite", f"a landmark at range {z_range!r} would make "
                                                 "the state non-finite")
        if guard.psd_rtol is not None and not _psd2(
                m00, m10, m11, guard.psd_rtol * max(m00, m11) + guard.atol):
            raise RefusedStepError("not-psd", f"a landmark at range {z_range!r} would have "
                                              "an indefinite covariance")
    L[N:N + 2, N:N + 2] = ((m00, m10), (m10, m11))
    x[N] = mx
    x[N + 1] = my


__all__ = [
    "GatedObservationError", "Guard", "RefusedStepError", "SingularInnovationError",
    "MAX_DEFERRED", "SyrkArgs", "Workspace", "downdate_lower", "flush",
    "initialise", "lower_from_symmetric", "predict",
    "robot_rows_into", "symmetric", "symmetric_after_predict", "update", "wrap_angle",
]
