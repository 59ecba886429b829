"""The EKF-SLAM estimator: a thin stateful class over the kernels of
:mod:`slamlens.services.slam.ekf`.

It owns the state buffers (capacity doubled when the map outgrows them, so adding a
landmark does not reallocate every time), maps landmark ids to state order, applies
observation batches one observation at a time (docs/estimator.md), associates anonymous observations
(:mod:`slamlens.services.slam.association`), plants a configured fault
(:mod:`slamlens.services.slam.faults`)
and turns its state into a :class:`~slamlens.common.messages.SlamState`. No I/O here.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from slamlens.common.arrays import RecycledBuffers
from slamlens.common.errors import EstimationError
from slamlens.common.messages import SlamState, finite_by_construction
from slamlens.services.slam import association, ekf, faults
from slamlens.services.slam.linearisation import FEJ, FirstEstimates, fused
from slamlens.services.slam.observe_report import BatchRecord, ObserveReport, Refusal
from slamlens.services.slam.plausibility import (
    Bounds,
    ImplausibleInputError,
    InputGates,
    checked_batch,
    describe_batch,
)
from slamlens.services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")

_INITIAL_CAPACITY = 16  # landmarks; doubled on demand


class Estimator:
    """EKF-SLAM with the standard model (docs/estimator.md)."""

    def __init__(self, settings: EstimatorSettings, *,
                 capacity: int = _INITIAL_CAPACITY) -> None:
        self.settings = settings
        self._var_v = settings.sigma_v ** 2
        self._var_w = settings.sigma_w ** 2
        self._var_r = settings.sigma_range ** 2
        self._var_b = settings.sigma_bearing ** 2
        # opt-in range noise terms: variance (k·r)² and (k·r·φ²)² on top of σr²
        self._q_range = settings.sigma_range_per_m ** 2
        self._q_off_axis = settings.sigma_range_off_axis ** 2
        self._gates = association.Gates(settings.gate_chi2, settings.new_landmark_chi2)
        self._fault = faults.make_fault(settings.fault, settings.faulty_features,
                                        magnitude=settings.fault_magnitude,
                                        onset=settings.fault_onset)
        # the opt-in motion noise terms (0 = docs/estimator.md exactly), as variances per m / rad
        self._q_dist = settings.sigma_distance ** 2
        self._q_turn = settings.sigma_turn ** 2
        self._q_head_dist = settings.sigma_heading_per_distance ** 2
        self._motion_extra = bool(self._q_dist or self._q_turn or self._q_head_dist)
        self._gate = float(settings.innovation_gate_chi2)
        # a planted fault breaks PSD on purpose: then the guard checks finiteness only
        self._guard = ekf.Guard(psd_rtol=None if self._fault is not None
                                else settings.guard_rtol)
        self.gates = InputGates(Bounds(
            max_dt_s=settings.max_dt_s, max_speed=settings.max_speed,
            max_turn_rate=settings.max_turn_rate, max_range=settings.max_range,
            max_abs_bearing=settings.max_abs_bearing,
            max_stamp_jump_s=settings.max_stamp_jump_s, stamp_resync=settings.stamp_resync,
            max_batch=settings.max_batch, max_landmarks=settings.max_landmarks))
        self._capacity = max(1, int(capacity))
        size = 3 + 2 * self._capacity
        self._x = np.zeros(size)
        self._L = np.zeros((size, size))
        self._ws = ekf.Workspace.for_capacity(size)
        self._x[0:3] = [float(v) for v in settings.initial_pose]
        self._x[2] = float(ekf.wrap_angle(self._x[2]))
        self._L[0:3, 0:3] = np.diag([float(s) ** 2 for s in settings.initial_pose_sigma])
        #: the FEJ linearisation points (None: the standard EKF, Jacobians at the estimates)
        self._fej = (FirstEstimates(self._x[0], self._x[1])
                     if settings.linearisation == FEJ else None)
        self._n = 0
        self._ids: list[int] = []
        self._index: dict[int, int] = {}
        self._next_anonymous = settings.anonymous_id_base
        self.refused_updates = 0  #: observations refused because S was not positive definite
        self.gated = 0  #: observations of known landmarks refused by the innovation gate
        #: inputs refused whole (plausibility reasons) and steps refused by the guard
        #: ("non-finite", "not-psd"), by reason
        self.refusals: Counter[str] = Counter()
        self.last_refusal: Refusal | None = None
        #: the covariance of the last state made (to_state), and whether anything but the
        #: robot rows/columns may have changed since (then it is materialised again whole)
        self._published: np.ndarray | None = None
        #: predict states whose matrix was the last state's, patched in place (to_state)
        self.predicts_in_place = 0
        self._map_dirty = True
        self._buffers = RecycledBuffers(keep=4)

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
        """Apply one odometry step (v m/s, w rad/s held for dt s).

        Refuses with EstimationError, leaving the state unchanged: NaN and dt < 0; an input
        outside a plausibility bound (:class:`ImplausibleInputError`, counted in
        ``refusals`` by reason); a step the guard refuses (:class:`ekf.RefusedStepError`).
        """
        ekf.check_finite_inputs(v=v, w=w, dt=dt, stamp=stamp)
        if dt < 0:
            raise EstimationError(f"dt must be ≥ 0, got {dt!r}")
        try:
            self.gates.check_odometry(v=v, w=w, dt=dt, stamp=stamp)
            extra_qv = extra_qw = 0.0
            if self._motion_extra:
                dist, turn = abs(v * dt), abs(w * dt)
                extra_qv = self._q_dist * dist
                extra_qw = self._q_turn * turn + self._q_head_dist * dist
            fault = self._fault
            if fault is not None and fault.kind == faults.CROSS_COVARIANCE and \
                    fault.active(stamp):
                faults.predict_without_cross_covariance(
                    self._x, self._L, self._n, indices=self._faulty_indices(),
                    fraction=fault.magnitude, v=v, w=w, dt=dt, var_v=self._var_v,
                    var_w=self._var_w, extra_qv=extra_qv, extra_qw=extra_qw,
                    guard=self._guard, ws=self._ws,
                    at=None if self._fej is None else self._fej.robot)
            else:
                ekf.predict(self._x, self._L, self._n, v=v, w=w, dt=dt, var_v=self._var_v,
                            var_w=self._var_w, extra_qv=extra_qv, extra_qw=extra_qw,
                            guard=self._guard, ws=self._ws,
                            at=None if self._fej is None else self._fej.robot)
        except (ImplausibleInputError, ekf.RefusedStepError) as exc:
            self._refuse(exc.reason, str(exc), stamp,
                         f"odometry dt={dt!r} v={v!r} w={w!r}")
            raise
        if self._fej is not None:
            self._fej.propagated(float(self._x[0]), float(self._x[1]))
        self.gates.applied(stamp)

    def observe(self, *, ids: Any, ranges: Any, bearings: Any, stamp: float) -> ObserveReport:
        """Apply one observation batch, one observation at a time in message order.

        A known id updates, an unknown id is initialised (and not also used to update), id
        −1 is associated (:mod:`slamlens.services.slam.association`). Malformed input (NaN, negative
        range, ids < −1, mismatched lengths) raises EstimationError before anything changes,
        and so does a batch outside a plausibility bound (:class:`ImplausibleInputError`).
        A known id whose NIS is above ``innovation_gate_chi2`` is not applied (``gated``);
        a step the guard refuses is skipped (``refused``), and if the guard refused every
        observation of the batch, :class:`ekf.RefusedStepError` is raised (nothing changed).
        """
        self._map_dirty = True  # an update touches the whole matrix
        id_list, range_list, bearing_list = checked_batch(ids, ranges, bearings, stamp)
        try:
            self.gates.check_batch(
                ranges=range_list, bearings=bearing_list, landmarks=self._n, stamp=stamp,
                new_ids=len({i for i in id_list if i >= 0 and i not in self._index}))
        except ImplausibleInputError as exc:
            self._refuse(exc.reason, str(exc), stamp, describe_batch(
                id_list, range_list, bearing_list))
            raise
        batch = BatchRecord()
        try:
            for lid, z_r, z_b in zip(id_list, range_list, bearing_list, strict=True):
                self._observe_one(batch, lid, z_r, z_b, stamp)
            if batch.unmapped:
                self._map_unmapped(batch, stamp)
        finally:
            self._flush()  # the batch's updates are in x; their downdates held back (ekf.py)
        if batch.refused and batch.refused == len(id_list):
            raise ekf.RefusedStepError(
                self.last_refusal.reason if self.last_refusal else "non-finite",
                f"every observation of the batch ({batch.refused}) was refused by the guard")
        fault = self._fault
        if (fault is not None and fault.kind == faults.MAP_UPDATE and batch.innovation_ids
                and fault.active(stamp)):
            faults.inflate_map_covariance(self._L, self._faulty_indices(), fault.magnitude)
        self.gates.applied(stamp)
        return batch.report()

    def _observe_one(self, batch: BatchRecord, lid: int, z_r: float, z_b: float,
                     stamp: float) -> None:
        """One observation of a batch: associated if anonymous, then an update or a new
        landmark; what happened goes into ``batch``."""
        var_r = self._range_variance(z_r, z_b)
        if lid == -1:
            found = self._associate(batch, z_r, z_b, var_r, stamp)
            if found is None:
                batch.assigned.append(-1)
                return
            lid = found
        j = self._index.get(lid)
        if j is None and self._fej is not None:
            batch.hold_new(lid, z_r, z_b, var_r)  # FEJ: mapped after the batch's updates
            return
        try:
            if j is None:
                self._initialise(lid, z_r, z_b, var_r)
                batch.new.append(lid)
            else:
                out = ekf.update(self._x, self._L, self._n, j, z_range=z_r, z_bearing=z_b,
                                 var_range=var_r, var_bearing=self._var_b, ws=self._ws,
                                 gate=self._gate, guard=self._guard, defer=True,
                                 at=None if self._fej is None else self._fej.update_point(j))
        except ekf.GatedObservationError as exc:
            self.gated += 1
            batch.gated.append((lid, z_r, z_b, exc.nis))
            batch.rejected += 1
            batch.assigned.append(-1)
            return
        except ekf.RefusedStepError as exc:  # the guard: an update or a new landmark
            self._refuse(exc.reason, str(exc), stamp,
                         f"observation id={lid} range={z_r!r} bearing={z_b!r}")
            batch.rejected += 1
            batch.refused += 1
            batch.assigned.append(-1)
            return
        except ekf.SingularInnovationError as exc:
            self._log_refused(lid, exc)
            batch.rejected += 1
            batch.assigned.append(-1)
            return
        if j is not None:
            nu_r, nu_b, s00, s01, s11 = out
            batch.innovation_ids.append(lid)
            batch.innovations.append((nu_r, nu_b))
            batch.covariances.append((s00, s01, s01, s11))
        batch.assigned.append(lid)
        if lid not in batch.observed:
            batch.observed.append(lid)

    def _map_unmapped(self, batch: BatchRecord, stamp: float) -> None:
        """FEJ: the batch's new landmarks, mapped after its updates (so that no update of
        the batch moves them: a state publishes a new landmark at its first estimate, which
        a monitor takes as its linearisation point); sightings of one landmark fused."""
        for lid, sightings in batch.unmapped.items():
            z_r, z_b, var_r, var_b = fused(sightings, self._var_b)
            try:
                self._initialise(lid, z_r, z_b, var_r, var_b)
            except ekf.RefusedStepError as exc:
                self._refuse(exc.reason, str(exc), stamp,
                             f"observation id={lid} range={z_r!r} bearing={z_b!r}")
                batch.drop_new(lid, refused=True)
                continue
            batch.new.append(lid)

    def _associate(self, batch: BatchRecord, z_r: float, z_b: float, var_r: float,
                   stamp: float) -> int | None:
        """The id an anonymous observation is (a landmark's, or a fresh one for a new
        landmark), or None when it is not applied (ambiguous, or the map is full)."""
        self._flush()  # association reads P
        decision = association.decide(association.mahalanobis_all(
            self._x, self._L, self._n, z_range=z_r, z_bearing=z_b, var_range=var_r,
            var_bearing=self._var_b), self._gates)
        if decision.kind == association.AMBIGUOUS:
            log.debug("anonymous observation (%.3f m, %.3f rad) ambiguous: d² = %.2f",
                      z_r, z_b, decision.d2)
            batch.rejected += 1
            batch.ambiguous += 1
            return None
        if decision.kind != association.MATCH and self.gates.map_full(self._n):
            self._refuse("map_size", f"the map holds {self._n} landmarks, the bound: an "
                                     "anonymous observation was not mapped",
                         stamp, f"observation range={z_r!r} bearing={z_b!r}")
            batch.rejected += 1
            return None
        return (self._ids[decision.index] if decision.kind == association.MATCH
                else self._fresh_anonymous_id())

    def to_state(self, *, seq: int, stamp: float, step: str,
                 report: ObserveReport | None = None, epoch: int = 0,
                 input_stamp: float | None = None, origin_stamp: float | None = None,
                 counts: Mapping[str, float] | None = None) -> SlamState:
        """The current state as a SlamState message (covariance materialised once);
        ``counts`` are more running counts for its ``diagnostics`` (the service's)."""
        n = self._n
        N = 3 + 2 * n
        # backed by a bytearray: shared memory takes it with one copy (common/bus.py);
        # recycled once no message or view of an earlier state holds it any more
        previous, self._published = self._published, None
        if not self._map_dirty and previous is not None and previous.shape == (N, N):
            # only predicts since the last state: P_mm is as it was (docs/estimator.md). If nothing
            # holds the last state's matrix any more (its message went out: a large state
            # is sent from shared memory and a get answers with that), its robot rows and
            # columns are patched in place, O(N); else it is copied with them patched
            reclaimed = self._buffers.reclaim(previous, holders=1)
            if reclaimed is not None:
                cov = ekf.robot_rows_into(self._L, N, reclaimed)
                self.predicts_in_place += 1
            else:
                cov = self._buffers.array((N, N), "<f8")
                ekf.symmetric_after_predict(self._L, N, previous, out=cov)
        else:
            cov = self._buffers.array((N, N), "<f8")
            ekf.symmetric(self._L, N, out=cov)
        del previous
        cov.flags.writeable = False  # the message keeps it without another copy
        self._published, self._map_dirty = cov, False
        extra: dict[str, Any] = {}
        if report is not None:
            extra["observed_ids"] = report.observed_ids
            extra["new_ids"] = report.new_ids
            if self.settings.publish_innovations:
                extra["innovation_ids"] = report.innovation_ids
                extra["innovations"] = report.innovations
                extra["innovation_covariances"] = report.innovation_covariances
            if report.gated:
                extra["gated_ids"] = report.gated_ids
                extra["gated_observations"] = report.gated_observations
                extra["gated_nis"] = report.gated_nis
        # the guard refuses any step that would make P non-finite (|P_ij| ≤ 1e300, PSD to
        # rounding: docs/estimator.md), so the message need not sum 32 MB to know it; a
        # planted fault breaks PSD on purpose, and then the message checks P in full
        with finite_by_construction(cov if self._guard.psd_rtol is not None else None):
            return SlamState(robot=self.settings.robot, seq=seq, stamp=stamp, step=step,
                             pose=self.pose, landmark_ids=self.landmark_ids,
                             landmarks=self.landmarks, covariance=cov, epoch=epoch,
                             input_stamp=input_stamp, origin_stamp=origin_stamp,
                             diagnostics={**self.diagnostics(), **(counts or {})}, **extra)

    def diagnostics(self) -> dict[str, float]:
        """Running counts published in every state (docs/protocol.md ``diagnostics``):
        ``gated``, ``refused_updates`` (S not PD) and ``refused.<reason>`` per reason; and
        ``linearisation.fej`` = 1 when the Jacobians are FEJ's (the monitor then holds the
        filter to FEJ's theorems: docs/monitor.md)."""
        out = {"gated": float(self.gated), "refused_updates": float(self.refused_updates)}
        for reason, count in sorted(self.refusals.items()):
            out[f"refused.{reason}"] = float(count)
        if self._fej is not None:
            out["linearisation.fej"] = 1.0
        return out

    def linearisation_points(self) -> dict[str, Any] | None:
        """What a checkpoint must keep besides the state for the map to continue exactly:
        the FEJ linearisation points (None for the standard EKF, which needs none)."""
        return None if self._fej is None else self._fej.to_dict(self._ids)

    # -- checkpoints -------------------------------------------------------------------
    @property
    def next_anonymous_id(self) -> int:
        """The id the next landmark found by association gets (kept by checkpoints)."""
        return self._next_anonymous

    def restore(self, state: SlamState, *, next_anonymous_id: int | None = None,
                linearisation: dict[str, Any] | None = None) -> None:
        """Continue from ``state`` (a checkpoint): the same map, bit for bit.

        The buffers get the capacity an uninterrupted run would have by now (16 doubled
        as needed), so that every later BLAS call sees the same layout. With FEJ,
        ``linearisation`` is what :meth:`linearisation_points` gave when the checkpoint was
        made; without it the estimates of ``state`` become the first estimates.
        """
        n = state.n
        capacity = _INITIAL_CAPACITY
        while capacity < n:
            capacity *= 2
        size, N = 3 + 2 * capacity, 3 + 2 * n
        self._x = np.zeros(size)
        self._x[0:3] = state.pose
        self._x[3:N] = state.landmarks.reshape(-1)
        self._map_dirty = True
        self._L = np.zeros((size, size))
        self._L[:N, :N] = state.covariance  # only the lower triangle is read (ekf.py)
        self._ws = ekf.Workspace.for_capacity(size)
        self._capacity = capacity
        self._n = n
        self._ids = [int(i) for i in state.landmark_ids]
        self._index = {lid: k for k, lid in enumerate(self._ids)}
        self._next_anonymous = (self.settings.anonymous_id_base if next_anonymous_id is None
                                else int(next_anonymous_id))
        if self._fej is not None:
            self._fej = FirstEstimates.from_dict(
                linearisation, ids=self._ids, robot=[float(v) for v in state.pose],
                landmarks=state.landmarks.reshape(-1, 2).tolist())
        self.gates.restore(None if state.step == "init" else
                           float(state.input_stamp if state.input_stamp is not None
                                 else state.stamp))
        counts = state.diagnostics or {}
        self.gated = int(counts.get("gated", 0))
        self.refused_updates = int(counts.get("refused_updates", 0))
        self.refusals = Counter({k.partition(".")[2]: int(v) for k, v in counts.items()
                                 if k.startswith("refused.")})

    # -- internals ---------------------------------------------------------------------
    def _range_variance(self, z_range: float, z_bearing: float) -> float:
        """σr² (docs/estimator.md), plus the opt-in terms (k·r)² and (k·r·φ²)² when configured."""
        var = self._var_r
        if self._q_range:
            var += self._q_range * z_range * z_range
        if self._q_off_axis:
            off = z_range * z_bearing * z_bearing
            var += self._q_off_axis * off * off
        return var

    def _refuse(self, reason: str, detail: str, stamp: float, what: str) -> None:
        self.refusals[reason] += 1
        self.last_refusal = Refusal(reason=reason, detail=detail, stamp=stamp, input=what)

    def _log_refused(self, lid: int, exc: Exception) -> None:
        self.refused_updates += 1
        count = self.refused_updates
        if count == 1 or count % 100 == 0:  # a broken P refuses every update: do not flood
            log.warning("observation of landmark %d not applied (%d so far): %s", lid, count, exc)

    def _flush(self) -> None:
        """Apply the downdates held back by this batch's updates (ekf.update ``defer``):
        after it, ``_L`` is P again for anything that reads it."""
        ekf.flush(self._L, 3 + 2 * self._n, self._ws)

    def _fresh_anonymous_id(self) -> int:
        while self._next_anonymous in self._index:
            self._next_anonymous += 1
        lid = self._next_anonymous
        self._next_anonymous += 1
        return lid

    def _initialise(self, lid: int, z_range: float, z_bearing: float, var_range: float,
                    var_bearing: float | None = None) -> None:
        self._flush()  # the new rows are made from P's robot rows (and a larger L from P)
        self._ensure_capacity(self._n + 1)
        ekf.initialise(self._x, self._L, self._n, z_range=z_range, z_bearing=z_bearing,
                       var_range=var_range,
                       var_bearing=self._var_b if var_bearing is None else var_bearing,
                       ws=self._ws,
                       guard=self._guard, at=None if self._fej is None else self._fej.robot)
        if self._fej is not None:
            a = 3 + 2 * self._n
            self._fej.mapped(float(self._x[a]), float(self._x[a + 1]))
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
