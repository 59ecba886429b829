"""The estimator's input checks and refusal counts.

Before the filter sees an input it is checked: finite, dt ≥ 0, a well-formed batch
(:func:`~slamlens.services.slam.plausibility.checked_batch`) and inside the plausibility
bounds (:class:`~slamlens.services.slam.plausibility.InputGates`). What is refused, here or
later by the filter's guard, the innovation gate or an S that is not positive definite, is
counted by reason and the last refusal kept (docs/estimator.md); the counts are the
``diagnostics`` every state carries and a checkpoint puts back. No I/O.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Mapping
from typing import Any

from slamlens.common.errors import EstimationError
from slamlens.common.messages import SlamState
from slamlens.services.slam.observe_report import Refusal
from slamlens.services.slam.plausibility import (
    Bounds,
    ImplausibleInputError,
    InputGates,
    checked_batch,
    describe_batch,
)
from slamlens.services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")

Batch = tuple[list[int], list[float], list[float]]


def check_finite_inputs(**values: float) -> None:
    """Raise EstimationError naming the first non-finite value (NaN/inf would poison P)."""
    for name, value in values.items():
        if not math.isfinite(value):
            raise EstimationError(f"{name} must be finite, got {value!r}")


def odometry_text(v: float, w: float, dt: float) -> str:
    """An odometry input, abridged (:attr:`Refusal.input`)."""
    return f"odometry dt={dt!r} v={v!r} w={w!r}"


def observation_text(lid: int | None, z_r: float, z_b: float) -> str:
    """One observation, abridged (:attr:`Refusal.input`); ``lid`` None: anonymous."""
    who = "" if lid is None else f"id={lid} "
    return f"observation {who}range={z_r!r} bearing={z_b!r}"


class InputChecks:
    """The checks every input passes and what was refused, counted."""

    def __init__(self, settings: EstimatorSettings) -> None:
        self.gates = InputGates(Bounds(
            max_dt_s=settings.max_dt_s, max_speed=settings.max_speed,
            max_turn_rate=settings.max_turn_rate, max_range=settings.max_range,
            max_abs_bearing=settings.max_abs_bearing,
            max_stamp_jump_s=settings.max_stamp_jump_s, stamp_resync=settings.stamp_resync,
            max_batch=settings.max_batch, max_landmarks=settings.max_landmarks))
        self.refused_updates = 0  #: observations refused because S was not positive definite
        self.gated = 0  #: observations of known landmarks refused by the innovation gate
        #: inputs refused whole (plausibility reasons) and steps refused by the guard
        #: ("non-finite", "not-psd"), by reason
        self.refusals: Counter[str] = Counter()
        self.last_refusal: Refusal | None = None

    def odometry(self, *, v: float, w: float, dt: float, stamp: float) -> None:
        """Raise EstimationError for NaN or dt < 0, :class:`ImplausibleInputError`
        (counted) for a step outside a bound."""
        check_finite_inputs(v=v, w=w, dt=dt, stamp=stamp)
        if dt < 0:
            raise EstimationError(f"dt must be ≥ 0, got {dt!r}")
        try:
            self.gates.check_odometry(v=v, w=w, dt=dt, stamp=stamp)
        except ImplausibleInputError as exc:
            self.refuse(exc.reason, str(exc), stamp, odometry_text(v, w, dt))
            raise

    def batch(self, ids: Any, ranges: Any, bearings: Any, stamp: float, *,
              landmarks: int, index: Mapping[int, int]) -> Batch:
        """The batch as lists (ids, ranges, bearings); EstimationError if malformed,
        :class:`ImplausibleInputError` (counted) if outside a bound for a map of
        ``landmarks`` whose ids are ``index``'s keys."""
        id_list, range_list, bearing_list = checked_batch(ids, ranges, bearings, stamp)
        try:
            self.gates.check_batch(
                ranges=range_list, bearings=bearing_list, landmarks=landmarks, stamp=stamp,
                new_ids=len({i for i in id_list if i >= 0 and i not in index}))
        except ImplausibleInputError as exc:
            self.refuse(exc.reason, str(exc), stamp, describe_batch(
                id_list, range_list, bearing_list))
            raise
        return id_list, range_list, bearing_list

    def applied(self, stamp: float) -> None:
        """An input with ``stamp`` was applied (the stamp-jump gate's reference)."""
        self.gates.applied(stamp)

    def refuse(self, reason: str, detail: str, stamp: float, what: str) -> None:
        """Count a refusal by ``reason`` and keep it as the last one."""
        self.refusals[reason] += 1
        self.last_refusal = Refusal(reason=reason, detail=detail, stamp=stamp, input=what)

    def singular(self, lid: int, exc: Exception) -> None:
        """Count an observation not applied because S was not positive definite."""
        self.refused_updates += 1
        count = self.refused_updates
        if count == 1 or count % 100 == 0:  # a broken P refuses every update: do not flood
            log.warning("observation of landmark %d not applied (%d so far): %s", lid, count, exc)

    def diagnostics(self) -> dict[str, float]:
        """``gated``, ``refused_updates`` and ``refused.<reason>`` per reason."""
        out = {"gated": float(self.gated), "refused_updates": float(self.refused_updates)}
        for reason, count in sorted(self.refusals.items()):
            out[f"refused.{reason}"] = float(count)
        return out

    def restore(self, state: SlamState) -> None:
        """Continue the counts and the stamp gate from a checkpointed ``state``."""
        self.gates.restore(None if state.step == "init" else
                           float(state.input_stamp if state.input_stamp is not None
                                 else state.stamp))
        counts = state.diagnostics or {}
        self.gated = int(counts.get("gated", 0))
        self.refused_updates = int(counts.get("refused_updates", 0))
        self.refusals = Counter({k.partition(".")[2]: int(v) for k, v in counts.items()
                                 if k.startswith("refused.")})
