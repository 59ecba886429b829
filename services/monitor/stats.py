"""Statistical consistency tests of the monitor: NEES against truth, NIS of innovations.

A single NEES / NIS value is only a statistic (reported with its χ² band); a *violation*
is raised when the mean over a completed window leaves its band at the configured two-sided
significance α. Windows are tumbling (one test per ``window`` samples, not per state), so a
run of S samples makes S / window tests and the false-alarm rate per run is ≈ α·S / window.

Two bands, because the two statistics differ in their dependence along one run:

* NIS: the innovations of a consistent EKF are white, so N·mean ~ χ²(N·dof) exactly. Real
  sensors' errors persist from one sighting to the next, and then they are not: the band
  used (``nis_dependence = "measured"``) counts a window of N as N / τ_N independent
  samples, τ_N measured on the run's innovations before the window (dependence.py) — on
  white innovations τ_N ≈ 1 and the band is the textbook one; ``"white"`` keeps that always.
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

from slamlens.common.errors import ConfigError
from slamlens.common.geometry import wrap_angle
from slamlens.services.monitor.dependence import LagCovariance


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
    # sym(Pvv) in Python floats: the same IEEE operations as numpy's 0.5 * (P + Pᵀ)
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = Pvv.tolist()
    a, b, c = 0.5 * (p00 + p00), 0.5 * (p01 + p10), 0.5 * (p02 + p20)
    d, e_, f = 0.5 * (p11 + p11), 0.5 * (p12 + p21), 0.5 * (p22 + p22)
    A, B, C = d * f - e_ * e_, c * e_ - b * f, b * e_ - c * d  # adjugate (symmetric)
    D, E, F = a * f - c * c, b * c - a * e_, a * d - b * b
    det = a * A + b * B + c * C
    tr = a + d + f
    if not (a > 0 and F > 0 and det > 0) or tr ** 3 > condition_max * det:
        return None
    (x0, y0, t0), (x1, y1, t1) = np.asarray(pose).tolist(), np.asarray(true_pose).tolist()
    x = x0 - x1
    y = y0 - y1
    t = float(wrap_angle(t0 - t1))
    q = A * x * x + D * y * y + F * t * t + 2.0 * (B * x * y + C * x * t + E * y * t)
    return q / det


def match_ids(ids: np.ndarray, true_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions in ``ids`` and in ``true_ids`` of the ids present in both."""
    _, i_est, i_true = np.intersect1d(ids, true_ids, assume_unique=True, return_indices=True)
    return i_est, i_true


@dataclass(frozen=True)
class BlockTerms:
    """What each feature's own 2×2 block P_ii = [[a, b], [b, c]] gives its NEES, for all
    features of a state (or a stack of states: leading axes): entries, determinant, and
    whether it is usable (positive definite and condition number ≤ ``condition_max``)."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    det: np.ndarray
    usable: np.ndarray  #: bool
    #: [..., n, 5]: a, b, c, det and usable (1.0 / 0.0) side by side (one gather a state)
    packed: np.ndarray

    def __getitem__(self, k: int) -> BlockTerms:
        """The terms of state ``k`` of a stack."""
        return BlockTerms(self.a[k], self.b[k], self.c[k], self.det[k], self.usable[k],
                          self.packed[k])


def block_terms(blocks: np.ndarray, *, condition_max: float) -> BlockTerms:
    """:class:`BlockTerms` of blocks [..., n, 2, 2] (b symmetrised, as NIS and NEES use it)."""
    a, c = blocks[..., 0, 0], blocks[..., 1, 1]
    b = 0.5 * (blocks[..., 0, 1] + blocks[..., 1, 0])
    det = a * c - b * b
    r = np.hypot(0.5 * (a - c), b)
    lo, hi = 0.5 * (a + c) - r, 0.5 * (a + c) + r
    usable = (a > 0) & (det > 0) & (lo > 0) & (hi <= condition_max * lo)
    return BlockTerms(a, b, c, det, usable, np.stack([a, b, c, det, usable], axis=-1))


def feature_nees(ids: np.ndarray, landmarks: np.ndarray, terms: BlockTerms,
                 true_landmarks: np.ndarray, matched: tuple[np.ndarray, np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(ids, NEES) of the features that have a truth and a usable P_ii (2 dof): eᵀP_ii⁻¹e
    in closed form, as :func:`quadratic_forms_2x2`.

    ``matched`` is :func:`match_ids` of the state's and the truth's landmark ids; ``terms``
    the state's :func:`block_terms`.
    """
    i_est, i_true = matched
    if i_est.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    e = landmarks[i_est] - true_landmarks[i_true]
    t = terms.packed[i_est]
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    e0, e1 = e[:, 0], e[:, 1]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = (c * e0 ** 2 - 2.0 * b * e0 * e1 + a * e1 ** 2) / t[:, 3]
    keep = (t[:, 4] != 0.0) & np.isfinite(q)
    if keep.all():  # (the usual case: no copies)
        return ids[i_est], q
    return ids[i_est][keep], q[keep]


@dataclass(frozen=True)
class WindowResult:
    """One completed window: its mean and the band it was tested against."""

    mean: float
    lo: float
    hi: float
    samples: int
    effective: float  #: independent samples the band counted them as

    @property
    def failed(self) -> bool:
        return not (self.lo <= self.mean <= self.hi)

    @property
    def edge(self) -> float:
        """The band edge a failed window crossed."""
        return float(self.hi if self.mean > self.hi else self.lo)

    @property
    def side(self) -> str:
        """Where a failed window left its band: "below" or "above"."""
        return "above" if self.mean > self.hi else "below"


#: what a NIS window outside its band says, by the side it left by (docs/monitor.md)
NIS_READING = {
    "below": "the innovations are smaller than S predicts (timid: noise set too large, "
             "or errors correlated in time)",
    "above": "the innovations are larger than S predicts (overconfident: noise set too "
             "small, or a model error)"}
#: what a NEES window outside its band says
NEES_READING = {
    "below": "the error is smaller than the covariance says (timid)",
    "above": "the error is larger than the covariance says (overconfident)"}


def window_detail(what: str, result: WindowResult, samples: str,
                  readings: dict[str, str]) -> str:
    """A failed window in words: "mean NIS 0.67 over 50 innovations, below [0.907, 3.7]: the
    innovations are smaller than S predicts (timid: …)"; a band that counted the samples as
    fewer independent ones (measured dependence) says so after the band: "… [0.21, 6.1]
    (as 8.3 independent, correlated in time): …"."""
    counted = ""
    if 1.0 < result.effective < result.samples:
        counted = f" (as {result.effective:.3g} independent, correlated in time)"
    return (f"{what} {result.mean:.3g} over {result.samples} {samples}, {result.side} "
            f"[{result.lo:.3g}, {result.hi:.3g}]{counted}: {readings[result.side]}")


class WindowTest:
    """Tumbling-window test of the mean of χ²(dof) samples; also a sliding mean for display.

    ``band`` says how the samples of a window depend on each other:

    * ``"white"``: independent, band of the mean = χ²(N·dof)/N;
    * ``"dependent"``: the dependence-robust band of the mean = χ²(dof) (one sample);
    * ``"measured"``: the stream's own dependence, measured on the samples before the window
      (dependence.py): N samples weigh as N_eff = N / τ_N independent ones, and the band is
      χ²(N_eff·dof)/N_eff (a χ² matched to the mean's mean and variance). White samples give
      τ_N ≈ 1, the white band; before ``measure_after`` samples, the white band.
    """

    BANDS = ("white", "dependent", "measured")

    def __init__(self, *, dof: int, window: int, alpha: float, band: str,
                 measure_after: int = 0) -> None:
        if band not in self.BANDS:
            raise ConfigError(f"band must be one of {self.BANDS}, got {band!r}")
        self.dof = dof
        self.window = window
        self.alpha = alpha
        self.band = band
        self.measure_after = measure_after
        self._lags = LagCovariance(window - 1) if band == "measured" else None
        self.tau = 1.0  #: τ_N of the band in use (1 unless measured)
        if band == "dependent":
            self.lo, self.hi = chi2_band(dof, alpha)
        else:
            self.lo, self.hi = self._white
        self.sample_lo, self.sample_hi = chi2_band(dof, alpha)
        self._recent: deque[float] = deque(maxlen=window)
        self._sum = 0.0
        self._count = 0
        self._mean: float | None = None  #: sliding_mean, until a sample comes

    @property
    def effective(self) -> float:
        """Independent samples the band counts a window as."""
        return 1.0 if self.band == "dependent" else self.window / self.tau

    @property
    def _white(self) -> tuple[float, float]:
        lo, hi = chi2_band(self.dof * self.window, self.alpha)
        return lo / self.window, hi / self.window

    def _measure(self) -> None:
        """The band of the next window, from the samples so far (``band="measured"``)."""
        assert self._lags is not None
        self._lags.add(np.fromiter(self._recent, dtype=float, count=len(self._recent)))
        if self._lags.count < self.measure_after:
            return
        tau = self._lags.tau(self.window)
        if tau != self.tau:
            self.tau = tau
            effective = self.window / tau
            lo, hi = chi2_band(self.dof * effective, self.alpha)
            self.lo, self.hi = lo / effective, hi / effective

    def reset(self) -> None:
        self._recent.clear()
        self._sum = 0.0
        self._count = 0
        self._mean = None
        if self._lags is not None:
            self._lags.reset()
            self.tau = 1.0
            self.lo, self.hi = self._white

    def add(self, values: np.ndarray | list[float]) -> list[WindowResult]:
        """Add samples; returns the windows they completed (usually none or one)."""
        done: list[WindowResult] = []
        for v in np.asarray(values, dtype=float).reshape(-1).tolist():
            result = self.add_one(v)
            if result is not None:
                done.append(result)
        return done

    def add_one(self, v: float) -> WindowResult | None:
        """Add one sample (a Python float); the window it completed, if it did."""
        if not math.isfinite(v):
            return None
        self._recent.append(v)
        self._mean = None
        self._sum += v
        self._count += 1
        if self._count == self.window:
            self._sum, total = 0.0, self._sum
            self._count = 0
            result = WindowResult(total / self.window, self.lo, self.hi, self.window,
                                  self.effective)
            if self._lags is not None:
                self._measure()
            return result
        return None

    @property
    def sliding_mean(self) -> float | None:
        """Mean of the last ``window`` samples (None before the first sample)."""
        if self._mean is None and self._recent:
            self._mean = sum(self._recent) / len(self._recent)
        return self._mean


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
                                               self.window, 1.0)))
                acc[0], acc[1] = 0.0, 0
        return done
