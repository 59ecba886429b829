"""Materialising the published covariance from the estimator's lower triangle at n = 1000
(``ekf.symmetric``, the largest share of an update state's publish path; docs/large_maps.md).

The baseline, in the same run and interleaved: the copy-then-mirror it replaced (copy the
N×N block, then overwrite the upper triangle tile by tile from the lower one). Prints the
median of ``--repeats`` calls each and their ratio.

Run: ``.venv/bin/python benchmarks/bench_symmetric.py [--n 1000] [--repeats 40]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slamlens.common.arrays import bytes_backed_array  # noqa: E402
from slamlens.services.slam import ekf, ekf_storage  # noqa: E402


def copy_then_mirror(L: np.ndarray, N: int, out: np.ndarray) -> np.ndarray:
    """``ekf.symmetric`` before 2026-12-02 (the baseline)."""
    out[...] = L[:N, :N]
    B = ekf_storage._SYM_BLOCK
    for s in range(0, N, B):
        e = min(N, s + B)
        for c in range(e, N, B):
            f = min(N, c + B)
            out[s:e, c:f] = out[c:f, s:e].T
        tile = out[s:e, s:e]
        tile[...] = np.where(ekf_storage._lower_mask(e - s), tile, tile.T)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1000, help="landmarks")
    ap.add_argument("--repeats", type=int, default=40)
    args = ap.parse_args()
    N = 3 + 2 * args.n
    capacity = 3 + 2 * 1024  # the estimator's buffer at n = 1000 (capacity doubled to 1024)
    rng = np.random.default_rng(0)
    L = np.zeros((max(capacity, N), max(capacity, N)))
    L[:N, :N] = np.tril(rng.standard_normal((N, N)))
    out = bytes_backed_array((N, N), "<f8")  # what to_state writes into
    assert np.array_equal(copy_then_mirror(L, N, out.copy()), ekf.symmetric(L, N, out=out))
    old, new = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        copy_then_mirror(L, N, out)
        old.append(time.perf_counter() - t)
        t = time.perf_counter()
        ekf.symmetric(L, N, out=out)
        new.append(time.perf_counter() - t)
    a, b = statistics.median(old), statistics.median(new)
    print(f"symmetric at n = {args.n} (N = {N}, {N * N * 8 / 2**20:.1f} MiB), load "
          f"{os.getloadavg()[0]:.2f}: copy-then-mirror {a * 1e3:.2f} ms, one pass "
          f"{b * 1e3:.2f} ms (median of {args.repeats}); ratio {a / b:.2f}x")


if __name__ == "__main__":
    main()
