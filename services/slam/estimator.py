"""The EKF-SLAM estimator: a thin stateful class over the kernels of :mod:`services.slam.ekf`.

It owns the state buffers (capacity doubled when the map outgrows them, so adding a
landmark does not reallocate every time), maps landmark ids to state order, applies
observation batches one observation at a time (SPEC §4), associates anonymous observations
(:mod:`services.slam.association`), plants a configured fault (:mod:`services.slam.faults`)
and turns its state into a :class:`~common.messages.SlamState`. No I/O here.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.errors import EstimationError
from common.messages import SlamState
from services.slam import association, ekf, faults
from services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")

_INITIAL_CAPACITY = 16  # landmarks; doubled on demand


@dataclass(frozen=True, eq=False)
class ObserveReport:
    """What one observation batch did (arrays are read-only)."""

    observed_ids: np.ndarray  #: int64, landmarks updated or initialised, message order, once
    new_ids: np.ndarray  #: int64, landmarks initialised by this batch
    innovation_ids: np.ndarray  #: int64[k], the landmark of each update, in order
    innovations: np.ndarray  #: float64[k, 2], ν = z − h (m, rad) before each update
    innovation_covariances: np.ndarray  #: float64[k, 2, 2], S of each update
    assigned_ids: np.ndarray  #: int64[m], per observation: the id it was applied to, or −1
    rejected: int  #: observations not applied (ambiguous, or S not positive definite)
    ambiguous: int  #: of those, id −1 observations between the two association thresholds


def _frozen(values: Any, dtype: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    a = np.array(values, dtype=dtype)
    if shape is not None:
        a = a.reshape(shape)
    a.flags.writeable = False
    return a


class Estimator:
    """EKF-SLAM with the SPEC §4 models (see docs/estimator.md)."""

    def __init__(self, settings: EstimatorSettings, *,
                 capacity: int = _INITIAL_CAPACITY) -> None:
        self.settings = settings
        self._var_v = settings.sigma_v ** 2
        self._var_w = settings.sigma_w ** 2
        self._var_r = settings.sigma_range ** 2
        self._var_b = settings.sigma_bearing ** 2
        self._gates = association.Gates(settings.gate_chi2, settings.new_landmark_chi2)
        self._fault = faults.make_fault(settings.fault, settings.faulty_features,
                                        magnitude=settings.fault_magnitude,
                                        onset=settings.fault_onset)
        self._capacity = max(1, int(capacity))
        size = 3 + 2 * self._capacity
        self._x = np.zeros(size)
        self._L = np.zeros((size, size))
        self._ws = ekf.Workspace.for_capacity(size)
        self._x[0:3] = [float(v) for v in settings.initial_pose]
        self._x[2] = float(ekf.wrap_angle(self._x[2]))
        self._L[0:3, 0:3] = np.diag([float(s) ** 2 for s in settings.initial_pose_sigma])
        self._n = 0
        self._ids: list[int] = []
        self._index: dict[int, int] = {}
        self._next_anonymous = settings.anonymous_id_base
        self.refused_updates = 0  #: observations refused because S was not positive definite

    # -- read-only views ---------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of landmarks in the map."""
        return self._n

    @property
    def pose(self) -> np.ndarray:
        """Robot pose (x m, y m, θ rad) in the map frame (a copy)."""
        return self._x[0:3].copy()

    @property
    def landmark_ids(self) -> np.ndarray:
        """Landmark ids, int64[n], in state order (a copy)."""
        return np.array(self._ids, dtype=np.int64)

    @property
    def landmarks(self) -> np.ndarray:
        """Landmark positions [n, 2], m, map frame (a copy)."""
        return self._x[3:3 + 2 * self._n].reshape(self._n, 2).copy()

    @property
    def covariance(self) -> np.ndarray:
        """Full symmetric state covariance [(3+2n), (3+2n)] (a new array)."""
        return ekf.symmetric(self._L, 3 + 2 * self._n)

    @property
    def pose_covariance(self) -> np.ndarray:
        """P_vv, the 3×3 robot pose covariance (a copy; O(1), unlike ``covariance``)."""
        return ekf.symmetric(self._L, 3)

    @property
    def capacity(self) -> int:
        """Landmarks the buffers hold before the next doubling."""
        return self._capacity

    def index_of(self, landmark_id: int) -> int | None:
        """State-order index of a landmark id, or None if it is not in the map."""
        return self._index.get(int(landmark_id))

    # -- events ------------------------------------------------------------------------
    def predict(self, *, v: float, w: float, dt: float, stamp: float) -> None:
        """Apply one odometry step (v m/s, w rad/s held for dt s). Refuses NaN and dt < 0
        with EstimationError, leaving the state unchanged."""
        ekf.check_finite_inputs(v=v, w=w, dt=dt, stamp=stamp)
        if dt < 0:
            raise EstimationError(f"dt must be ≥ 0, got {dt!r}")
        fault = self._fault
        if fault is not None and fault.kind == faults.CROSS_COVARIANCE and fault.active(stamp):
            faults.predict_without_cross_covariance(
                self._x, self._L, self._n, indices=self._faulty_indices(), fraction=fault.magnitude,
                v=v, w=w, dt=dt, var_v=self._var_v, var_w=self._var_w)
            return
        ekf.predict(self._x, self._L, self._n, v=v, w=w, dt=dt, var_v=self._var_v,
                    var_w=self._var_w)

    def observe(self, *, ids: Any, ranges: Any, bearings: Any, stamp: float) -> ObserveReport:
        """Apply one observation batch, one observation at a time in message order.

        A known id updates, an unknown id is initialised (and not also used to update), id
        −1 is associated (:mod:`services.slam.association`). Malformed input (NaN, negative
        range, ids < −1, mismatched lengths) raises EstimationError before anything changes.
        """
        id_list, range_list, bearing_list = self._check_batch(ids, ranges, bearings, stamp)
        observed: list[int] = []
        new: list[int] = []
        innovation_ids: list[int] = []
        innovations: list[tuple[float, float]] = []
        covariances: list[tuple[float, float, float, float]] = []
        assigned: list[int] = []
        rejected = ambiguous = 0
        for lid, z_r, z_b in zip(id_list, range_list, bearing_list, strict=True):
            if lid == -1:
                decision = association.decide(association.mahalanobis_all(
                    self._x, self._L, self._n, z_range=z_r, z_bearing=z_b,
                    var_range=self._var_r, var_bearing=self._var_b), self._gates)
                if decision.kind == association.AMBIGUOUS:
                    log.debug("anonymous observation (%.3f m, %.3f rad) ambiguous: d² = %.2f",
                              z_r, z_b, decision.d2)
                    rejected += 1
                    ambiguous += 1
                    assigned.append(-1)
                    continue
                lid = (self._ids[decision.index] if decision.kind == association.MATCH
                       else self._fresh_anonymous_id())
            j = self._index.get(lid)
            if j is None:
                self._initialise(lid, z_r, z_b)
                new.append(lid)
            else:
                try:
                    out = ekf.update(self._x, self._L, self._n, j, z_range=z_r, z_bearing=z_b,
                                     var_range=self._var_r, var_bearing=self._var_b,
                                     ws=self._ws)
                except ekf.SingularInnovationError as exc:
                    self._log_refused(lid, exc)
                    rejected += 1
                    assigned.append(-1)
                    continue
                nu_r, nu_b, s00, s01, s11 = out
                innovation_ids.append(lid)
                innovations.append((nu_r, nu_b))
                covariances.append((s00, s01, s01, s11))
            assigned.append(lid)
            if lid not in observed:
                observed.append(lid)
        fault = self._fault
        if (fault is not None and fault.kind == faults.MAP_UPDATE and innovation_ids
                and fault.active(stamp)):
            faults.inflate_map_covariance(self._L, self._faulty_indices(), fault.magnitude)
        k = len(innovation_ids)
        return ObserveReport(
            observed_ids=_frozen(observed, np.int64), new_ids=_frozen(new, np.int64),
            innovation_ids=_frozen(innovation_ids, np.int64),
            innovations=_frozen(innovations, np.float64, (k, 2)),
            innovation_covariances=_frozen(covariances, np.float64, (k, 2, 2)),
            assigned_ids=_frozen(assigned, np.int64), rejected=rejected, ambiguous=ambiguous)

    def to_state(self, *, seq: int, stamp: float, step: str,
                 report: ObserveReport | None = None, epoch: int = 0,
                 input_stamp: float | None = None,
                 origin_stamp: float | None = None) -> SlamState:
        """The current state as a SlamState message (covariance materialised once)."""
        n = self._n
        cov = ekf.symmetric(self._L, 3 + 2 * n)
        cov.flags.writeable = False  # the message keeps it without another copy
        extra: dict[str, Any] = {}
        if report is not None:
            extra["observed_ids"] = report.observed_ids
            extra["new_ids"] = report.new_ids
            if self.settings.publish_innovations:
                extra["innovation_ids"] = report.innovation_ids
                extra["innovations"] = report.innovations
                extra["innovation_covariances"] = report.innovation_covariances
        return SlamState(robot=self.settings.robot, seq=seq, stamp=stamp, step=step,
                         pose=self.pose, landmark_ids=self.landmark_ids,
                         landmarks=self.landmarks, covariance=cov, epoch=epoch,
                         input_stamp=input_stamp, origin_stamp=origin_stamp, **extra)

    # -- checkpoints -------------------------------------------------------------------
    @property
    def next_anonymous_id(self) -> int:
        """The id the next landmark found by association gets (kept by checkpoints)."""
        return self._next_anonymous

    def restore(self, state: SlamState, *, next_anonymous_id: int | None = None) -> None:
        """Continue from ``state`` (a checkpoint): the same map, bit for bit.

        The buffers get the capacity an uninterrupted run would have by now (16 doubled
        as needed), so that every later BLAS call sees the same layout.
        """
        n = state.n
        capacity = _INITIAL_CAPACITY
        while capacity < n:
            capacity *= 2
        size, N = 3 + 2 * capacity, 3 + 2 * n
        self._x = np.zeros(size)
        self._x[0:3] = state.pose
        self._x[3:N] = state.landmarks.reshape(-1)
        self._L = np.zeros((size, size))
        self._L[:N, :N] = state.covariance  # only the lower triangle is read (ekf.py)
        self._ws = ekf.Workspace.for_capacity(size)
        self._capacity = capacity
        self._n = n
        self._ids = [int(i) for i in state.landmark_ids]
        self._index = {lid: k for k, lid in enumerate(self._ids)}
        self._next_anonymous = (self.settings.anonymous_id_base if next_anonymous_id is None
                                else int(next_anonymous_id))

    # -- internals ---------------------------------------------------------------------
    @staticmethod
    def _check_batch(ids: Any, ranges: Any, bearings: Any,
                     stamp: float) -> tuple[list[int], list[float], list[float]]:
        """Validated plain lists (the loop runs on Python scalars; builtins over small
        lists are cheaper than a numpy call per check)."""
        ekf.check_finite_inputs(stamp=stamp)
        ids_a = np.asarray(ids)
        if ids_a.ndim != 1 or (ids_a.size and ids_a.dtype.kind not in "iu"):
            raise EstimationError(f"ids must be a 1-D integer array, got dtype {ids_a.dtype} "
                             f"shape {ids_a.shape}")
        ranges_a = np.asarray(ranges, dtype=np.float64)
        bearings_a = np.asarray(bearings, dtype=np.float64)
        if ranges_a.shape != ids_a.shape or bearings_a.shape != ids_a.shape:
            raise EstimationError(f"ids, ranges and bearings must have the same length, got "
                             f"{ids_a.shape}, {ranges_a.shape}, {bearings_a.shape}")
        id_list: list[int] = ids_a.tolist()
        range_list: list[float] = ranges_a.tolist()
        bearing_list: list[float] = bearings_a.tolist()
        if not (all(map(math.isfinite, range_list)) and all(map(math.isfinite, bearing_list))):
            raise EstimationError("ranges and bearings must be finite (NaN or infinity received)")
        if id_list:
            if min(range_list) < 0:
                raise EstimationError("ranges must be ≥ 0")
            if min(id_list) < -1:
                raise EstimationError(f"ids must be ≥ −1, got {min(id_list)}")
        return id_list, range_list, bearing_list

    def _log_refused(self, lid: int, exc: Exception) -> None:
        self.refused_updates += 1
        count = self.refused_updates
        if count == 1 or count % 100 == 0:  # a broken P refuses every update: do not flood
            log.warning("observation of landmark %d not applied (%d so far): %s", lid, count, exc)

    def _fresh_anonymous_id(self) -> int:
        while self._next_anonymous in self._index:
            self._next_anonymous += 1
        lid = self._next_anonymous
        self._next_anonymous += 1
        return lid

    def _initialise(self, lid: int, z_range: float, z_bearing: float) -> None:
        self._ensure_capacity(self._n + 1)
        ekf.initialise(self._x, self._L, self._n, z_range=z_range, z_bearing=z_bearing,
                       var_range=self._var_r, var_bearing=self._var_b, ws=self._ws)
        self._index[lid] = self._n
        self._ids.append(lid)
        self._n += 1

    def _ensure_capacity(self, n_needed: int) -> None:
        if n_needed <= self._capacity:
            return
        capacity = max(2 * self._capacity, n_needed)
        size, N = 3 + 2 * capacity, 3 + 2 * self._n
        x = np.zeros(size)
        x[:N] = self._x[:N]
        L = np.zeros((size, size))
        L[:N, :N] = self._L[:N, :N]
        self._x, self._L = x, L
        self._ws = ekf.Workspace.for_capacity(size)
        self._capacity = capacity
        log.debug("state capacity doubled to %d landmarks", capacity)

    def _faulty_indices(self) -> list[int]:
        assert self._fault is not None
        return sorted(self._index[i] for i in self._fault.feature_ids if i in self._index)
