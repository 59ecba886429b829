"""Statistical consistency tests of the monitor: NEES against truth, NIS of innovations.

A single NEES / NIS value is only a statistic (reported with its χ² band); a *violation*
is raised when the mean over a completed window leaves its band at the configured two-sided
significance α. Windows are tumbling (one test per ``window`` samples, not per state), so a
run of S samples makes S / window tests and the false-alarm rate per run is ≈ α·S / window.

Two bands, because the two statistics differ in their dependence along one run:

* NIS: the innovations of a consistent EKF are white, so N·mean ~ χ²(N·dof) exactly.
* NEES: the estimation error along one run is strongly autocorrelated (map errors persist
  for the whole run), so N·mean ~ χ²(N·dof) is false and would alarm on correct runs.
  The band used is the dependence-robust one: the window mean of fully dependent samples
  is one χ²(dof) sample, so the band is that of a single sample at the same α.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from common.geometry import wrap_angle


def chi2_band(dof: float, alpha: float) -> tuple[float, float]:
    """Two-sided (α/2, 1 − α/2) quantiles of χ²(dof)."""
    lo, hi = chi2.ppf([alpha / 2.0, 1.0 - alpha / 2.0], dof)
    return float(lo), float(hi)


def quadratic_forms_2x2(e: np.ndarray, S: np.ndarray) -> np.ndarray:
    """eᵀ S⁻¹ e for stacks e [k,2], S [k,2,2] in closed form; NaN where S is not PD."""
    a, b, c = S[:, 0, 0], 0.5 * (S[:, 0, 1] + S[:, 1, 0]), S[:, 1, 1]
    det = a * c - b * b
    ok = (a > 0) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = (c * e[:, 0] ** 2 - 2.0 * b * e[:, 0] * e[:, 1] + a * e[:, 1] ** 2) / det
    return np.where(ok, q, np.nan)


def pose_nees(pose: np.ndarray, Pvv: np.ndarray, true_pose: np.ndarray, *,
              condition_max: float) -> float | None:
    """NEES of the robot pose (3 dof, heading error wrapped); None if Pvv is unusable.

    Closed form eᵀ·adj(P)·e / det(P) in plain floats (a 3×3 LAPACK call costs more in
    overhead than the arithmetic). Pvv is unusable when tr³/det, an upper bound of its
    condition number, exceeds ``condition_max`` (e.g. the first steps from a zero initial
    covariance: rank-deficient, error dominated by linearisation) or it is not PD.
    """
    (a, b, c), (_, d, e_), (_, _, f) = (0.5 * (Pvv + Pvv.T)).tolist()
    A, B, C = d * f - e_ * e_, c * e_ - b * f, b * e_ - c * d  # adjugate (symmetric)
    D, E, F = a * f - c * c, b * c - a * e_, a * d - b * b
    det = a * A + b * B + c * C
    tr = a + d + f
    if not (a > 0 and F > 0 and det > 0) or tr ** 3 > condition_max * det:
        return None
    x = float(pose[0] - true_pose[0])
    y = float(pose[1] - true_pose[1])
    t = float(wrap_angle(float(pose[2] - true_pose[2])))
    q = A * x * x + D * y * y + F * t * t + 2.0 * (B * x * y + C * x * t + E * y * t)
    return q / det


def match_ids(ids: np.ndarray, true_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions in ``ids`` and in ``true_ids`` of the ids present in both."""
    _, i_est, i_true = np.intersect1d(ids, true_ids, assume_unique=True, return_indices=True)
    return i_est, i_true


def feature_nees(ids: np.ndarray, landmarks: np.ndarray, blocks: np.ndarray,
                 true_landmarks: np.ndarray, matched: tuple[np.ndarray, np.ndarray], *,
                 condition_max: float) -> tuple[np.ndarray, np.ndarray]:
    """(ids, NEES) of the features that have a truth and a well-conditioned P_ii (2 dof).

    ``matched`` is :func:`match_ids` of the state's and the truth's landmark ids.
    """
    i_est, i_true = matched
    if i_est.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    S = blocks[i_est]
    e = landmarks[i_est] - true_landmarks[i_true]
    q = quadratic_forms_2x2(e, S)
    a, c = S[:, 0, 0], S[:, 1, 1]
    b = 0.5 * (S[:, 0, 1] + S[:, 1, 0])
    r = np.hypot(0.5 * (a - c), b)
    lo, hi = 0.5 * (a + c) - r, 0.5 * (a + c) + r
    keep = np.isfinite(q) & (lo > 0) & (hi <= condition_max * lo)
    return ids[i_est][keep], q[keep]


@dataclass(frozen=True)
class WindowResult:
    """One completed window: its mean and the band it was tested against."""

    mean: float
    lo: float
    hi: float
    samples: int

    @property
    def failed(self) -> bool:
        return not (self.lo <= self.mean <= self.hi)


class WindowTest:
    """Tumbling-window test of the mean of χ²(dof) samples; also a sliding mean for display.

    ``dependent=False``: samples independent, band of the mean = χ²(N·dof)/N.
    ``dependent=True``: dependence-robust band of the mean = χ²(dof) (one sample).
    """

    def __init__(self, *, dof: int, window: int, alpha: float, dependent: bool) -> None:
        self.dof = dof
        self.window = window
        if dependent:
            self.lo, self.hi = chi2_band(dof, alpha)
        else:
            lo, hi = chi2_band(dof * window, alpha)
            self.lo, self.hi = lo / window, hi / window
        self.sample_lo, self.sample_hi = chi2_band(dof, alpha)
        self._recent: deque[float] = deque(maxlen=window)
        self._sum = 0.0
        self._count = 0

    def reset(self) -> None:
        self._recent.clear()
        self._sum = 0.0
        self._count = 0

    def add(self, values: np.ndarray | list[float]) -> list[WindowResult]:
        """Add samples; returns the windows they completed (usually none or one)."""
        done: list[WindowResult] = []
        for v in np.asarray(values, dtype=float).reshape(-1):
            if not math.isfinite(v):
                continue
            self._recent.append(float(v))
            self._sum += float(v)
            self._count += 1
            if self._count == self.window:
                done.append(WindowResult(self._sum / self.window, self.lo, self.hi,
                                         self.window))
                self._sum = 0.0
                self._count = 0
        return done

    @property
    def sliding_mean(self) -> float | None:
        """Mean of the last ``window`` samples (None before the first sample)."""
        return sum(self._recent) / len(self._recent) if self._recent else None


class FeatureWindows:
    """One dependence-robust tumbling window per feature id (2-dof NEES)."""

    def __init__(self, *, window: int, alpha: float) -> None:
        self.window = window
        self.lo, self.hi = chi2_band(2, alpha)
        self._sums: dict[int, list[float]] = {}

    def reset(self) -> None:
        self._sums.clear()

    def add(self, ids: np.ndarray, values: np.ndarray) -> list[tuple[int, WindowResult]]:
        done: list[tuple[int, WindowResult]] = []
        for fid, v in zip(ids.tolist(), values.tolist(), strict=True):
            acc = self._sums.setdefault(fid, [0.0, 0])
            acc[0] += v
            acc[1] += 1
            if acc[1] == self.window:
                done.append((fid, WindowResult(acc[0] / self.window, self.lo, self.hi,
                                               self.window)))
                acc[0], acc[1] = 0.0, 0
        return done
