"""Pure, vectorised covariance checks of the behaviour monitor (docs/monitor.md, paper §2.2).

All functions take plain arrays and return plain arrays; nothing here keeps state. State
index conventions follow docs/estimator.md: robot rows 0..2, landmark k at rows 3 + 2k, 3 + 2k + 1.

The Loewner test "A ≽ B" for 2×2 blocks is the sign of the smallest eigenvalue of
D = A − B, in closed form: λ_min = (a + c)/2 − hypot((a − c)/2, b) for D = [[a, b], [b, c]].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg
from scipy.linalg import lapack


@dataclass(frozen=True)
class Findings:
    """Entries that broke a check: indices (landmark positions or state indices), the
    amount by which each broke it and the tolerance it was held against."""

    index: np.ndarray  #: int [m] or [m, 2]
    value: np.ndarray  #: float [m]: growth (m²), residual, or excess
    bound: np.ndarray  #: float [m]: tolerance used
    checked: int = 0  #: how many entries were tested

    @property
    def count(self) -> int:
        return int(self.value.shape[0])


def _empty(width: int = 1, *, checked: int = 0) -> Findings:
    shape = (0,) if width == 1 else (0, width)
    return Findings(np.zeros(shape, dtype=np.int64), np.zeros(0), np.zeros(0), checked)


def min_eig_2x2(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue of symmetric [[a, b], [b, c]], elementwise."""
    return 0.5 * (a + c) - np.hypot(0.5 * (a - c), b)


def common_landmarks(prev_ids: np.ndarray, cur_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (in the older and newer state) of the landmarks present in both.

    Fast path for the usual case (landmarks only appended): both are ``arange(n_prev)``.
    """
    n_prev = prev_ids.shape[0]
    if n_prev <= cur_ids.shape[0] and np.array_equal(cur_ids[:n_prev], prev_ids):
        idx = np.arange(n_prev)
        return idx, idx
    _, i_prev, i_cur = np.intersect1d(prev_ids, cur_ids, assume_unique=True,
                                      return_indices=True)
    order = np.argsort(i_prev)
    return i_prev[order], i_cur[order]


def map_rows(positions: np.ndarray) -> np.ndarray:
    """State rows of the landmarks at ``positions``: [3+2k, 3+2k+1, ...]."""
    return (3 + 2 * positions[:, None] + np.arange(2)[None, :]).reshape(-1)


def map_block(P: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """P_mm restricted to the landmarks at ``positions`` (a view when they are a prefix)."""
    m = positions.shape[0]
    if m == 0:
        return np.zeros((0, 0))
    if positions[0] == 0 and positions[-1] == m - 1:
        return P[3:3 + 2 * m, 3:3 + 2 * m]
    rows = map_rows(positions)
    return P[np.ix_(rows, rows)]


def _block_parts(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(xx, yy, xy, yx) n×n views of a 2n×2n map block: xy[i, j] = M[i_x, j_y]."""
    return M[0::2, 0::2], M[1::2, 1::2], M[0::2, 1::2], M[1::2, 0::2]


def feature_growth(Pmm_prev: np.ndarray, Pmm_cur: np.ndarray, *, rtol: float,
                   atol: float, delta: np.ndarray | None = None) -> Findings:
    """Features whose own block P_ii grew: P_ii(prev) − P_ii(cur) not PSD.

    Both inputs are 2m×2m map blocks of the same landmarks in the same order; ``delta``
    is Pmm_prev − Pmm_cur if the caller has it already.
    """
    m = Pmm_prev.shape[0] // 2
    if m == 0:
        return _empty()
    xx, yy, xy, yx = _block_parts(Pmm_prev - Pmm_cur if delta is None else delta)
    a, c, b = np.diagonal(xx), np.diagonal(yy), 0.5 * (np.diagonal(xy) + np.diagonal(yx))
    lam = min_eig_2x2(a, b, c)
    d = np.abs(np.diagonal(Pmm_prev))
    tol = rtol * (d[0::2] + d[1::2]) + atol
    bad = np.flatnonzero(lam < -tol)
    return Findings(bad, -lam[bad], tol[bad], m)


def pair_growth(Pmm_prev: np.ndarray, Pmm_cur: np.ndarray, *, rtol: float,
                atol: float, delta: np.ndarray | None = None) -> Findings:
    """Pairs (i < j) whose relative covariance P_d grew in the Loewner order.

    D_ij = P_d,ij(prev) − P_d,ij(cur) is linear in P, so it is formed once from
    Δ = P_prev − P_cur for all pairs as n×n arrays (no per-pair loop, no (m,2,2) gathers).
    The tolerance of a pair is rtol·(tr P_ii + tr P_jj) + atol with the older blocks: the
    rounding of P_d = P_ii + P_jj − 2P_ij is relative to those entries, not to P_d.
    """
    m = Pmm_prev.shape[0] // 2
    if m < 2:
        return _empty(2)
    xx, yy, xy, yx = _block_parts(Pmm_prev - Pmm_cur if delta is None else delta)
    dxx, dyy = np.diagonal(xx), np.diagonal(yy)
    dxy = 0.5 * (np.diagonal(xy) + np.diagonal(yx))
    a = dxx[:, None] + dxx[None, :] - 2.0 * xx
    c = dyy[:, None] + dyy[None, :] - 2.0 * yy
    b = dxy[:, None] + dxy[None, :] - (xy + yx)
    lam = min_eig_2x2(a, b, c)
    d = np.abs(np.diagonal(Pmm_prev))
    t = d[0::2] + d[1::2]
    tol = rtol * (t[:, None] + t[None, :]) + atol
    bad_mask = lam < -tol
    np.fill_diagonal(bad_mask, False)  # i == j is P_d = 0 by definition
    rows, cols = np.nonzero(np.triu(bad_mask))
    checked = m * (m - 1) // 2
    if rows.size == 0:
        return _empty(2, checked=checked)
    return Findings(np.stack([rows, cols], axis=1), -lam[rows, cols], tol[rows, cols], checked)


def structure(P: np.ndarray, *, rtol_symmetry: float, rtol_correlation: float,
              atol: float) -> tuple[Findings, Findings]:
    """Symmetry and correlation of one covariance, sharing one pass over P.

    * asymmetry: entries a < b with |P_ab − P_ba| > rtol_symmetry·sqrt(|P_aa·P_bb|) + atol;
    * correlation: entries a < b with |sym(P)_ab| > sqrt(P_aa·P_bb)·(1 + rtol_correlation)
      + atol, i.e. |ρ| > 1; the value reported is |ρ| − 1 (a negative variance counts as
      ρ = ∞, capped to a finite number for the message).

    Both tests are symmetric in (a, b), so the common case (nothing wrong) is decided on
    the full matrix without extracting a triangle.
    """
    N = P.shape[0]
    pairs = N * (N - 1) // 2
    diag = np.diagonal(P)
    d = np.sqrt(np.abs(diag))
    scale = np.multiply.outer(d, d)  # sqrt(|P_aa·P_bb|)
    diff = np.abs(P - P.T)
    asym_bad = diff > rtol_symmetry * scale + atol
    absP = np.abs(P + P.T)
    absP *= 0.5
    dpos = np.sqrt(np.maximum(diag, 0.0))
    corr_bad = absP > np.multiply.outer(dpos, dpos) * (1.0 + rtol_correlation) + atol
    asym = _empty(2, checked=pairs)
    if asym_bad.any():
        A, B = np.nonzero(np.triu(asym_bad, k=1))
        asym = Findings(np.stack([A, B], axis=1), diff[A, B],
                        rtol_symmetry * scale[A, B] + atol, pairs)
    corr = _empty(2, checked=pairs)
    np.fill_diagonal(corr_bad, False)  # a = b is |ρ| = 1 by definition
    if corr_bad.any():
        A, B = np.nonzero(np.triu(corr_bad, k=1))
        pos = dpos[A] * dpos[B]
        with np.errstate(divide="ignore"):
            rho = np.where(pos > 0, absP[A, B] / np.maximum(pos, 1e-300), np.inf)
        corr = Findings(np.stack([A, B], axis=1), np.minimum(rho - 1.0, 1e300),
                        np.full(A.shape, rtol_correlation), pairs)
    return asym, corr


def min_eigenvalue_if_indefinite(P: np.ndarray, *, rtol: float,
                                 atol: float) -> tuple[float, float, np.ndarray] | None:
    """``(λ_min, tolerance, eigenvector)`` if P has λ_min < −tol, else ``None``.

    Cheap test first: a Cholesky factorisation of sym(P) + tol·I succeeds for every P with
    λ_min ≥ −tol (up to rounding); only when it fails is the full eigvalsh computed.
    """
    N = P.shape[0]
    if N == 0:
        return None
    S = 0.5 * (P + P.T)
    tol = rtol * float(np.max(np.abs(np.diagonal(S)))) + atol
    S_jit = S + tol * np.eye(N)
    _, info = lapack.dpotrf(S_jit, lower=True, clean=False, overwrite_a=True)
    if info == 0:
        return None
    # only the smallest eigenpair is needed (LAPACK's subset driver: cheaper than all)
    try:
        w, V = linalg.eigh(S, subset_by_index=[0, 0], check_finite=False)
    except (linalg.LinAlgError, ValueError):  # no convergence (overflowing entries)
        return -np.inf, tol, np.zeros(N)
    if not w[0] >= -tol:
        return float(w[0]), tol, V[:, 0]
    return None


def psd_factor(P: np.ndarray, *, rtol: float, atol: float) -> np.ndarray | None:
    """The lower Cholesky factor of sym(P) + tol·I that :func:`screen_alone` makes for a
    state, made the same way for one state (the same operations, so the same numbers);
    None if there is none."""
    S = P + P.T
    S *= 0.5
    tol = rtol * np.abs(np.diagonal(S)).max() + atol if S.size else atol
    if not (np.isfinite(S.sum()) and np.isfinite(tol)):
        return None
    idx = np.arange(S.shape[0])
    S[idx, idx] += tol
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None


def prediction_residuals(P_prev: np.ndarray, P_cur: np.ndarray, pose_prev: np.ndarray,
                         pose_cur: np.ndarray, pos_prev: np.ndarray, pos_cur: np.ndarray, *,
                         rtol: float, atol: float, map_unchanged: bool | None = None
                         ) -> tuple[Findings, Findings, float | None]:
    """Check one predict step without knowing the controls.

    For any odometry model whose displacement turns with the heading (the standard first-order
    model, the midpoint and the exact arc models), ∂(x', y')/∂θ = (−Δy, Δx) with (Δx, Δy)
    the change of the estimated position, so Fx = [[1,0,−Δy],[0,1,Δx],[0,0,1]] and:

    * P_mm is unchanged → ``(map_changed)`` findings: landmark positions whose rows changed;
    * P_vm = Fx·P_vm(prev) → ``(cross_wrong)`` findings: landmark positions whose columns
      mismatch (value = largest |residual| / sqrt(P_aa·P_bb) of that landmark);
    * Pvv − Fx·Pvv(prev)·Fxᵀ ≽ 0 (process noise is PSD) → ``noise_min_eig`` (the violating
      smallest eigenvalue) or ``None``.

    ``pos_prev`` / ``pos_cur`` are the positions of the common landmarks in each state;
    ``map_unchanged`` is whether their P_mm blocks are bit-equal, if the caller knows.
    """
    dx = float(pose_cur[0] - pose_prev[0])
    dy = float(pose_cur[1] - pose_prev[1])
    Fx = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
    m = pos_prev.shape[0]
    floor = atol / max(rtol, 1e-300)  # atol expressed in units of the scale below
    map_changed = cross_wrong = _empty(checked=m)
    if m:
        rows_prev, rows_cur = map_rows(pos_prev), map_rows(pos_cur)
        dm = np.abs(np.diagonal(P_prev)[rows_prev])
        if map_unchanged is None:
            map_unchanged = np.array_equal(map_block(P_prev, pos_prev),
                                           map_block(P_cur, pos_cur))
        # map block: untouched by a predict, so bit-equal in a correct filter (fast path);
        # otherwise each landmark's columns are held to rtol·sqrt(P_aa·P_bb) + atol
        if not map_unchanged:
            sq = np.sqrt(dm)
            rel = np.abs(map_block(P_cur, pos_cur) - map_block(P_prev, pos_prev))
            rel /= np.multiply.outer(sq, sq) + floor
            worst_mm = rel.reshape(2 * m, m, 2).max(axis=(0, 2))  # per landmark column
            changed = np.flatnonzero(worst_mm > rtol)
            map_changed = Findings(changed, worst_mm[changed], np.full(changed.shape, rtol), m)
        # cross-covariance: P_vm' = Fx·P_vm, residual scaled by the Cauchy-Schwarz bound
        Pvm_prev = P_prev[:3, rows_prev]
        resid = P_cur[:3, rows_cur] - Pvm_prev
        resid[0] += dy * Pvm_prev[2]  # − (Fx − I)·P_vm, written out (two rows only)
        resid[1] -= dx * Pvm_prev[2]
        np.abs(resid, out=resid)
        dv = np.maximum(np.abs(np.diagonal(P_prev)[:3]), np.abs(np.diagonal(P_cur)[:3]))
        resid /= np.sqrt(np.multiply.outer(dv, dm)) + floor
        worst_vm = resid.reshape(3, m, 2).max(axis=(0, 2))
        wrong = np.flatnonzero(worst_vm > rtol)
        if wrong.size:
            cross_wrong = Findings(wrong, worst_vm[wrong], np.full(wrong.shape, rtol), m)
    Pvv_cur = P_cur[:3, :3]
    Q = Pvv_cur - Fx @ P_prev[:3, :3] @ Fx.T
    tol_q = rtol * float(np.abs(np.diagonal(Pvv_cur)).sum()) + atol
    (a, b, c), (_, d, e), (_, _, f) = (0.5 * (Q + Q.T) + tol_q * np.eye(3)).tolist()
    # Q + tol·I positive definite (Sylvester's leading minors) ⇒ λ_min(Q) > −tol: done
    if a > 0 and a * d - b * b > 0 and a * (d * f - e * e) - b * (b * f - c * e) \
            + c * (b * e - c * d) > 0:
        return map_changed, cross_wrong, None
    lam = float(np.linalg.eigvalsh(0.5 * (Q + Q.T))[0])
    return map_changed, cross_wrong, (lam if lam < -tol_q else None)


# -- batched screens ------------------------------------------------------------------------
# A monitor that takes a burst of states checks them all at once: the tests above, as array
# operations over stacks [K, N, N] of consecutive covariances, decide for each state whether
# it is *clean* (nothing to report). Every comparison is the one the per-state test makes,
# entry for entry (elementwise arithmetic does not depend on the stack's size), so a state
# screened clean is one the per-state test finds clean; a state not screened clean goes
# through the per-state tests above, which say what is wrong. The monitor screens one state
# as a stack of one, so checking a burst and checking one by one give the same Health.


@dataclass(frozen=True)
class Screen:
    """Per state of a stack: which tests a batched pass found clean."""

    structure: np.ndarray  #: bool [K]: no asymmetric entry, no |ρ| > 1 (:func:`structure`)
    psd: np.ndarray  #: bool [K]: sym(P) + tol·I has a Cholesky factor (PSD within tol)
    #: that lower factor per state where it was made (for the unobservable-directions check,
    #: unobservable.py: O(N²) solves on it instead of a factorisation of its own)
    factors: tuple[np.ndarray | None, ...] = ()


@dataclass(frozen=True)
class PairScreen:
    """Per consecutive pair (same landmarks, same order) of two stacks."""

    unchanged: np.ndarray  #: bool [K]: P_mm bit-equal (every predict of a correct filter)
    growth: np.ndarray  #: bool [K]: no feature P_ii and no pair P_d grew (beyond tolerance)
    prediction: np.ndarray  #: bool [K]: the predict-step tests pass (where asked for)


def screen_alone(P: np.ndarray, *, rtol_symmetry: float, rtol_correlation: float,
                 rtol_psd: float, atol: float) -> Screen:
    """:func:`structure` and :func:`min_eigenvalue_if_indefinite` for a stack P [K, N, N].

    The PSD test is one batched Cholesky (numpy's LAPACK) of sym(P) + tol·I; if any matrix
    of the stack has none, or has non-finite entries, the whole stack is left to the
    per-state test (a fault that breaks PSD is rare and then costs what it did before).
    """
    K, N, _ = P.shape
    if N == 0 or K == 0:
        return Screen(np.ones(K, bool), np.ones(K, bool), (None,) * K)
    idx = np.arange(N)
    PT = P.transpose(0, 2, 1)
    diag = np.diagonal(P, axis1=1, axis2=2)
    d = np.sqrt(np.abs(diag))
    # the same operations as |P − Pᵀ| > rtol·(d_a·d_b) + atol, in two reused buffers
    value = np.subtract(P, PT)
    np.abs(value, out=value)
    bound = np.multiply(d[:, :, None], d[:, None, :])
    bound *= rtol_symmetry
    bound += atol
    bad = np.greater(value, bound)
    clean = ~bad.any(axis=(1, 2))
    S = P + PT
    S *= 0.5  # sym(P); |sym(P)| is the correlation test's 0.5·|P + Pᵀ| (0.5 is exact)
    dpos = np.sqrt(np.maximum(diag, 0.0))
    # |sym(P)| > (dpos_a·dpos_b)·(1 + rtol_correlation) + atol
    np.abs(S, out=value)
    np.multiply(dpos[:, :, None], dpos[:, None, :], out=bound)
    bound *= 1.0 + rtol_correlation
    bound += atol
    np.greater(value, bound, out=bad)
    bad[:, idx, idx] = False  # a = b is |ρ| = 1 by definition
    clean &= ~bad.any(axis=(1, 2))
    tol = rtol_psd * np.abs(np.diagonal(S, axis1=1, axis2=2)).max(axis=1) + atol
    psd = np.isfinite(S.sum(axis=(1, 2))) & np.isfinite(tol)
    factors: list[np.ndarray | None] = [None] * K
    if psd.any():
        S[:, idx, idx] += tol[:, None]
        try:
            made = np.linalg.cholesky(S[psd] if not psd.all() else S)
        except np.linalg.LinAlgError:  # some matrix of the stack has none: test each
            psd[:] = False
        else:
            for j, k in enumerate(np.flatnonzero(psd).tolist()):
                factors[k] = made[j]
    return Screen(clean, psd, tuple(factors))


def screen_pairs(P_prev: np.ndarray, P_cur: np.ndarray, pose_prev: np.ndarray,
                 pose_cur: np.ndarray, predict: np.ndarray, *, rtol_growth: float,
                 atol_growth: float, rtol_prediction: float) -> PairScreen:
    """:func:`feature_growth`, :func:`pair_growth` and :func:`prediction_residuals` for
    stacks of consecutive covariances [K, N, N] whose landmarks are the same, in the same
    order; ``predict`` [K] says where the predict-step tests apply (poses [K, 3])."""
    K, N, _ = P_cur.shape
    m = (N - 3) // 2
    Mp, Mc = P_prev[:, 3:, 3:], P_cur[:, 3:, 3:]
    unchanged = (Mp == Mc).all(axis=(1, 2))
    growth = np.ones(K, bool)
    changed = np.flatnonzero(~unchanged)
    if changed.size and m:
        D = Mp[changed] - Mc[changed]
        xx, yy, xy, yx = D[:, 0::2, 0::2], D[:, 1::2, 1::2], D[:, 0::2, 1::2], D[:, 1::2, 0::2]
        dxx = np.diagonal(xx, axis1=1, axis2=2)
        dyy = np.diagonal(yy, axis1=1, axis2=2)
        dxy = 0.5 * (np.diagonal(xy, axis1=1, axis2=2) + np.diagonal(yx, axis1=1, axis2=2))
        dp = np.abs(np.diagonal(Mp[changed], axis1=1, axis2=2))
        t = dp[:, 0::2] + dp[:, 1::2]
        lam = min_eig_2x2(dxx, dxy, dyy)
        ok = ~(lam < -(rtol_growth * t + atol_growth)).any(axis=1)
        if m >= 2:
            a = dxx[:, :, None] + dxx[:, None, :] - 2.0 * xx
            c = dyy[:, :, None] + dyy[:, None, :] - 2.0 * yy
            b = dxy[:, :, None] + dxy[:, None, :] - (xy + yx)
            lam2 = min_eig_2x2(a, b, c)
            tol2 = rtol_growth * (t[:, :, None] + t[:, None, :]) + atol_growth
            upper = np.triu(np.ones((m, m), bool), 1)  # i < j, as pair_growth reads them
            ok &= ~((lam2 < -tol2) & upper).any(axis=(1, 2))
        growth[changed] = ok
    prediction = np.ones(K, bool)
    which = np.flatnonzero(predict)
    if which.size:
        prediction[which] = _screen_prediction(
            P_prev[which], P_cur[which], pose_prev[which], pose_cur[which],
            unchanged[which], rtol=rtol_prediction, atol=atol_growth)
    return PairScreen(unchanged, growth, prediction)


def _screen_prediction(P_prev: np.ndarray, P_cur: np.ndarray, pose_prev: np.ndarray,
                       pose_cur: np.ndarray, unchanged: np.ndarray, *, rtol: float,
                       atol: float) -> np.ndarray:
    """Stacked :func:`prediction_residuals`: True where all three of its tests pass (a
    changed map block is left to the per-state test, which weighs the change)."""
    dx = (pose_cur[:, 0] - pose_prev[:, 0])[:, None]
    dy = (pose_cur[:, 1] - pose_prev[:, 1])[:, None]
    floor = atol / max(rtol, 1e-300)
    ok = unchanged.copy()
    if P_cur.shape[1] > 3:
        Pvm_prev = P_prev[:, :3, 3:]
        resid = P_cur[:, :3, 3:] - Pvm_prev
        resid[:, 0] += dy * Pvm_prev[:, 2]
        resid[:, 1] -= dx * Pvm_prev[:, 2]
        np.abs(resid, out=resid)
        dm = np.abs(np.diagonal(P_prev, axis1=1, axis2=2)[:, 3:])
        dv = np.maximum(np.abs(np.diagonal(P_prev, axis1=1, axis2=2)[:, :3]),
                        np.abs(np.diagonal(P_cur, axis1=1, axis2=2)[:, :3]))
        resid /= np.sqrt(dv[:, :, None] * dm[:, None, :]) + floor
        ok &= ~(resid > rtol).any(axis=(1, 2))
    # Q = Pvv − Fx·Pvv(prev)·Fxᵀ with Fx = I + u·e_θᵀ, u = (−Δy, Δx, 0), written out
    V = P_prev[:, :3, :3]
    u = np.concatenate([-dy, dx, np.zeros_like(dx)], axis=1)  # [K, 3]
    col = V[:, :, 2]  # Pvv(prev)·e_θ
    row = V[:, 2, :]  # e_θᵀ·Pvv(prev)
    FPF = V + u[:, :, None] * row[:, None, :] + col[:, :, None] * u[:, None, :] \
        + (u[:, :, None] * u[:, None, :]) * V[:, 2, 2][:, None, None]
    Pvv = P_cur[:, :3, :3]
    Q = Pvv - FPF
    tol = rtol * np.abs(np.diagonal(Pvv, axis1=1, axis2=2)).sum(axis=1) + atol
    Q = 0.5 * (Q + Q.transpose(0, 2, 1))
    a, b, c = Q[:, 0, 0] + tol, Q[:, 0, 1], Q[:, 0, 2]
    d, e, f = Q[:, 1, 1] + tol, Q[:, 1, 2], Q[:, 2, 2] + tol
    # Q + tol·I positive definite (Sylvester's leading minors) ⇒ λ_min(Q) > −tol
    ok &= (a > 0) & (a * d - b * b > 0) & (
        a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - c * d) > 0)
    return ok
