"""Spatial clusters of the map's features, with identities that persist between frames.

Paper §3.2: single-linkage hierarchical clustering on the Euclidean distance between the
estimated feature positions, cut at a distance (or into a given number of clusters).
``fcluster`` numbers clusters arbitrarily each time, so :class:`ClusterTracker` matches the
new clusters to the previous ones by shared members (Hungarian assignment on the overlap
counts): a matched cluster keeps its id (and so its colour), an unmatched one gets a new id.
"""

from __future__ import annotations

import colorsys

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.optimize import linear_sum_assignment


def cluster_labels(points_xy: np.ndarray, *, threshold_m: float = 0.6,
                   count: int = 0) -> np.ndarray:
    """Single-linkage cluster labels (n,) int64 in 0..k−1 for points (n, 2).

    ``count > 0`` cuts the dendrogram into (at most) that many clusters; otherwise clusters
    are the connected components of "closer than ``threshold_m``".
    """
    pts = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    n = len(pts)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    Z = linkage(pts, method="single", metric="euclidean")
    if count > 0:
        raw = fcluster(Z, t=min(count, n), criterion="maxclust")
    else:
        # fcluster's "distance" merges at ≤ t; single linkage = components of the t-graph.
        raw = fcluster(Z, t=threshold_m, criterion="distance")
    # Renumber by first appearance so labels do not depend on scipy's numbering.
    _, first, inverse = np.unique(raw, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inverse].astype(np.int64)


def cluster_colour(cluster_id: int) -> tuple[int, int, int]:
    """A distinct, stable BGR colour per cluster id (golden-ratio hue steps)."""
    hue = (0.13 + 0.618033988749895 * cluster_id) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.55, 1.0)
    return int(b * 255), int(g * 255), int(r * 255)


class ClusterTracker:
    """Keeps cluster ids stable across frames by matching members (landmark ids)."""

    def __init__(self) -> None:
        self._members: dict[int, frozenset[int]] = {}
        self._next_id = 0

    def reset(self) -> None:
        self._members = {}
        self._next_id = 0

    @property
    def clusters(self) -> dict[int, frozenset[int]]:
        """Current cluster id → member landmark ids."""
        return dict(self._members)

    def update(self, landmark_ids: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Stable cluster ids (n,) for this frame's ``labels`` of ``landmark_ids``."""
        ids = np.asarray(landmark_ids, dtype=np.int64).reshape(-1)
        labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        new_labels = np.unique(labels)
        new_members = [frozenset(ids[labels == lab].tolist()) for lab in new_labels]
        old_ids = list(self._members)
        assigned: dict[int, int] = {}  # new label index → stable id
        if old_ids and new_members:
            overlap = np.array([[len(m & self._members[o]) for o in old_ids]
                                for m in new_members], dtype=float)
            union = np.array([[len(m | self._members[o]) for o in old_ids]
                              for m in new_members], dtype=float)
            # Most shared members wins; Jaccard breaks ties (a split keeps the id on
            # the part most like the old cluster).
            score = overlap + 1e-3 * overlap / np.maximum(union, 1.0)
            rows, cols = linear_sum_assignment(score, maximize=True)
            for r, c in zip(rows, cols, strict=True):
                if overlap[r, c] > 0:
                    assigned[int(r)] = old_ids[int(c)]
        members: dict[int, frozenset[int]] = {}
        for k, m in enumerate(new_members):
            if k not in assigned:
                assigned[k] = self._next_id
                self._next_id += 1
            members[assigned[k]] = m
            self._next_id = max(self._next_id, assigned[k] + 1)
        self._members = members
        lut = np.array([assigned[k] for k in range(len(new_labels))], dtype=np.int64)
        return lut[np.searchsorted(new_labels, labels)] if len(labels) else labels
