"""How dependent a stream of samples is: the effective size of a window's mean.

A window mean of N samples with variance σ² each has variance σ²·τ_N / N, where

    τ_N = 1 + 2 · Σ_{k=1}^{N−1} (1 − k/N) · ρ_k

and ρ_k is the stream's autocorrelation at lag k: N samples weigh as N / τ_N independent
ones. White samples give τ_N = 1. :class:`LagCovariance` keeps the stream's autocovariances
up to lag N − 1 in O(N) memory however long the stream (running sums of lagged products and
the first and last N − 1 samples), and :meth:`LagCovariance.tau` sums ρ_k while they are
above what white samples give (the first ρ_k within ±2/√n, n samples so far, ends the sum:
beyond it the estimates are noise, which would only widen the band of white innovations).

The monitor's NIS band uses it (stats.py): innovations of a consistent EKF are white, but
real sensors' errors persist from one sighting to the next (docs/consistency.md), and a band
that assumes them white then alarms far more often than its α says.
"""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.errors import ConfigError


class LagCovariance:
    """Autocovariances c_0 … c_K of a stream (divided by n, centred at the stream's mean)."""

    def __init__(self, max_lag: int) -> None:
        if max_lag < 0:
            raise ConfigError(f"max_lag must be ≥ 0, got {max_lag}")
        self.max_lag = max_lag
        self.reset()

    def reset(self) -> None:
        self.count = 0
        self._total = 0.0
        self._products = np.zeros(self.max_lag + 1)  #: Σ_t x_t · x_{t+k}, k = 0 … K
        self._head = np.zeros(0)  #: the first K samples
        self._tail = np.zeros(0)  #: the last K samples

    def add(self, block: np.ndarray) -> None:
        """Append samples (finite floats) to the stream."""
        block = np.asarray(block, dtype=float).reshape(-1)
        if block.size == 0:
            return
        K = self.max_lag
        joined = np.concatenate((self._tail, block))
        start = self._tail.size  # the products whose later sample is new
        for k in range(min(K, joined.size - 1) + 1):
            first = max(start, k)
            self._products[k] += float(np.dot(joined[first:], joined[first - k:joined.size - k]))
        self.count += block.size
        self._total += float(block.sum())
        if self._head.size < K:
            self._head = np.concatenate((self._head, block[:K - self._head.size]))
        self._tail = joined[max(0, joined.size - K):] if K else np.zeros(0)

    def autocovariance(self) -> np.ndarray:
        """c_k for k = 0 … min(K, n − 1): (1/n)·Σ_t (x_t − x̄)(x_{t+k} − x̄)."""
        n = self.count
        if n == 0:
            return np.zeros(0)
        lags = min(self.max_lag, n - 1)
        mean = self._total / n
        k = np.arange(lags + 1)
        # Σ over x_t, t < n − k (all but the last k) and over x_{t+k} (all but the first k)
        head_sums = np.concatenate(([0.0], np.cumsum(self._head)))[:lags + 1]
        tail_sums = np.concatenate(([0.0], np.cumsum(self._tail[::-1])))[:lags + 1]
        early = self._total - tail_sums
        late = self._total - head_sums
        return (self._products[:lags + 1] - mean * (early + late) + (n - k) * mean * mean) / n

    def tau(self, window: int) -> float:
        """τ_N of a window of ``window`` samples (module docstring), 1 with no variance."""
        c = self.autocovariance()
        if c.size < 2 or not c[0] > 0.0:
            return 1.0
        tau = 1.0
        noise = 2.0 / math.sqrt(self.count)  # ρ_k of white samples: within ±2/√n (95 %)
        for k in range(1, min(window, c.size)):
            rho = c[k] / c[0]
            if not rho > noise:
                break
            tau += 2.0 * (1.0 - k / window) * rho
        return min(tau, float(window))
