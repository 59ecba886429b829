"""The EKF-SLAM estimator: a thin stateful class over the kernels of
:mod:`slamlens.services.slam.ekf`, the one face its callers see.

:class:`Estimator` applies odometry and observation batches (docs/estimator.md), plants a
configured fault (:mod:`slamlens.services.slam.faults`) and turns its state into a
:class:`~slamlens.common.messages.SlamState`. Its collaborators each do one job: the state
buffers and the map's ids (:mod:`~slamlens.services.slam.state_store`), the input checks
and refusal counts (:mod:`~slamlens.services.slam.input_checks`), the noise model
(:mod:`~slamlens.services.slam.noise_model`), a batch's association, updates and report
(:mod:`~slamlens.services.slam.observe_batch`) and the published covariance
(:mod:`~slamlens.services.slam.state_covariance`). No I/O here.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from slamlens.common.messages import (
    Observations,
    Odometry,
    SlamState,
    finite_by_construction,
)
from slamlens.services.slam import association, ekf, faults
from slamlens.services.slam.input_checks import InputChecks, odometry_text
from slamlens.services.slam.noise_model import NoiseModel
from slamlens.services.slam.observe_batch import BatchApplier
from slamlens.services.slam.observe_report import ObserveReport, Refusal
from slamlens.services.slam.plausibility import InputGates
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.state_covariance import PublishedCovariance
from slamlens.services.slam.state_store import INITIAL_CAPACITY, StateStore


class Estimator:
    """EKF-SLAM with the standard model (docs/estimator.md)."""

    def __init__(self, settings: EstimatorSettings, *,
                 capacity: int = INITIAL_CAPACITY) -> None:
        self.settings = settings
        self.noise = NoiseModel.of(settings)
        self._fault = faults.make_fault(settings.fault, settings.faulty_features,
                                        magnitude=settings.fault_magnitude,
                                        onset=settings.fault_onset)
        # a planted fault breaks PSD on purpose: then the guard checks finiteness only
        self._guard = ekf.Guard(psd_rtol=None if self._fault is not None
                                else settings.guard_rtol)
        self.checks = InputChecks(settings)  #: the input checks and refusal counts
        self.store = StateStore(settings, capacity=capacity)  #: x, L and the map's ids
        self.published = PublishedCovariance()  #: the covariance of the states made
        self._batches = BatchApplier(
            self.store, self.checks, self.noise,
            gates=association.Gates(settings.gate_chi2, settings.new_landmark_chi2),
            innovation_gate=float(settings.innovation_gate_chi2), guard=self._guard,
            iterations=settings.update_iterations)

    # -- read-only views ---------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of landmarks in the map."""
        return self.store.n

    @property
    def pose(self) -> np.ndarray:
        """Robot pose (x m, y m, θ rad) in the map frame (a copy)."""
        return self.store.x[0:3].copy()

    @property
    def landmark_ids(self) -> np.ndarray:
        """Landmark ids, int64[n], in state order (a copy)."""
        return np.array(self.store.ids, dtype=np.int64)

    @property
    def landmarks(self) -> np.ndarray:
        """Landmark positions [n, 2], m, map frame (a copy)."""
        n = self.store.n
        return self.store.x[3:3 + 2 * n].reshape(n, 2).copy()

    @property
    def covariance(self) -> np.ndarray:
        """Full symmetric state covariance [(3+2n), (3+2n)] (a new array)."""
        return ekf.symmetric(self.store.L, self.store.size)

    @property
    def pose_covariance(self) -> np.ndarray:
        """P_vv, the 3×3 robot pose covariance (a copy; O(1), unlike ``covariance``)."""
        return ekf.symmetric(self.store.L, 3)

    @property
    def capacity(self) -> int:
        """Landmarks the buffers hold before the next doubling."""
        return self.store.capacity

    def index_of(self, landmark_id: int) -> int | None:
        """State-order index of a landmark id, or None if it is not in the map."""
        return self.store.index.get(int(landmark_id))

    @property
    def gates(self) -> InputGates:
        """The plausibility gates (their bounds, the stamp resyncs)."""
        return self.checks.gates

    @property
    def refusals(self) -> Counter[str]:
        """Inputs refused whole (plausibility reasons) and steps refused by the guard
        ("non-finite", "not-psd"), by reason."""
        return self.checks.refusals

    @property
    def last_refusal(self) -> Refusal | None:
        """The last input or step refused, and why."""
        return self.checks.last_refusal

    @property
    def gated(self) -> int:
        """Observations of known landmarks refused by the innovation gate."""
        return self.checks.gated

    @property
    def refused_updates(self) -> int:
        """Observations refused because S was not positive definite."""
        return self.checks.refused_updates

    @property
    def predicts_in_place(self) -> int:
        """Predict states whose matrix was the last state's, patched in place."""
        return self.published.predicts_in_place

    # -- events ------------------------------------------------------------------------
    def predict(self, *, v: float, w: float, dt: float, stamp: float) -> None:
        """Apply one odometry step (v m/s, w rad/s held for dt s).

        Refuses with EstimationError, leaving the state unchanged: NaN and dt < 0; an input
        outside a plausibility bound (:class:`ImplausibleInputError`, counted in
        ``refusals`` by reason); a step the guard refuses (:class:`ekf.RefusedStepError`).
        """
        self.checks.odometry(v=v, w=w, dt=dt, stamp=stamp)
        store, noise = self.store, self.noise
        extra_qv, extra_qw = noise.motion_extra(v, w, dt)
        fault = self._fault
        try:
            if fault is not None and fault.kind == faults.CROSS_COVARIANCE and \
                    fault.active(stamp):
                faults.predict_without_cross_covariance(
                    store.x, store.L, store.n, indices=store.indices_of(fault.feature_ids),
                    fraction=fault.magnitude, v=v, w=w, dt=dt, var_v=noise.var_v,
                    var_w=noise.var_w, extra_qv=extra_qv, extra_qw=extra_qw,
                    guard=self._guard, ws=store.ws, at=store.robot_point)
            else:
                ekf.predict(store.x, store.L, store.n, v=v, w=w, dt=dt, var_v=noise.var_v,
                            var_w=noise.var_w, extra_qv=extra_qv, extra_qw=extra_qw,
                            guard=self._guard, ws=store.ws, at=store.robot_point)
        except ekf.RefusedStepError as exc:
            self.checks.refuse(exc.reason, str(exc), stamp, odometry_text(v, w, dt))
            raise
        if store.fej is not None:
            store.fej.propagated(float(store.x[0]), float(store.x[1]))
        self.checks.applied(stamp)

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
        self.published.dirty = True  # an update touches the whole matrix
        id_list, range_list, bearing_list = self.checks.batch(
            ids, ranges, bearings, stamp, landmarks=self.store.n, index=self.store.index)
        batch = self._batches.apply(id_list, range_list, bearing_list, stamp)
        if batch.refused and batch.refused == len(id_list):
            last = self.checks.last_refusal
            raise ekf.RefusedStepError(
                last.reason if last else "non-finite",
                f"every observation of the batch ({batch.refused}) was refused by the guard")
        fault = self._fault
        if (fault is not None and fault.kind == faults.MAP_UPDATE and batch.innovation_ids
                and fault.active(stamp)):
            faults.inflate_map_covariance(self.store.L, self.store.indices_of(
                fault.feature_ids), fault.magnitude)
        self.checks.applied(stamp)
        return batch.report()

    def apply(self, message: Odometry | Observations) -> ObserveReport | None:
        """One input of either kind: an odometry step (:meth:`predict`; None) or an
        observation batch (:meth:`observe`; its report). Refuses as those do."""
        if isinstance(message, Odometry):
            self.predict(v=message.v, w=message.w, dt=message.dt, stamp=message.stamp)
            return None
        return self.observe(ids=message.ids, ranges=message.ranges, bearings=message.bearings,
                            stamp=message.stamp)

    def to_state(self, *, seq: int, stamp: float, step: str,
                 report: ObserveReport | None = None, epoch: int = 0,
                 input_stamp: float | None = None, origin_stamp: float | None = None,
                 counts: Mapping[str, float] | None = None) -> SlamState:
        """The current state as a SlamState message (covariance materialised once);
        ``counts`` are more running counts for its ``diagnostics`` (the service's)."""
        cov = self.published.materialise(self.store.L, self.store.size)
        extra = ({} if report is None else
                 report.state_fields(innovations=self.settings.publish_innovations))
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
        ``linearisation.fej`` = 1 when the filter keeps FEJ's linearisation points and
        unobservable directions (``fej`` and ``oc``), ``linearisation.invariant`` = 1 for
        the invariant EKF: the monitor then holds it to their theorems (docs/monitor.md)."""
        out = self.checks.diagnostics()
        if self.store.fej is not None:
            out["linearisation.fej"] = 1.0
        if self.store.invariant:
            out["linearisation.invariant"] = 1.0
        return out

    def linearisation_points(self) -> dict[str, Any] | None:
        """What a checkpoint must keep besides the state for the map to continue exactly:
        the FEJ linearisation points (None for the standard EKF, which needs none)."""
        return self.store.linearisation_points()

    # -- checkpoints -------------------------------------------------------------------
    @property
    def next_anonymous_id(self) -> int:
        """The id the next landmark found by association gets (kept by checkpoints)."""
        return self.store.next_anonymous

    def restore(self, state: SlamState, *, next_anonymous_id: int | None = None,
                linearisation: dict[str, Any] | None = None) -> None:
        """Continue from ``state`` (a checkpoint): the same map, bit for bit.

        The buffers get the capacity an uninterrupted run would have by now (16 doubled
        as needed), so that every later BLAS call sees the same layout. With FEJ,
        ``linearisation`` is what :meth:`linearisation_points` gave when the checkpoint was
        made; without it the estimates of ``state`` become the first estimates.
        """
        self.store.restore(state, next_anonymous_id=next_anonymous_id,
                           linearisation=linearisation)
        self.published.dirty = True
        self.checks.restore(state)
