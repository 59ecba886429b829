"""Where the EKF's Jacobians are evaluated: the bookkeeping of the First-Estimates-Jacobian
EKF (``slamlens estimator --linearisation fej``; Huang, Mourikis & Roumeliotis, IJRR 2010).

The standard EKF evaluates every Jacobian at the latest estimates. Its linearised system
then has an observable subspace of dimension 2n + 1 instead of 2n: the global rotation of
robot and map together gains information no measurement carries, and the filter becomes
overconfident in the map's heading (docs/estimator.md, "Linearisation"). FEJ evaluates

* the prediction Jacobian Fx between the robot's *propagated* estimates, p̂(k|k−1) →
  p̂(k+1|k) (:attr:`FirstEstimates.robot` before the step, the new position after it);
* each measurement Jacobian at the robot's propagated estimate p̂(k|k−1) and the landmark's
  *first* estimate (the position it was initialised at, kept for ever);
* the new landmark's initialisation Jacobian Gv at the robot's propagated estimate too,

so that, with N(k) = [I₂, J p̂(k|k−1); 0, 1; I₂, J ℓ₁; …; I₂, J ℓₙ] (J = [[0, −1], [1, 0]],
ℓᵢ the first estimates), F(k) N(k) = N(k+1), H(k) N(k) = 0 and the new landmark's rows are
Gv N(k): the three directions of N — global translation and rotation — stay unobservable.

``--linearisation oc`` (Observability-Constrained Jacobians) keeps the same points, Fx, Gv
and so the same N, but evaluates each update's H at the latest estimates and projects it
onto H N = 0 (:func:`slamlens.services.slam.ekf.update`'s ``null``): nearer the truth than
a first estimate when that has drifted far.

This module keeps those points (O(1) per step, 2 floats per landmark) and carries them
through checkpoints. No I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from slamlens.common.errors import EstimationError
from slamlens.services.slam.settings import FEJ, INVARIANT, LINEARISATIONS, OC, STANDARD

__all__ = ["FEJ", "INVARIANT", "LINEARISATIONS", "OC", "STANDARD", "FirstEstimates",
           "fused"]


class FirstEstimates:
    """The FEJ linearisation points of one map (module docstring)."""

    def __init__(self, robot_x: float, robot_y: float) -> None:
        self.robot: tuple[float, float] = (float(robot_x), float(robot_y))  #: p̂(k|k−1)
        self._landmarks: list[tuple[float, float]] = []  #: first estimates, state order

    @property
    def n(self) -> int:
        return len(self._landmarks)

    @property
    def landmarks(self) -> list[tuple[float, float]]:
        """The first estimates, in state order (a copy)."""
        return list(self._landmarks)

    def propagated(self, x: float, y: float) -> None:
        """A prediction moved the robot to p̂(k+1|k): the next steps linearise there."""
        self.robot = (x, y)

    def mapped(self, x: float, y: float) -> None:
        """A landmark was appended to the state at (x, y): its first estimate."""
        self._landmarks.append((x, y))

    def update_point(self, j: int) -> tuple[float, float, float, float]:
        """(robot x, y, landmark x, y) at which an observation of landmark ``j`` (state
        order) is linearised."""
        lx, ly = self._landmarks[j]
        return self.robot[0], self.robot[1], lx, ly

    def to_dict(self, ids: Sequence[int]) -> dict[str, Any]:
        """What a checkpoint keeps (msgpack-able): the robot's point and each landmark's
        first estimate by id."""
        if len(ids) != self.n:
            raise EstimationError(f"{len(ids)} ids for {self.n} first estimates")
        return {"robot": [self.robot[0], self.robot[1]],
                "landmarks": {int(i): [x, y] for i, (x, y) in zip(ids, self._landmarks,
                                                                   strict=True)}}

    @classmethod
    def from_dict(cls, saved: Mapping[str, Any] | None, *, ids: Sequence[int],
                  robot: Sequence[float], landmarks: Sequence[Sequence[float]]
                  ) -> FirstEstimates:
        """The points a checkpoint kept, for the map ``ids`` / ``landmarks`` it restores; a
        landmark (or robot) it does not name starts from its estimate now (a map resumed
        from a checkpoint written without FEJ: consistent from the restart on)."""
        saved = saved or {}
        point = saved.get("robot", robot[:2])
        out = cls(*_pair(point, "robot"))
        kept = {int(k): v for k, v in dict(saved.get("landmarks") or {}).items()}
        for lid, estimate in zip(ids, landmarks, strict=True):
            out.mapped(*_pair(kept.get(int(lid), estimate), f"landmark {lid}"))
        return out


def fused(sightings: Sequence[tuple[float, float, float]],
          var_bearing: float) -> tuple[float, float, float, float]:
    """k sightings (range, bearing, range variance) of one new landmark in one batch as one:
    the mean range and bearing (about the first, wrapped) with the variances over k — what
    FEJ maps when a batch sees a new landmark more than once (docs/estimator.md)."""
    k = len(sightings)
    b0 = sightings[0][1]
    z_r = sum(s[0] for s in sightings) / k
    z_b = _wrap(b0 + sum(_wrap(s[1] - b0) for s in sightings) / k)
    return z_r, z_b, sum(s[2] for s in sightings) / (k * k), var_bearing / k


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _pair(value: Any, what: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in value)
    except (TypeError, ValueError):
        raise EstimationError(f"first estimate of {what}: not two numbers ({value!r})") \
            from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise EstimationError(f"first estimate of {what} is not finite ({x!r}, {y!r})")
    return x, y
