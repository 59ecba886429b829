"""Plausibility gates on the estimator's inputs (docs/estimator.md).

A well-formed message can still be absurd: ``dt = 1e200``, a range of 1e300 m, a batch of a
thousand new landmarks. Each gate has a documented bound in SI units
(:class:`~slamlens.services.slam.settings.EstimatorSettings`, group "plausibility gates"; 0 turns a
bound off). An input outside any bound is refused *whole* before the filter sees it:
:class:`ImplausibleInputError` names the reason, the estimator counts it by reason and the
service logs the first of each reason and publishes no state for it.

Reasons: ``dt``, ``speed``, ``turn_rate``, ``range``, ``bearing``, ``stamp_jump``,
``batch_size``, ``map_size``.

Stamp jumps: an input stamped more than ``max_stamp_jump_s`` away (either way) from the
newest input applied is refused. A robot whose clock really jumped (a reboot, a replay
started again) would then be refused for ever, so after ``stamp_resync`` consecutive inputs
refused for a jump, each within the bound of the one before, the gate accepts the new clock
(logged by the service as a resync). No I/O here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from slamlens.common.errors import EstimationError

REASONS = ("dt", "speed", "turn_rate", "range", "bearing", "stamp_jump", "batch_size",
           "map_size")


class ImplausibleInputError(EstimationError):
    """An input outside a plausibility bound; refused whole, nothing applied."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason  #: one of :data:`REASONS`


@dataclass(frozen=True)
class Bounds:
    """The bounds (0 = no bound). Built from the estimator's settings."""

    max_dt_s: float = 10.0
    max_speed: float = 10.0
    max_turn_rate: float = 10.0
    max_range: float = 100.0
    max_abs_bearing: float = 2 * math.pi
    max_stamp_jump_s: float = 60.0
    stamp_resync: int = 20
    max_batch: int = 500
    max_landmarks: int = 2000


class InputGates:
    """Checks inputs against :class:`Bounds`; remembers the newest stamp applied."""

    def __init__(self, bounds: Bounds) -> None:
        self.bounds = bounds
        self.last_stamp: float | None = None  #: stamp of the newest input applied
        self._jumped: list[float] = []  #: stamps of consecutive inputs refused for a jump
        self.resyncs = 0  #: times the gate accepted a new clock

    # -- the checks ----------------------------------------------------------------
    def check_odometry(self, *, v: float, w: float, dt: float, stamp: float) -> None:
        """Raise :class:`ImplausibleInputError` if one odometry input is outside a bound."""
        b = self.bounds
        if b.max_dt_s and dt > b.max_dt_s:
            raise ImplausibleInputError("dt", f"dt {dt!r} s above the bound {b.max_dt_s:g} s")
        if b.max_speed and abs(v) > b.max_speed:
            raise ImplausibleInputError("speed", f"speed {v!r} m/s beyond ±{b.max_speed:g} m/s")
        if b.max_turn_rate and abs(w) > b.max_turn_rate:
            raise ImplausibleInputError("turn_rate", f"turn rate {w!r} rad/s beyond "
                                                     f"±{b.max_turn_rate:g} rad/s")
        self._check_stamp(stamp)

    def check_batch(self, *, ranges: list[float], bearings: list[float], new_ids: int,
                    landmarks: int, stamp: float) -> None:
        """Raise :class:`ImplausibleInputError` if an observation batch is outside a bound.

        ``new_ids`` is the number of distinct known ids in the batch that are not in the
        map yet, ``landmarks`` the map's size now.
        """
        b = self.bounds
        k = len(ranges)
        if b.max_batch and k > b.max_batch:
            raise ImplausibleInputError("batch_size", f"{k} observations in one batch, above "
                                                      f"the bound {b.max_batch}")
        if k:
            if b.max_range and max(ranges) > b.max_range:
                raise ImplausibleInputError("range", f"range {max(ranges)!r} m above the bound "
                                                     f"{b.max_range:g} m")
            worst = max(max(bearings), -min(bearings))
            if b.max_abs_bearing and worst > b.max_abs_bearing:
                raise ImplausibleInputError("bearing", f"bearing ±{worst!r} rad beyond "
                                                       f"±{b.max_abs_bearing:g} rad")
        if b.max_landmarks and landmarks + new_ids > b.max_landmarks:
            raise ImplausibleInputError("map_size", f"{new_ids} new landmarks would take the "
                                                    f"map to {landmarks + new_ids}, above the "
                                                    f"bound {b.max_landmarks}")
        self._check_stamp(stamp)

    def map_full(self, landmarks: int) -> bool:
        """Whether one more landmark (found by association) would exceed the map bound."""
        return bool(self.bounds.max_landmarks) and landmarks >= self.bounds.max_landmarks

    def _check_stamp(self, stamp: float) -> None:
        b = self.bounds
        last = self.last_stamp
        if not b.max_stamp_jump_s or last is None or abs(stamp - last) <= b.max_stamp_jump_s:
            return
        run = self._jumped
        if run and abs(stamp - run[-1]) > b.max_stamp_jump_s:
            run.clear()  # not the same new clock as the inputs refused before
        run.append(stamp)
        if b.stamp_resync and len(run) >= b.stamp_resync:
            run.clear()
            self.resyncs += 1
            return  # the clock really jumped: accept it from this input on
        raise ImplausibleInputError("stamp_jump", f"stamp {stamp!r} s is {stamp - last:+.6g} s "
                                                  f"from the newest input applied, beyond "
                                                  f"±{b.max_stamp_jump_s:g} s")

    # -- bookkeeping -----------------------------------------------------------------
    def applied(self, stamp: float) -> None:
        """An input with ``stamp`` was applied: the reference of the stamp-jump gate."""
        self.last_stamp = stamp
        self._jumped.clear()

    def restore(self, last_stamp: float | None) -> None:
        """Continue from a checkpoint whose newest input had ``last_stamp``."""
        self.last_stamp = last_stamp
        self._jumped.clear()


def checked_batch(ids: Any, ranges: Any, bearings: Any,
                 stamp: float) -> tuple[list[int], list[float], list[float]]:
    """Validated plain lists (the loop runs on Python scalars; builtins over small
    lists are cheaper than a numpy call per check)."""
    if not math.isfinite(stamp):
        raise EstimationError(f"stamp must be finite, got {stamp!r}")
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


def describe_batch(ids: list[int], ranges: list[float], bearings: list[float]) -> str:
    """A batch, abridged, for a refusal's record."""
    head = ", ".join(f"{i}:({r:.6g} m, {b:.6g} rad)"
                     for i, r, b in zip(ids[:3], ranges[:3], bearings[:3], strict=True))
    more = f" … ({len(ids)} in all)" if len(ids) > 3 else ""
    return f"observations [{head}{more}]"
