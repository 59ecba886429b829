"""What one observation batch did: :class:`ObserveReport` (the estimator's answer to
``observe``) and :class:`BatchRecord`, which collects it observation by observation; and
:class:`Refusal`, the last input the estimator refused. Plain values, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class ObserveReport:
    """What one observation batch did (arrays are read-only)."""

    observed_ids: np.ndarray  #: int64, landmarks updated or initialised, message order, once
    new_ids: np.ndarray  #: int64, landmarks initialised by this batch
    innovation_ids: np.ndarray  #: int64[k], the landmark of each update, in order
    innovations: np.ndarray  #: float64[k, 2], ν = z − h (m, rad) before each update
    innovation_covariances: np.ndarray  #: float64[k, 2, 2], S of each update
    assigned_ids: np.ndarray  #: int64[m], per observation: the id it was applied to, or −1
    rejected: int  #: observations not applied (ambiguous, gated, S not PD, refused, map full)
    ambiguous: int  #: of those, id −1 observations between the two association thresholds
    gated_ids: np.ndarray | None = None  #: int64[g], landmarks of the gated observations
    gated_observations: np.ndarray | None = None  #: float64[g, 2], their (range m, bearing)
    gated_nis: np.ndarray | None = None  #: float64[g], their NIS νᵀS⁻¹ν
    refused: int = 0  #: of the rejected, observations the guard refused (would poison P)

    @property
    def gated(self) -> int:
        """Observations of known landmarks not applied because their NIS was above the gate."""
        return 0 if self.gated_ids is None else int(self.gated_ids.shape[0])

    def state_fields(self, *, innovations: bool) -> dict[str, Any]:
        """The :class:`~slamlens.common.messages.SlamState` fields this batch fills: the ids
        observed and new, the gated observations if any, and with ``innovations`` each
        update's ν and S."""
        out: dict[str, Any] = {"observed_ids": self.observed_ids, "new_ids": self.new_ids}
        if innovations:
            out["innovation_ids"] = self.innovation_ids
            out["innovations"] = self.innovations
            out["innovation_covariances"] = self.innovation_covariances
        if self.gated:
            out["gated_ids"] = self.gated_ids
            out["gated_observations"] = self.gated_observations
            out["gated_nis"] = self.gated_nis
        return out


@dataclass(frozen=True)
class Refusal:
    """The last input (or step) the estimator refused, and why (for logs and status)."""

    #: a plausibility reason (slamlens.services.slam.plausibility) or non-finite / not-psd
    reason: str
    detail: str  #: one sentence
    stamp: float  #: the input's stamp
    input: str  #: the input, abridged


def _frozen(values: Any, dtype: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    a = np.array(values, dtype=dtype)
    if shape is not None:
        a = a.reshape(shape)
    a.flags.writeable = False
    return a


@dataclass
class BatchRecord:
    """What one observation batch did so far (collected by
    :class:`~slamlens.services.slam.observe_batch.BatchApplier`)."""

    observed: list[int] = field(default_factory=list)
    new: list[int] = field(default_factory=list)
    innovation_ids: list[int] = field(default_factory=list)
    innovations: list[tuple[float, float]] = field(default_factory=list)
    covariances: list[tuple[float, float, float, float]] = field(default_factory=list)
    assigned: list[int] = field(default_factory=list)
    gated: list[tuple[int, float, float, float]] = field(default_factory=list)
    rejected: int = 0
    ambiguous: int = 0
    refused: int = 0
    #: FEJ: new landmarks held to the batch's end: id → sightings (range, bearing, var_r)
    unmapped: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)

    def hold_new(self, lid: int, z_r: float, z_b: float, var_r: float) -> None:
        """A sighting of a landmark to be mapped at the batch's end (FEJ)."""
        self.unmapped.setdefault(lid, []).append((z_r, z_b, var_r))
        self.assigned.append(lid)
        if lid not in self.observed:
            self.observed.append(lid)

    def drop_new(self, lid: int, *, refused: bool) -> None:
        """A held new landmark that could not be mapped: its sightings not applied."""
        k = len(self.unmapped.get(lid, ()))
        self.assigned = [-1 if a == lid else a for a in self.assigned]
        self.observed = [o for o in self.observed if o != lid]
        self.rejected += k
        self.refused += k if refused else 0

    def report(self) -> ObserveReport:
        k, g = len(self.innovation_ids), len(self.gated)
        return ObserveReport(
            observed_ids=_frozen(self.observed, np.int64), new_ids=_frozen(self.new, np.int64),
            innovation_ids=_frozen(self.innovation_ids, np.int64),
            innovations=_frozen(self.innovations, np.float64, (k, 2)),
            innovation_covariances=_frozen(self.covariances, np.float64, (k, 2, 2)),
            assigned_ids=_frozen(self.assigned, np.int64), rejected=self.rejected,
            ambiguous=self.ambiguous,
            gated_ids=_frozen([e[0] for e in self.gated], np.int64) if g else None,
            gated_observations=_frozen([e[1:3] for e in self.gated], np.float64, (g, 2))
            if g else None,
            gated_nis=_frozen([e[3] for e in self.gated], np.float64) if g else None,
            refused=self.refused)
