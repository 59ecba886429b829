"""Which feature pairs a picture shows, and the min / mean / max of P_d per cluster pair.

Pure helpers of docs/visualisation.md's three modes, shared by the viewer's scene and the recorder's
Foxglove scene (they were ``services/visualiser/scene.py``'s; behaviour unchanged):
``all`` every pair, ``inter`` pairs in different clusters, ``minmeanmax`` per cluster pair
the smallest, the element-wise mean and the largest P_d, sizes by ``pd_size_m`` (why: the
viewer scene module's docstring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamlens.common.errors import RenderError
from slamlens.common.geometry import pd_size_m


def pair_size(Pd: np.ndarray) -> np.ndarray:
    """Scalar size of relative covariances (..., 2, 2): √λmax, m (``pd_size_m``)."""
    return pd_size_m(Pd)


def select_pairs(n: int, *, mode: str, cluster_ids: np.ndarray | None = None,
                 selected_index: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ii, jj), ii < jj, into the state's landmarks that ``mode`` considers.

    ``inter`` and ``minmeanmax`` keep pairs in different clusters; ``selected_index`` keeps
    pairs containing that landmark (see the module docstring for ``minmeanmax``).
    """
    ii, jj = np.triu_indices(n, k=1)
    keep = np.ones(len(ii), dtype=bool)
    if mode in ("inter", "minmeanmax") and not (mode == "minmeanmax"
                                                 and selected_index is not None):
        if cluster_ids is None:
            raise RenderError(f"mode {mode!r} needs cluster ids")
        keep &= cluster_ids[ii] != cluster_ids[jj]
    if selected_index is not None:
        keep &= (ii == selected_index) | (jj == selected_index)
    return ii[keep], jj[keep]


@dataclass(frozen=True)
class ClusterPairStats:
    """min / mean / max P_d per pair of clusters (one row per cluster pair)."""

    clusters: np.ndarray  #: (c, 2) cluster ids, first < second
    count: np.ndarray  #: (c,) number of feature pairs between them
    min_pair: np.ndarray  #: (c,) index into the given pair arrays of the smallest P_d
    max_pair: np.ndarray  #: (c,) index of the largest P_d
    mean_Pd: np.ndarray  #: (c, 2, 2) element-wise mean P_d


def min_mean_max(ii: np.ndarray, jj: np.ndarray, Pd: np.ndarray,
                 cluster_ids: np.ndarray) -> ClusterPairStats:
    """Group inter-cluster pairs by cluster pair; pick min/max by size; average P_d."""
    ca, cb = cluster_ids[ii], cluster_ids[jj]
    lo, hi = np.minimum(ca, cb), np.maximum(ca, cb)
    inter = lo != hi
    idx = np.flatnonzero(inter)
    if idx.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return ClusterPairStats(np.zeros((0, 2), np.int64), empty, empty, empty,
                                np.zeros((0, 2, 2)))
    keys = np.column_stack([lo[idx], hi[idx]])
    groups, inverse, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sizes = pair_size(Pd[idx])
    order = np.lexsort((sizes, inverse))  # by group, then by size within a group
    starts = np.concatenate([[0], np.cumsum(count)[:-1]])
    min_pair = idx[order[starts]]
    max_pair = idx[order[starts + count - 1]]
    sums = np.zeros((len(groups), 2, 2))
    np.add.at(sums, inverse, Pd[idx])
    return ClusterPairStats(groups.astype(np.int64), count.astype(np.int64), min_pair,
                            max_pair, sums / count[:, None, None])
