"""Planted programming faults, for demonstrations and for testing the monitor (docs/simulator.md).

A fault acts only on the features whose ids are listed (``--faulty-features``) and only on
events whose stamp is ≥ ``onset`` (s). With no fault the estimator never calls this module:
the correct filter runs exactly as written in :mod:`slamlens.services.slam.ekf`.

``map-update`` (paper §4: "the covariance of certain mapped features is updated incorrectly")
    After every observation batch that updated at least one landmark, each faulty feature's
    own 2×2 block P_ff receives spurious extra uncertainty ``magnitude``·I (m², default
    2e-3). P stays PSD (a PSD term is added), pairs without a faulty feature are not touched
    by the fault, so their P_d keeps shrinking; every pair with a faulty feature gains
    ``magnitude``·I in P_d at each such batch, which outgrows what the batch's observations
    remove whenever the faulty feature is not (well) observed.

``cross-covariance`` (a fault in the prediction step)
    The robot–feature cross-covariance P_v,f of each faulty feature is not propagated:
    P_v,f ← P_v,f + (1 − magnitude)·(Fx P_v,f − P_v,f), so with the default magnitude 1.0 it
    stays P_v,f where the model says Fx·P_v,f. A monitor that compares two consecutive
    states around a predict sees, for the faulty features only, P_v,f(after) ≠ Fx·P_v,f(before)
    with Fx = [[1, 0, −Δy], [0, 1, Δx], [0, 0, 1]] from the pose change (Δx, Δy): the x and y
    rows miss −Δy·P_θ,f and +Δx·P_θ,f (the θ row is right either way). Nothing shows while
    the robot stands still or while P_θ,f = 0. P_mm and P_vv are as the correct filter's.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from slamlens.common.errors import ConfigError
from slamlens.services.slam import ekf
from slamlens.services.slam.settings import (
    CROSS_COVARIANCE,
    FAULT_KINDS,
    MAP_UPDATE,
    NONE,
    check_fault,
)

DEFAULT_MAGNITUDE = {
    MAP_UPDATE: 2e-3,  # m² per update batch: σ grows ~4.5 cm in 1 s of 10 Hz batches
    CROSS_COVARIANCE: 1.0,  # fraction of the propagation Fx·P_v,f − P_v,f left out
}


@dataclass(frozen=True)
class PlantedFault:
    """One configured fault (see the module docstring for what each kind does)."""

    kind: str
    feature_ids: frozenset[int]
    magnitude: float
    onset: float = 0.0  #: s; the fault acts on events with stamp ≥ onset

    def __post_init__(self) -> None:
        if self.kind == NONE:
            raise ConfigError(f"unknown fault kind {self.kind!r}; one of {FAULT_KINDS[1:]}")
        check_fault(self.kind, tuple(self.feature_ids), self.magnitude)

    def active(self, stamp: float) -> bool:
        return stamp >= self.onset


def make_fault(kind: str, feature_ids: Iterable[int], *, magnitude: float | None,
               onset: float) -> PlantedFault | None:
    """The fault to plant, or None for ``"none"``; ``magnitude`` None = the kind's default."""
    if kind == NONE:
        return None
    if kind not in FAULT_KINDS:
        raise ConfigError(f"unknown fault kind {kind!r}; one of {FAULT_KINDS}")
    size = DEFAULT_MAGNITUDE[kind] if magnitude is None else float(magnitude)
    return PlantedFault(kind, frozenset(int(i) for i in feature_ids), size, float(onset))


def _state_rows(indices: Iterable[int]) -> np.ndarray:
    return np.array([r for j in indices for r in (3 + 2 * j, 4 + 2 * j)], dtype=np.intp)


def predict_without_cross_covariance(x: np.ndarray, L: np.ndarray, n: int, *,
                                     indices: Iterable[int], fraction: float, v: float,
                                     w: float, dt: float, var_v: float, var_w: float,
                                     extra_qv: float = 0.0, extra_qw: float = 0.0,
                                     guard: ekf.Guard | None = None,
                                     ws: ekf.Workspace | None = None,
                                     at: tuple[float, float] | None = None) -> None:
    """:func:`ekf.predict` with P_v,f of the landmarks ``indices`` (state order) not
    propagated (``fraction`` 1) or only partly (``fraction`` in (0, 1))."""
    rows = _state_rows(indices)
    saved = L[rows, 0:3].copy()  # P_f,v before (lower storage: rows of f, robot columns)
    ekf.predict(x, L, n, v=v, w=w, dt=dt, var_v=var_v, var_w=var_w, extra_qv=extra_qv,
                extra_qw=extra_qw, guard=guard, ws=ws, at=at)
    if rows.size:
        L[rows, 0:3] = fraction * saved + (1.0 - fraction) * L[rows, 0:3]


def inflate_map_covariance(L: np.ndarray, indices: Iterable[int], magnitude: float) -> None:
    """P_ff += magnitude·I for each landmark index in ``indices`` (the map-update fault)."""
    for j in indices:
        a = 3 + 2 * j
        L[a, a] += magnitude
        L[a + 1, a + 1] += magnitude
