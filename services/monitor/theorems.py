"""The covariance theorems on each state, as violations (docs/monitor.md, "What is checked").

On the state alone: symmetry, |correlation| ≤ 1, positive semi-definiteness. Against the
last received state: every common feature's P_ii and every common pair's P_d
non-increasing in the Loewner order; after a predict that immediately follows it: P_mm
unchanged, P_vm = Fx·P_vm, process noise PSD. The numbers come from the pure checks of
:mod:`slamlens.services.monitor.checks`; here they become :class:`Violation` s that name the
features, and the features to blame are collected. Nothing here keeps state.
"""

from __future__ import annotations

import numpy as np

from slamlens.common.arrays import frozen_array
from slamlens.common.messages import SlamState, Violation
from slamlens.services.monitor import checks
from slamlens.services.monitor.settings import MonitorSettings

NO_PAIRS = frozen_array(np.zeros((0, 2)), "<i8")  #: read-only: no growing pair


# -- checks on one state -------------------------------------------------------------------
def check_alone(s: MonitorSettings, state: SlamState, *, structure_clean: bool,
                psd_clean: bool) -> list[Violation]:
    """Symmetry and correlation (unless screened clean), then PSD (unless screened clean)."""
    out: list[Violation] = []
    if not structure_clean:
        out += check_structure(s, state)
    if not psd_clean:
        out += check_psd(s, state)
    return out


def check_structure(s: MonitorSettings, state: SlamState) -> list[Violation]:
    P = state.covariance
    out: list[Violation] = []
    ids = state.landmark_ids
    asym, corr = checks.structure(P, rtol_symmetry=s.rtol_symmetry,
                                  rtol_correlation=s.rtol_correlation, atol=s.atol_growth)
    # the worst entry of each: asymmetry relative to its bound, |ρ| by its excess
    for kind, found, worst, what in (
            ("symmetry", asym, lambda f: f.value / f.bound, "P_ab ≠ P_ba"),
            ("correlation", corr, lambda f: f.value, "|ρ| > 1")):
        if not found.count:
            continue
        k = int(np.argmax(worst(found)))
        a, b = found.index[k]
        out.append(Violation(
            kind=kind, ids=_owners(ids, a, b), step=state.seq,
            value=float(found.value[k]), bound=float(found.bound[k]), phase=state.step,
            detail=f"{found.count} entries with {what}, worst {_name(ids, a)} / "
                   f"{_name(ids, b)}"))
    return out


def check_psd(s: MonitorSettings, state: SlamState) -> list[Violation]:
    P = state.covariance
    out: list[Violation] = []
    ids = state.landmark_ids
    neg = checks.min_eigenvalue_if_indefinite(P, rtol=s.rtol_psd, atol=s.atol_growth)
    if neg is not None:
        lam, tol, vec = neg
        # blame-free, but name the features carrying ≥ 10 % of the negative direction
        weight = vec[3:].reshape(-1, 2) ** 2
        per_feature = weight.sum(axis=1) if weight.size else np.zeros(0)
        total = float(np.sum(vec ** 2))
        heavy = (np.flatnonzero(per_feature >= 0.1 * total) if total > 0
                 else np.zeros(0, dtype=np.int64))
        out.append(Violation(
            kind="psd", ids=tuple(int(ids[i]) for i in heavy), step=state.seq,
            value=-lam, bound=tol, phase=state.step,
            detail=f"covariance not PSD: smallest eigenvalue {lam:.3g}"))
    return out


# -- checks against the previous received state --------------------------------------------
def check_against(s: MonitorSettings, prev: SlamState, state: SlamState,
                  stats: dict[str, float], screened: tuple[bool, bool, bool] | None = None, *,
                  before: np.ndarray | None = None
                  ) -> tuple[np.ndarray, list[int], list[Violation]]:
    """Growth of P_ii and P_d since ``prev``, and the predict step; ``screened``: (map block
    unchanged, nothing grew, predict-step tests pass) from the batched screen, or None.
    Returns the growing pairs (feature ids), the features blamed directly, the violations."""
    out: list[Violation] = []
    direct: list[int] = []
    if screened is not None:  # the same landmarks in the same order, screened
        pos_prev = pos_cur = np.arange(prev.n)
        unchanged, no_growth, predicted = screened
    else:
        pos_prev, pos_cur = checks.common_landmarks(prev.landmark_ids,
                                                    state.landmark_ids)
        unchanged, no_growth, predicted = False, False, False
    removed = prev.n - pos_prev.shape[0]
    if removed:
        stats["landmarks_removed"] = float(removed)
    ids = prev.landmark_ids[pos_prev]
    pairs = NO_PAIRS
    if screened is None:
        Pmm_prev = checks.map_block(prev.covariance, pos_prev)
        Pmm_cur = checks.map_block(state.covariance, pos_cur)
        # cheap sufficient test: an untouched map block (every predict) cannot grow
        unchanged = np.array_equal(Pmm_prev, Pmm_cur)
    feats = pair = None
    if not unchanged and not no_growth:
        if screened is not None:  # the screen saw growth: now the blocks are needed
            Pmm_prev = checks.map_block(prev.covariance, pos_prev)
            Pmm_cur = checks.map_block(state.covariance, pos_cur)
        delta = Pmm_prev - Pmm_cur
        feats = checks.feature_growth(Pmm_prev, Pmm_cur, rtol=s.rtol_growth,
                                      atol=s.atol_growth, delta=delta)
        pair = checks.pair_growth(Pmm_prev, Pmm_cur, rtol=s.rtol_growth,
                                  atol=s.atol_growth, delta=delta)
    m = ids.shape[0]
    stats["pairs_checked"] = float(m * (m - 1) // 2)
    stats["pairs_growing"] = float(0 if pair is None else pair.count)
    stats["features_growing"] = float(0 if feats is None else feats.count)
    growth_max = 0.0
    if feats is not None and feats.count:
        growth_max = max(growth_max, float(feats.value.max()))
        out += _feature_growth(s, state, ids, feats)
        direct += [int(f) for f in ids[feats.index]]
    if pair is not None and pair.count:
        growth_max = max(growth_max, float(pair.value.max()))
        pairs = ids[pair.index]
        out += _pair_growth(s, state, pairs, pair)
    stats["growth_max"] = growth_max
    if (s.check_prediction and state.step == "predict"
            and state.seq == prev.seq + 1 and not predicted and before is not None):
        more, blamed = check_prediction(s, prev, state, pos_prev, pos_cur, ids,
                                        map_unchanged=unchanged, before=before)
        out += more
        direct += blamed
    return pairs, direct, out


def _feature_growth(s: MonitorSettings, state: SlamState, ids: np.ndarray,
                    feats: checks.Findings) -> list[Violation]:
    out: list[Violation] = []
    for k in top(s, feats.value):
        f = int(ids[feats.index[k]])
        out.append(Violation(
            kind="feature", ids=(f,), step=state.seq, value=float(feats.value[k]),
            bound=float(feats.bound[k]), phase=state.step,
            detail=f"P_ii of feature {f} grew by {feats.value[k]:.3g} m²"))
    return out


def _pair_growth(s: MonitorSettings, state: SlamState, pairs: np.ndarray,
                 pair: checks.Findings) -> list[Violation]:
    out: list[Violation] = []
    for k in top(s, pair.value):
        i, j = sorted(int(x) for x in pairs[k])  # a pair is written low–high
        out.append(Violation(
            kind="pair", ids=(i, j), step=state.seq, value=float(pair.value[k]),
            bound=float(pair.bound[k]), phase=state.step,
            detail=f"P_d of features {i}, {j} grew by {pair.value[k]:.3g} m²"))
    return out


def top(s: MonitorSettings, values: np.ndarray) -> np.ndarray:
    """Indices of the largest ``max_violations_per_kind`` values (all if fewer)."""
    limit = s.max_violations_per_kind
    if values.shape[0] <= limit:
        return np.arange(values.shape[0])
    return np.argpartition(-values, limit - 1)[:limit]


def check_prediction(s: MonitorSettings, prev: SlamState, state: SlamState,
                     pos_prev: np.ndarray, pos_cur: np.ndarray, ids: np.ndarray, *,
                     map_unchanged: bool, before: np.ndarray
                     ) -> tuple[list[Violation], list[int]]:
    """The predict step right after ``prev``: P_mm untouched, P_vm = Fx·P_vm, process
    noise PSD (``before``: where the prediction's Fx is measured from)."""
    map_changed, cross_wrong, noise = checks.prediction_residuals(
        prev.covariance, state.covariance, np.array([before[0], before[1], 0.0]),
        state.pose, pos_prev, pos_cur,
        rtol=s.rtol_prediction, atol=s.atol_growth, map_unchanged=map_unchanged)
    out: list[Violation] = []
    blamed: list[int] = []
    for k in range(map_changed.count):
        f = int(ids[map_changed.index[k]])
        blamed.append(f)
        out.append(Violation(
            kind="prediction", ids=(f,), step=state.seq, value=float(map_changed.value[k]),
            bound=float(map_changed.bound[k]), phase="predict",
            detail=f"P_mm rows of feature {f} changed in a predict (must be untouched)"))
    for k in range(cross_wrong.count):
        f = int(ids[cross_wrong.index[k]])
        blamed.append(f)
        out.append(Violation(
            kind="prediction", ids=(f,), step=state.seq, value=float(cross_wrong.value[k]),
            bound=float(cross_wrong.bound[k]), phase="predict",
            detail=f"P_v,m of feature {f} ≠ Fx·P_v,m(previous): cross-covariance not "
                   f"propagated"))
    if noise is not None:
        out.append(Violation(
            kind="prediction", ids=(), step=state.seq, value=-noise, bound=0.0,
            phase="predict",
            detail=f"Pvv − Fx·Pvv·Fxᵀ not PSD (λ_min {noise:.3g}): process noise "
                   f"negative"))
    return out, blamed


def _name(ids: np.ndarray, index: int) -> str:
    """Human name of state index ``index``: robot x/y/θ or feature id x/y."""
    if index < 3:
        return f"robot {'xyθ'[index]}"
    k, axis = divmod(index - 3, 2)
    return f"feature {int(ids[k])} {'xy'[axis]}"


def _owners(ids: np.ndarray, *indices: int) -> tuple[int, ...]:
    """Feature ids owning the state indices given (robot indices own none)."""
    out: list[int] = []
    for index in indices:
        if index >= 3:
            f = int(ids[(index - 3) // 2])
            if f not in out:
                out.append(f)
    return tuple(out)
