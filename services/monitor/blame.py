"""Pinpointing: which features to blame for the violations of one state, and over time.

Rule (documented in docs/monitor.md):

1. *Direct* evidence: a feature whose own block P_ii grew, or whose P_vm columns / P_mm rows
   came out of a predict wrong, is blamed with weight 1 (a correct EKF never does that to a
   feature, whatever the others do).
2. The growing pairs not touching a directly blamed feature are covered greedily: take the
   feature in most uncovered growing pairs; a tie is broken by the older evidence; a tie that
   remains blames every tied feature with weight 1/k. Repeat until every growing pair is
   covered (greedy minimum set cover: a faulty feature sits in all of its growing pairs, a
   correct one only in those with faulty partners).
3. Evidence decays with a half-life (in states) and a feature is a *suspect* while its
   evidence is ≥ ``suspect_score`` and ≥ ``suspect_ratio`` × the strongest evidence, so
   suspects are stable across states that show nothing (predict states for an update fault,
   a landmark out of view) and a one-off ambiguous blame fades.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping

import numpy as np


def blame_weights(*, direct: Iterable[int], pairs: np.ndarray,
                  prior: Mapping[int, float]) -> dict[int, float]:
    """Blame of one state: feature id → weight (see the module rule, steps 1-2).

    ``pairs`` are the growing pairs as feature ids, shape [m, 2].
    """
    weights = {int(f): 1.0 for f in direct}
    uncovered = [(int(i), int(j)) for i, j in np.asarray(pairs).reshape(-1, 2).tolist()
                 if i not in weights and j not in weights]
    while uncovered:
        counts = Counter(f for pair in uncovered for f in pair)
        top = max(counts.values())
        tied = [f for f, c in counts.items() if c == top]
        if len(tied) > 1:
            best = max(prior.get(f, 0.0) for f in tied)
            tied = [f for f in tied if prior.get(f, 0.0) == best]
        for f in tied:
            weights[f] = weights.get(f, 0.0) + 1.0 / len(tied)
        chosen = set(tied)
        uncovered = [p for p in uncovered if p[0] not in chosen and p[1] not in chosen]
    return weights


class Evidence:
    """Exponentially decaying blame per feature; suspects by absolute and relative score."""

    def __init__(self, *, half_life: float, suspect_score: float, suspect_ratio: float) -> None:
        self._decay = 0.5 ** (1.0 / half_life)
        self._min_score = suspect_score
        self._ratio = suspect_ratio
        self.scores: dict[int, float] = {}

    def reset(self) -> None:
        self.scores.clear()

    def step(self, weights: Mapping[int, float], present: Iterable[int] | None = None) -> None:
        """Age the evidence by one state, then add this state's blame.

        ``present``: ids still in the map; evidence of features that left it is dropped.
        """
        if not self.scores and not weights:  # nothing to age, nothing to add
            return
        keep = None if present is None else set(
            present.tolist() if isinstance(present, np.ndarray) else (int(i) for i in present))
        aged = {}
        for f, s in self.scores.items():
            s *= self._decay
            if s > 1e-3 and (keep is None or f in keep):
                aged[f] = s
        for f, w in weights.items():
            aged[f] = aged.get(f, 0.0) + w
        self.scores = aged

    @property
    def suspects(self) -> tuple[int, ...]:
        if not self.scores:
            return ()
        top = max(self.scores.values())
        floor = max(self._min_score, self._ratio * top)
        return tuple(sorted(f for f, s in self.scores.items() if s >= floor))
