"""One observation batch applied to the map, one observation at a time in message order
(docs/estimator.md).

A known id updates, an unknown id is mapped, id −1 is associated first
(:mod:`slamlens.services.slam.association`: a landmark's id, a fresh one, or not applied).
With FEJ, OC and the invariant EKF a batch's new landmarks are mapped after its updates,
several sightings of one fused (:func:`~slamlens.services.slam.linearisation.fused`). What
each observation did goes into a :class:`~slamlens.services.slam.observe_report.BatchRecord`;
what was not applied is counted (:class:`~slamlens.services.slam.input_checks.InputChecks`). No I/O.
"""

from __future__ import annotations

import logging

from slamlens.services.slam import association, ekf, ekf_invariant
from slamlens.services.slam.input_checks import InputChecks, observation_text
from slamlens.services.slam.linearisation import fused
from slamlens.services.slam.noise_model import NoiseModel
from slamlens.services.slam.observe_report import BatchRecord
from slamlens.services.slam.state_store import StateStore

log = logging.getLogger("slamlens.estimator")


class BatchApplier:
    """Applies observation batches to ``store``'s map with the model's noise."""

    def __init__(self, store: StateStore, checks: InputChecks, noise: NoiseModel, *,
                 gates: association.Gates, innovation_gate: float, guard: ekf.Guard,
                 iterations: int = 1) -> None:
        self.store = store
        self.checks = checks
        self.noise = noise
        self.gates = gates  #: the association thresholds
        self.innovation_gate = innovation_gate  #: χ² on a known landmark's NIS
        self.guard = guard
        self.iterations = iterations  #: Gauss-Newton steps of each update (iterated EKF)

    def apply(self, ids: list[int], ranges: list[float], bearings: list[float],
              stamp: float) -> BatchRecord:
        """Apply a checked batch; what it did. P is whole again on return (flushed)."""
        batch = BatchRecord()
        try:
            for lid, z_r, z_b in zip(ids, ranges, bearings, strict=True):
                self._observe_one(batch, lid, z_r, z_b, stamp)
            if batch.unmapped:
                self._map_unmapped(batch, stamp)
        finally:
            self.store.flush()  # the batch's updates are in x; their downdates held back
        return batch

    def _observe_one(self, batch: BatchRecord, lid: int, z_r: float, z_b: float,
                     stamp: float) -> None:
        """One observation of a batch: associated if anonymous, then an update or a new
        landmark; what happened goes into ``batch``."""
        store = self.store
        var_r = self.noise.range_variance(z_r, z_b)
        if lid == -1:
            found = self._associate(batch, z_r, z_b, var_r, stamp)
            if found is None:
                batch.assigned.append(-1)
                return
            lid = found
        j = store.index.get(lid)
        if j is None and store.holds_new:
            batch.hold_new(lid, z_r, z_b, var_r)  # mapped after the batch's updates
            return
        try:
            if j is None:
                store.initialise(lid, z_r, z_b, var_range=var_r, var_bearing=self.noise.var_b,
                                 guard=self.guard)
                batch.new.append(lid)
            elif store.invariant:
                out = ekf_invariant.update(
                    store.x, store.L, store.n, j, z_range=z_r, z_bearing=z_b, var_range=var_r,
                    var_bearing=self.noise.var_b, ws=store.ws, gate=self.innovation_gate,
                    guard=self.guard)
            else:
                out = ekf.update(store.x, store.L, store.n, j, z_range=z_r, z_bearing=z_b,
                                 var_range=var_r, var_bearing=self.noise.var_b, ws=store.ws,
                                 gate=self.innovation_gate, guard=self.guard, defer=True,
                                 iterations=self.iterations,
                                 **store.linearisation(j))
        except ekf.GatedObservationError as exc:
            self.checks.gated += 1
            batch.gated.append((lid, z_r, z_b, exc.nis))
            self._not_applied(batch)
            return
        except ekf.RefusedStepError as exc:  # the guard: an update or a new landmark
            self.checks.refuse(exc.reason, str(exc), stamp, observation_text(lid, z_r, z_b))
            batch.refused += 1
            self._not_applied(batch)
            return
        except ekf.SingularInnovationError as exc:
            self.checks.singular(lid, exc)
            self._not_applied(batch)
            return
        if j is not None:
            nu_r, nu_b, s00, s01, s11 = out
            batch.innovation_ids.append(lid)
            batch.innovations.append((nu_r, nu_b))
            batch.covariances.append((s00, s01, s01, s11))
        batch.assigned.append(lid)
        if lid not in batch.observed:
            batch.observed.append(lid)

    @staticmethod
    def _not_applied(batch: BatchRecord) -> None:
        batch.rejected += 1
        batch.assigned.append(-1)

    def _map_unmapped(self, batch: BatchRecord, stamp: float) -> None:
        """The batch's new landmarks, mapped after its updates (FEJ: so that no update of
        the batch moves them — a state publishes a new landmark at its first estimate, which
        a monitor takes as its linearisation point; the invariant EKF: so that no update's
        retraction moves them); sightings of one landmark fused."""
        for lid, sightings in batch.unmapped.items():
            z_r, z_b, var_r, var_b = fused(sightings, self.noise.var_b)
            try:
                self.store.initialise(lid, z_r, z_b, var_range=var_r, var_bearing=var_b,
                                      guard=self.guard)
            except ekf.RefusedStepError as exc:
                self.checks.refuse(exc.reason, str(exc), stamp,
                                   observation_text(lid, z_r, z_b))
                batch.drop_new(lid, refused=True)
                continue
            batch.new.append(lid)

    def _associate(self, batch: BatchRecord, z_r: float, z_b: float, var_r: float,
                   stamp: float) -> int | None:
        """The id an anonymous observation is (a landmark's, or a fresh one for a new
        landmark), or None when it is not applied (ambiguous, or the map is full)."""
        store = self.store
        store.flush()  # association reads P
        decision = association.decide(association.mahalanobis_all(
            store.x, store.L, store.n, z_range=z_r, z_bearing=z_b, var_range=var_r,
            var_bearing=self.noise.var_b), self.gates)
        if decision.kind == association.AMBIGUOUS:
            log.debug("anonymous observation (%.3f m, %.3f rad) ambiguous: d² = %.2f",
                      z_r, z_b, decision.d2)
            batch.rejected += 1
            batch.ambiguous += 1
            return None
        if decision.kind != association.MATCH and self.checks.gates.map_full(store.n):
            self.checks.refuse("map_size", f"the map holds {store.n} landmarks, the bound: "
                               "an anonymous observation was not mapped",
                               stamp, observation_text(None, z_r, z_b))
            batch.rejected += 1
            return None
        return (store.ids[decision.index] if decision.kind == association.MATCH
                else store.fresh_anonymous_id())
