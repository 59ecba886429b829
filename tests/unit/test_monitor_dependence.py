"""The NIS band that counts the innovations' dependence (services/monitor/dependence.py,
WindowTest(band="measured")), against independent oracles: numpy's autocovariance of the
whole stream, the closed-form τ of an AR(1) process, and Monte-Carlo false-alarm rates of
dependent χ²(2) streams whose every sample has the consistent mean."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from slamlens.common.messages import SlamState
from slamlens.services.monitor.dependence import LagCovariance
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import WindowTest
from tests.unit.monitor_runs import feed, violations


def ar1_innovations(rng: np.random.Generator, n: int, phi: float) -> np.ndarray:
    """n 2-d unit innovations that follow ν_t = φ·ν_{t−1} + √(1−φ²)·ε_t (unit variance at
    every step), dependent in time for φ ≠ 0."""
    eps = rng.normal(size=(n, 2))
    nu = np.empty_like(eps)
    nu[0] = eps[0]
    gain = np.sqrt(1.0 - phi * phi)
    for t in range(1, n):
        nu[t] = phi * nu[t - 1] + gain * eps[t]
    return nu


def ar1_nis(rng: np.random.Generator, n: int, phi: float) -> np.ndarray:
    """NIS |ν|² of :func:`ar1_innovations`: every sample χ²(2) (mean 2, as a consistent
    filter's), dependent in time for φ ≠ 0."""
    nu = ar1_innovations(rng, n, phi)
    return (nu * nu).sum(axis=1)


def numpy_autocovariance(x: np.ndarray, lags: int) -> np.ndarray:
    xc = x - x.mean()
    return np.array([np.dot(xc[:x.size - k], xc[k:]) / x.size for k in range(lags + 1)])


@pytest.mark.parametrize("blocks", [[50] * 12, [1, 3, 200, 7, 0, 49, 50, 51, 2],
                                    [5, 5, 5], [30]])
def test_lag_covariance_equals_numpy_on_the_whole_stream(blocks) -> None:
    rng = np.random.default_rng(len(blocks))
    x = rng.gamma(2.0, size=sum(blocks)) + np.repeat(rng.normal(size=len(blocks)), blocks)
    lags = LagCovariance(49)
    start = 0
    for size in blocks:
        lags.add(x[start:start + size])
        start += size
    expected = numpy_autocovariance(x, min(49, x.size - 1))
    np.testing.assert_allclose(lags.autocovariance(), expected, rtol=1e-10, atol=1e-12)


def test_tau_of_an_ar1_stream_is_the_closed_form() -> None:
    """NIS of AR(1) innovations: corr(|ν_t|², |ν_{t+k}|²) = φ^{2k} (Isserlis)."""
    N, phi = 50, 0.8
    lags = LagCovariance(N - 1)
    lags.add(ar1_nis(np.random.default_rng(1), 400_000, phi))
    k = np.arange(1, N)
    expected = 1.0 + 2.0 * np.sum((1.0 - k / N) * phi ** (2 * k))
    assert lags.tau(N) == pytest.approx(expected, rel=0.05)
    white = LagCovariance(N - 1)
    white.add(ar1_nis(np.random.default_rng(2), 400_000, 0.0))
    assert 1.0 <= white.tau(N) < 1.02


def failure_rate(nis: np.ndarray, band: str, alpha: float, window: int = 50) -> float:
    test = WindowTest(dof=2, window=window, alpha=alpha, band=band, measure_after=4 * window)
    results = test.add(nis)
    return sum(r.failed for r in results) / len(results)


@pytest.mark.parametrize("phi", [0.6, 0.85])
def test_the_measured_band_keeps_its_false_alarm_rate_where_the_white_band_does_not(phi):
    """Dependent NIS with the consistent mean: the white band fails windows far more often
    than its α (here 1 %), the measured band about as often as α says."""
    alpha = 0.01
    nis = ar1_nis(np.random.default_rng(int(phi * 100)), 200_000, phi)
    white = failure_rate(nis, "white", alpha)
    measured = failure_rate(nis, "measured", alpha)
    assert white > 5 * alpha, white
    assert measured < 2.5 * alpha, measured


def test_on_white_innovations_the_measured_band_is_the_textbook_band() -> None:
    alpha = 0.01
    nis = ar1_nis(np.random.default_rng(5), 100_000, 0.0)
    test = WindowTest(dof=2, window=50, alpha=alpha, band="measured", measure_after=200)
    test.add(nis)
    textbook_hi = chi2.ppf(1 - alpha / 2, 100) / 50
    assert 1.0 <= test.tau < 1.03
    assert textbook_hi <= test.hi < 1.01 * textbook_hi
    assert failure_rate(nis, "measured", alpha) < 2 * alpha


@pytest.mark.parametrize("phi", [0.0, 0.6])
def test_an_overconfident_filter_still_fails_every_window(phi) -> None:
    """S four times too small (NIS × 4): the white band fails every window, the measured
    band (dependence counted: fewer independent samples, a wider band) nearly every one."""
    nis = 4.0 * ar1_nis(np.random.default_rng(7), 20_000, phi)
    assert failure_rate(nis, "white", 1e-6) == 1.0
    assert failure_rate(nis, "measured", 1e-6) >= (1.0 if phi == 0.0 else 0.95)


def test_the_band_is_white_until_measured_and_the_dependence_is_reported() -> None:
    test = WindowTest(dof=2, window=50, alpha=1e-6, band="measured", measure_after=200)
    white_band = (test.lo, test.hi)
    nis = ar1_nis(np.random.default_rng(8), 400, 0.85)
    results = test.add(nis)
    assert [(r.lo, r.hi) for r in results[:4]] == [white_band] * 4
    assert results[4].hi > white_band[1] and results[4].effective < 50
    test.reset()
    assert (test.lo, test.hi, test.tau) == (*white_band, 1.0)


def states_with_innovations(nis_scale: float, phi: float, count: int) -> list[SlamState]:
    """Update states with 4 innovations each, S = I, ν AR(1) in time (scaled by √scale)."""
    nu = ar1_innovations(np.random.default_rng(11), 4 * count, phi) * np.sqrt(nis_scale)
    return [SlamState(robot="r", seq=k, stamp=0.1 * k, step="update", pose=np.zeros(3),
                      landmark_ids=np.zeros(0, dtype=np.int64), landmarks=np.zeros((0, 2)),
                      covariance=np.zeros((3, 3)), innovation_ids=np.arange(4),
                      innovations=nu[4 * k:4 * k + 4],
                      innovation_covariances=np.repeat(np.eye(2)[None], 4, axis=0))
            for k in range(count)]


def test_the_monitor_counts_correlated_innovations_and_says_so() -> None:
    """The same correlated innovations, consistent in their mean: the white band raises NIS
    violations, the default (measured) band raises none and reports τ; scaled × 3 the
    measured band fails them and its detail says how many independent ones it counted."""
    states = states_with_innovations(1.0, 0.9, 2500)
    white = feed(Monitor(MonitorSettings(nis_dependence="white")), states)
    measured = feed(Monitor(MonitorSettings()), states)
    assert [v for v in violations(white) if v.kind == "nis"]
    assert [v for v in violations(measured) if v.kind == "nis"] == []
    assert measured[-1].statistics["nis_tau"] > 3.0
    assert white[-1].statistics["nis_tau"] == 1.0
    bad = feed(Monitor(MonitorSettings()), states_with_innovations(3.0, 0.9, 2500))
    nis = [v for v in violations(bad) if v.kind == "nis"]
    assert nis and all(v.value > v.bound for v in nis)
    assert any(" independent, correlated in time): the innovations are larger" in v.detail
               for v in nis)
