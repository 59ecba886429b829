"""Large maps within a glyph budget: which pairs a picture can afford, and the
min / mean / max of every group pair without a Python-level pass over all pairs.

A picture of n features in "all" mode has n(n−1)/2 glyphs: 1225 at n = 50, 499 500 at
n = 1000 — unreadable, and far beyond a frame's time. The rule (docs/visualisation.md):

* a mode draws individual pairs while their number is within ``glyph_budget``;
* above it ("all", "inter"; or "minmeanmax" whose cluster pairs exceed it) the picture
  becomes the min / mean / max overview: per pair of *groups*, the smallest, the mean and
  the largest P_d over the pairs between them, on the line between the group centroids.
  The groups are the view's clusters (single linkage at its cut) when they fit
  (:func:`max_groups`: 3·C(k, 2) glyphs within the budget, and at most ``MAX_GROUPS``);
  else square map tiles, anchored at the map origin, of the smallest side of 0.25 · 2^m m
  whose occupied tiles fit (a tile keeps its id as the map grows);
* a selected feature (its n−1 pairs) or a selected cluster (the pairs inside it) is drawn
  in full detail whatever the budget (a cluster of more than ``SELECTED_CAP`` pairs: its
  largest ones, said in the legend).

:func:`group_min_mean_max` finds the min and max pair of every group pair and the mean
P_d exactly, from the covariance in float32 whole-matrix passes (OpenCV/NumPy kernels, no
per-pair gathers); the picked pairs' glyphs are then computed from P in float64 as usual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: a selected cluster shows at most this many times the budget (its largest pairs)
SELECTED_CAP = 4
#: above this many pairs the min/mean/max mode uses the whole-matrix kernel too
FAST_PAIRS = 20_000
TILE_BASE_M = 0.25  #: tile sides are this times a power of two
MAX_GROUPS = 12  #: an overview has at most this many groups (clusters or tiles)
_TILE_OFFSET = 1 << 20  # tile ids: (ix + offset) · 2^21 + (iy + offset), stable and unique


def pair_count(n: int, cluster_ids: np.ndarray | None = None, *, inter: bool = False) -> int:
    """Pairs of n features, or (``inter``) only those whose features are in different
    clusters."""
    total = n * (n - 1) // 2
    if not inter or cluster_ids is None or n < 2:
        return total
    _, sizes = np.unique(cluster_ids, return_counts=True)
    return total - int(np.sum(sizes * (sizes - 1) // 2))


def overview_glyphs(groups: int) -> int:
    """Glyphs of a min/mean/max picture over ``groups`` groups: three per group pair."""
    return 3 * groups * (groups - 1) // 2


def max_groups(budget: int) -> int:
    """The most groups of an overview: its min/mean/max picture within ``budget`` glyphs,
    and at most ``MAX_GROUPS`` (66 lines: more crossing lines read as a web, not a map)."""
    k = int((1 + math.sqrt(1 + 8 * budget / 3)) / 2)
    while overview_glyphs(k + 1) <= budget:
        k += 1
    while k > 2 and overview_glyphs(k) > budget:
        k -= 1
    return max(2, min(k, MAX_GROUPS))


def tile_groups(xy: np.ndarray, budget: int) -> tuple[np.ndarray, float]:
    """(stable tile id per feature, tile side m): the smallest side 0.25 · 2^m m whose
    occupied tiles give a min/mean/max picture within ``budget`` glyphs."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    limit = max_groups(budget)
    side = TILE_BASE_M
    for _ in range(40):
        cells = np.floor(xy / side).astype(np.int64)
        ids = (cells[:, 0] + _TILE_OFFSET) * (1 << 21) + (cells[:, 1] + _TILE_OFFSET)
        if len(np.unique(ids)) <= limit:
            return ids, side
        side *= 2.0
    return np.zeros(len(xy), np.int64), side


def pair_relative_covariances(P: np.ndarray, first: np.ndarray,
                              second: np.ndarray) -> np.ndarray:
    """P_d (k, 2, 2) of the pairs (first[k], second[k]) of landmark indices — the same
    arithmetic as ``slamlens.common.geometry.all_relative_covariances``, for these pairs only."""
    lm = 3 + 2 * np.arange((P.shape[0] - 3) // 2)
    a_, b_, d_ = P[lm, lm], P[lm + 1, lm], P[lm + 1, lm + 1]
    r, c = lm[first], lm[second]
    Pd = np.empty((len(first), 2, 2))
    Pd[:, 0, 0] = a_[first] + a_[second] - 2.0 * P[r, c]
    Pd[:, 1, 1] = d_[first] + d_[second] - 2.0 * P[r + 1, c + 1]
    off = b_[first] + b_[second] - P[r, c + 1] - P[r + 1, c]
    Pd[:, 0, 1] = off
    Pd[:, 1, 0] = off
    return Pd


@dataclass(frozen=True)
class GroupPairs:
    """min / mean / max P_d per pair of groups (one row per group pair)."""

    groups: np.ndarray  #: (c, 2) group ids, first < second
    count: np.ndarray  #: (c,) feature pairs between them
    min_pair: np.ndarray  #: (c, 2) landmark indices (i < j) of the smallest P_d
    max_pair: np.ndarray  #: (c, 2) landmark indices (i < j) of the largest P_d
    mean_Pd: np.ndarray  #: (c, 2, 2) element-wise mean P_d over the group pair


def group_min_mean_max(P: np.ndarray, groups: np.ndarray) -> GroupPairs:
    """min / max (by √λmax of P_d) and mean P_d over the pairs between every two groups.

    ``groups`` is a group id per landmark. The map block of P is cast to float32 once, in
    the state's order; then, group by group, the block of its rows against the later
    groups' columns (gathered in group order — each inter-group pair once, in pieces that
    fit the cache) gives every pair's λmax (the ranking only: the glyphs are computed from
    P in float64) and the block sums of P for the mean: mean P_d(A, B) = mean_A P_ii +
    mean_B P_jj − mean over A × B of (P_ij + P_ji), exact up to float32 sums.
    """
    groups = np.asarray(groups, dtype=np.int64)
    n = len(groups)
    order = np.argsort(groups, kind="stable")
    g_sorted = groups[order]
    starts = np.flatnonzero(np.r_[True, g_sorted[1:] != g_sorted[:-1]])
    ends = np.r_[starts[1:], n]
    ids = g_sorted[starts]
    k = len(ids)
    empty = np.zeros((0, 2), np.int64)
    if k < 2:
        return GroupPairs(empty, np.zeros(0, np.int64), empty, empty, np.zeros((0, 2, 2)))
    lm = 3 + 2 * order  # x row/column of each landmark of P, in group order
    sorted_xy = np.column_stack([lm - 3, lm - 2]).reshape(-1)  # the same, in P_mm
    # the map block in float32 (one pass, whatever P's alignment); each group's rows and
    # the later groups' columns are gathered below, a piece that fits the cache (gathering
    # all rows into group order first cost 1.2 ms more at n = 1000: one more 16 MB copy)
    R = P[3:, 3:].astype(np.float32)
    dx = P[lm, lm].astype(np.float32)
    dy = P[lm + 1, lm + 1].astype(np.float32)
    dz = P[lm, lm + 1].astype(np.float32)
    size = (ends - starts).astype(float)
    ga, gb = np.triu_indices(k, k=1)
    sums = np.zeros((3, k, k))  # Σ P_xx, Σ P_yy, Σ (P_xy + P_yx) per block (u < v)
    lo = np.empty((len(ga), 2), np.int64)
    hi = np.empty((len(ga), 2), np.int64)
    p = 0
    for u in range(k - 1):
        r0, r1, c0 = starts[u], ends[u], ends[u]
        block = R.take(sorted_xy[2 * r0:2 * r1], axis=0).take(sorted_xy[2 * c0:], axis=1)
        Rx, Ry = block[0::2], block[1::2]
        X, Zxy, Zyx, Y = Rx[:, 0::2], Rx[:, 1::2], Ry[:, 0::2], Ry[:, 1::2]
        cuts = starts[u + 1:] - c0
        a = (dx[r0:r1, None] + dx[None, c0:]) - 2.0 * X
        c = (dy[r0:r1, None] + dy[None, c0:]) - 2.0 * Y
        Z = Zxy + Zyx
        b = (dz[r0:r1, None] + dz[None, c0:]) - Z
        half = 0.5 * (a - c)
        lam = 0.5 * (a + c) + np.sqrt(half * half + b * b)
        for q, A in enumerate((X, Y, Z)):
            sums[q, u, u + 1:] = np.add.reduceat(A, cuts, axis=1).sum(axis=0, dtype=float)
        row_min = np.minimum.reduceat(lam, cuts, axis=1)
        row_max = np.maximum.reduceat(lam, cuts, axis=1)
        col_end = np.r_[cuts[1:], lam.shape[1]]
        for v in range(len(cuts)):
            q0, q1 = cuts[v], col_end[v]
            i = int(row_min[:, v].argmin())
            lo[p] = (r0 + i, c0 + q0 + int(lam[i, q0:q1].argmin()))
            i = int(row_max[:, v].argmax())
            hi[p] = (r0 + i, c0 + q0 + int(lam[i, q0:q1].argmax()))
            p += 1
    mx = np.add.reduceat(dx.astype(float), starts) / size
    my = np.add.reduceat(dy.astype(float), starts) / size
    mz = np.add.reduceat(dz.astype(float), starts) / size
    cnt = size[ga] * size[gb]
    mean = np.empty((len(ga), 2, 2))
    mean[:, 0, 0] = mx[ga] + mx[gb] - 2.0 * sums[0, ga, gb] / cnt
    mean[:, 1, 1] = my[ga] + my[gb] - 2.0 * sums[1, ga, gb] / cnt
    off = mz[ga] + mz[gb] - sums[2, ga, gb] / cnt
    mean[:, 0, 1] = mean[:, 1, 0] = off
    lo, hi = order[lo], order[hi]  # back to the state's landmark indices
    return GroupPairs(groups=np.column_stack([ids[ga], ids[gb]]),
                      count=cnt.astype(np.int64), min_pair=np.sort(lo, axis=1),
                      max_pair=np.sort(hi, axis=1), mean_Pd=mean)
