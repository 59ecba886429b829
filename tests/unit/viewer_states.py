"""States for the viewer's unit tests: a random SlamState with a valid covariance."""

from __future__ import annotations

import numpy as np

from slamlens.common.messages import SlamState


def random_state(n: int, *, seq: int = 1, seed: int = 0, landmarks=None) -> SlamState:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n)) * 0.05
    P = A @ A.T + 1e-4 * np.eye(3 + 2 * n)
    xy = rng.uniform(0, 3, (n, 2)) if landmarks is None else np.asarray(landmarks, float)
    return SlamState(robot="r", seq=seq, stamp=0.1 * seq, step="update",
                     pose=np.array([1.0, 1.0, 0.0]), landmark_ids=np.arange(100, 100 + n),
                     landmarks=xy, covariance=P)
