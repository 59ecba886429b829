"""The estimator's state storage and map bookkeeping.

It owns the buffers of the state x and the lower triangle L of P (capacity doubled when
the map outgrows them, so adding a landmark does not reallocate every time), the landmark
ids in state order and their index, the ids handed to landmarks found by association, and,
with FEJ, the first estimates (:mod:`slamlens.services.slam.linearisation`). It adds a
landmark's rows (:func:`ekf.initialise`) and puts a checkpoint's state back. No I/O.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

import numpy as np

from slamlens.common.messages import SlamState
from slamlens.services.slam import ekf
from slamlens.services.slam.linearisation import FEJ, INVARIANT, OC, FirstEstimates
from slamlens.services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")

INITIAL_CAPACITY = 16  #: landmarks; doubled on demand


class StateStore:
    """x, L and the map's ids (docs/estimator.md); the kernels of :mod:`ekf` act on them."""

    def __init__(self, settings: EstimatorSettings, *,
                 capacity: int = INITIAL_CAPACITY) -> None:
        self.capacity = max(1, int(capacity))  #: landmarks the buffers hold
        size = 3 + 2 * self.capacity
        self.x = np.zeros(size)  #: the state (pose, then landmarks in state order)
        self.L = np.zeros((size, size))  #: P's lower triangle (ekf.py)
        self.ws = ekf.Workspace.for_capacity(size)
        self.x[0:3] = [float(v) for v in settings.initial_pose]
        self.x[2] = float(ekf.wrap_angle(self.x[2]))
        self.L[0:3, 0:3] = np.diag([float(s) ** 2 for s in settings.initial_pose_sigma])
        #: the FEJ linearisation points (None: the standard EKF, Jacobians at the estimates)
        self.fej = (FirstEstimates(self.x[0], self.x[1])
                    if settings.linearisation in (FEJ, OC) else None)
        #: OC-EKF: H at the estimates, projected so that it leaves N (of ``fej``) unobserved
        self.oc = settings.linearisation == OC
        #: the invariant EKF: each update's step by the group's exponential
        #: (:mod:`~slamlens.services.slam.ekf_invariant`)
        self.invariant = settings.linearisation == INVARIANT
        self.n = 0  #: landmarks in the map
        self.ids: list[int] = []  #: landmark ids in state order
        self.index: dict[int, int] = {}  #: landmark id → state order
        self.next_anonymous = settings.anonymous_id_base
        self._anonymous_base = settings.anonymous_id_base

    @property
    def size(self) -> int:
        """The state's length now, 3 + 2n."""
        return 3 + 2 * self.n

    @property
    def robot_point(self) -> Any:
        """Where the robot's Jacobians are evaluated: FEJ's point, or None (the estimate)."""
        return None if self.fej is None else self.fej.robot

    @property
    def holds_new(self) -> bool:
        """Whether a batch's new landmarks are mapped after its updates (FEJ, OC and the
        invariant EKF: docs/estimator.md)."""
        return self.fej is not None or self.invariant

    def linearisation(self, j: int) -> dict[str, Any]:
        """How an update of landmark ``j`` is linearised, as ekf.update's keywords: FEJ's
        point (robot x, y, landmark x, y) as ``at`` — H evaluated there —, for the OC-EKF
        the same point as ``null`` — the unobservable directions H must leave alone —, and
        nothing for the standard EKF (H at the latest estimates)."""
        if self.fej is None:
            return {}
        point = self.fej.update_point(j)
        return {"null": point} if self.oc else {"at": point}

    def flush(self) -> None:
        """Apply the downdates held back by a batch's updates (ekf.update ``defer``):
        after it, ``L`` is P again for anything that reads it."""
        ekf.flush(self.L, self.size, self.ws)

    def fresh_anonymous_id(self) -> int:
        """An id no landmark has, for a landmark found by association."""
        while self.next_anonymous in self.index:
            self.next_anonymous += 1
        lid = self.next_anonymous
        self.next_anonymous += 1
        return lid

    def initialise(self, lid: int, z_range: float, z_bearing: float, *, var_range: float,
                   var_bearing: float, guard: ekf.Guard) -> None:
        """Map landmark ``lid`` from one (range, bearing) observation (ekf.initialise;
        :class:`ekf.RefusedStepError` from the guard leaves the map unchanged)."""
        self.flush()  # the new rows are made from P's robot rows (and a larger L from P)
        self._ensure_capacity(self.n + 1)
        ekf.initialise(self.x, self.L, self.n, z_range=z_range, z_bearing=z_bearing,
                       var_range=var_range, var_bearing=var_bearing, ws=self.ws,
                       guard=guard, at=self.robot_point)
        if self.fej is not None:
            a = 3 + 2 * self.n
            self.fej.mapped(float(self.x[a]), float(self.x[a + 1]))
        self.index[lid] = self.n
        self.ids.append(lid)
        self.n += 1

    def indices_of(self, ids: Iterable[int]) -> list[int]:
        """The state-order indices of those of ``ids`` in the map, sorted."""
        return sorted(self.index[i] for i in ids if i in self.index)

    def linearisation_points(self) -> dict[str, Any] | None:
        """The FEJ linearisation points (None for the standard EKF, which needs none)."""
        return None if self.fej is None else self.fej.to_dict(self.ids)

    def restore(self, state: SlamState, *, next_anonymous_id: int | None,
                linearisation: dict[str, Any] | None) -> None:
        """Continue from ``state``: the same map, bit for bit, in the buffers an
        uninterrupted run would have by now (16 landmarks doubled as needed), so that
        every later BLAS call sees the same layout. With FEJ, ``linearisation`` is what
        :meth:`linearisation_points` gave; without it the estimates become the first."""
        n = state.n
        capacity = INITIAL_CAPACITY
        while capacity < n:
            capacity *= 2
        size, N = 3 + 2 * capacity, 3 + 2 * n
        self.x = np.zeros(size)
        self.x[0:3] = state.pose
        self.x[3:N] = state.landmarks.reshape(-1)
        self.L = np.zeros((size, size))
        self.L[:N, :N] = state.covariance  # only the lower triangle is read (ekf.py)
        self.ws = ekf.Workspace.for_capacity(size)
        self.capacity = capacity
        self.n = n
        self.ids = [int(i) for i in state.landmark_ids]
        self.index = {lid: k for k, lid in enumerate(self.ids)}
        self.next_anonymous = (self._anonymous_base if next_anonymous_id is None
                               else int(next_anonymous_id))
        if self.fej is not None:
            self.fej = FirstEstimates.from_dict(
                linearisation, ids=self.ids, robot=[float(v) for v in state.pose],
                landmarks=state.landmarks.reshape(-1, 2).tolist())

    def _ensure_capacity(self, n_needed: int) -> None:
        if n_needed <= self.capacity:
            return
        capacity = max(2 * self.capacity, n_needed)
        size, N = 3 + 2 * capacity, self.size
        x = np.zeros(size)
        x[:N] = self.x[:N]
        L = np.zeros((size, size))
        L[:N, :N] = self.L[:N, :N]
        self.x, self.L = x, L
        self.ws = ekf.Workspace.for_capacity(size)
        self.capacity = capacity
        log.debug("state capacity doubled to %d landmarks", capacity)
